"""What a comparison could have found: the spread of its per-seed log ratios (spread) and the
smallest loss ratio its design finds with probability POWER (detectable_ratio, seeds_for_ratio)."""

from __future__ import annotations

import functools
import math

import numpy as np

from physgrad.replication import majority
from physgrad.verdict import (
    ALPHA,
    CONFIDENCE,
    LOG_CAP,
    MARGIN,
    Paired,
    PairVerdict,
    seeds_needed,
)

POWER = 0.8  # the chance of finding an effect that "detectable" promises


def spread(p: Paired) -> float:
    """The spread of a comparison's per-seed log ratios: 1.4826 x their median absolute deviation
    (the standard deviation where they are normal, robust to a few wild seeds), over the pairs
    where neither side diverged; NaN with fewer than 3 such pairs."""
    finite = np.array([r for r in p.log_ratios if not math.isnan(r) and abs(r) < LOG_CAP])
    if finite.size < 3:
        return math.nan
    return float(1.4826 * np.median(np.abs(finite - np.median(finite))))


def measured(verdict: PairVerdict, fraction: float = 1.0) -> tuple[float, float, float, float]:
    """What a pair's studies measured at `fraction` of the budget, for detectable_ratio: the
    spread of the seeds' log ratios (1.4826 x the median absolute deviation of every study's finite
    log ratios about that study's median, so that the studies' offsets do not count as seed noise),
    the spread between the studies (the standard deviation of their medians less what the seeds'
    noise gives them, sd x sqrt(pi / 2) / sqrt(n); 0 with one study or none beyond it) and the rate
    at which runs diverged (both variants' divergences over both variants' runs)."""
    studies = [s.at[fraction] for s in (verdict.studies or [verdict])]
    centred, medians, pairs = [], [], []
    for p in studies:
        finite = np.array([r for r in p.log_ratios if not math.isnan(r) and abs(r) < LOG_CAP])
        if finite.size:
            centred.extend(finite - np.median(finite))
            medians.append(float(np.median(finite)))
            pairs.append(finite.size)
    if len(centred) < 3:
        return math.nan, math.nan, math.nan, math.nan
    sd = float(1.4826 * np.median(np.abs(np.array(centred))))
    between = 0.0
    if len(medians) > 1:
        noise = sd**2 * (math.pi / 2) / float(np.mean(pairs))
        between = math.sqrt(max(0.0, float(np.var(medians, ddof=1)) - noise))
    runs = sum(p.seeds for p in studies)
    rates = sorted(
        sum(getattr(p, side) for p in studies) / runs if runs else 0.0
        for side in ("diverged_a", "diverged_b")
    )
    return sd, between, rates[0], rates[1]


@functools.lru_cache(maxsize=1024)
def wrong_side_allowed(seeds: int, comparisons: int = 1, alpha: float = ALPHA) -> int:
    """The most pairs of `seeds` on which the better variant diverged (log ratio +-LOG_CAP on the
    wrong side) that still let a study find it better, at best (every other pair on its side): the
    signed-rank test's two-sided p with those pairs at the top ranks below alpha / comparisons
    (Holm's strictest step), and the percentile bootstrap interval of the median finite (fewer than
    ceil(seeds / 2) of them in a resample with probability above 1 - (1 - CONFIDENCE) / 2); -1
    where not even none does."""
    from scipy.stats import binom

    from physgrad.paired_stats import _wilcoxon

    allowed = -1
    for wrong in range(seeds + 1):
        r = np.array([-(k + 1.0) for k in range(seeds - wrong)] + [LOG_CAP] * wrong)
        p = min(1.0, 2 * _wilcoxon(r, "less"))
        capped = binom.sf(math.ceil(seeds / 2) - 1, seeds, wrong / seeds) if seeds else 1.0
        if p >= alpha / comparisons or capped > (1 - CONFIDENCE) / 2:
            break
        allowed = wrong
    return allowed


def power_at(
    ratio: float,
    sd: float,
    seeds: int,
    comparisons: int = 1,
    studies: int = 1,
    need: int | None = None,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    divergence: float = 0.0,
    between: float = 0.0,
    study_alpha: float | None = None,
    divergence_other: float | None = None,
) -> float:
    """The chance that a design finds a true loss ratio `ratio` (above 1: B worse) "better", by a
    normal model of the whole rule. Per study: the pairs where neither run diverged, seeds x (1
    - divergence) (1 - divergence_other), carry log ratios of spread sd around log(ratio) plus
    the study's offset (the tuning's luck, N(0, between^2)); the signed-rank test at Holm's
    strictest step (efficiency 3 / pi of the t test) and the median's interval beyond the margin
    (standard error sd x sqrt(pi / 2) / sqrt(n)) must both pass, each a normal probability
    averaged over the offset; and the better variant (diverging at the rate `divergence`, the
    other at `divergence_other`, the same where None) may have diverged on at most
    wrong_side_allowed pairs (each pair one-sided that way with probability divergence x (1 -
    divergence_other)). Over the studies: `need` of `studies` pass (binomial) and, with several
    studies, the studies as draws (replication.between_studies) exclude a ratio of 1 at
    study_alpha: a noncentral t with studies - 1 degrees of freedom. The two are taken as
    independent (they are positively correlated), so the chance is on the low side."""
    from scipy.stats import binom, nct, norm

    from physgrad.replication import STUDY_ALPHA

    study_alpha = STUDY_ALPHA if study_alpha is None else study_alpha
    if ratio <= margin or seeds < seeds_needed(alpha, comparisons):
        return 0.0
    need = need or majority(studies)
    other = divergence if divergence_other is None else divergence_other
    finite = seeds * (1.0 - divergence) * (1.0 - other)
    if finite < 1:
        return 0.0
    mu, delta = math.log(ratio), math.log(margin)
    test_error = sd * math.sqrt(math.pi / 3) / math.sqrt(finite)
    median_error = sd * math.sqrt(math.pi / 2) / math.sqrt(finite)
    z_test = _quantile("norm", 1 - alpha / (2 * comparisons))
    z_interval = _quantile("norm", 1 - (1 - CONFIDENCE) / 2)
    # each study's chance, averaged over its offset by Gauss-Hermite quadrature
    nodes, weights = _hermite_rule()
    shifted = mu + between * nodes
    test = norm.cdf((shifted / max(test_error, 1e-300)) - z_test)
    interval = norm.cdf(((shifted - delta) / max(median_error, 1e-300)) - z_interval)
    one = float(np.sum(weights * np.minimum(test, interval)) / np.sum(weights))
    allowed = wrong_side_allowed(seeds, comparisons, alpha)
    one *= float(binom.cdf(allowed, seeds, divergence * (1 - other))) if allowed >= 0 else 0
    chance = float(binom.sf(need - 1, studies, one))
    if studies > 1:
        spread_of_mean = math.sqrt((median_error**2 + between**2) / studies)
        critical = _quantile("t", 1 - study_alpha / 2, studies - 1)
        # a noncentrality past 100 finds it surely (scipy's nct loses its accuracy far out)
        if spread_of_mean > 0 and mu / spread_of_mean < 100:
            chance *= float(nct.sf(critical, studies - 1, mu / spread_of_mean))
    return chance


@functools.lru_cache(maxsize=1)
def _hermite_rule() -> tuple[np.ndarray, np.ndarray]:
    """The 24-point Gauss-Hermite rule (probabilists'), computed once: a detectable ratio's
    bisection asks power_at for it some fifty times."""
    return np.polynomial.hermite_e.hermegauss(24)


@functools.lru_cache(maxsize=256)
def _quantile(distribution: str, q: float, df: int | None = None) -> float:
    """The q quantile of the standard normal ("norm") or of Student's t with df degrees of
    freedom ("t"), kept: power_at asks for the same few many times, and SciPy's call costs
    about 0.1 ms."""
    from scipy.stats import norm
    from scipy.stats import t as student

    return float(norm.ppf(q) if distribution == "norm" else student.ppf(q, df))


def detectable_ratio(
    sd: float,
    seeds: int,
    comparisons: int = 1,
    studies: int = 1,
    need: int | None = None,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    power: float = POWER,
    divergence: float = 0.0,
    between: float = 0.0,
    divergence_other: float | None = None,
) -> float:
    """The smallest loss ratio (above the margin) that the design finds with probability `power`
    (power_at, solved by bisection in the log ratio): for log ratios of spread sd on `seeds` paired
    seeds per study, `comparisons` comparisons, `need` of `studies` tuning studies, the better
    variant's runs diverging at the rate `divergence` and the other's at `divergence_other` (the
    same where None), and the studies' offsets of spread `between`.
    Infinite where no ratio reaches it (too few seeds, or divergences too frequent), NaN without a
    spread; the margin itself where sd and between are 0 (every ratio above it is found, the
    margin itself never: "better" is strictly beyond it)."""
    if math.isnan(sd) or math.isnan(between) or math.isnan(divergence):
        return math.nan
    rule = dict(
        seeds=seeds,
        comparisons=comparisons,
        studies=studies,
        need=need,
        margin=margin,
        alpha=alpha,
        divergence=divergence,
        between=between,
        divergence_other=divergence_other,
    )
    if sd == 0 and between == 0:
        return margin if power_at(margin * 1.001, 1e-12, **rule) >= power else math.inf
    low, high = math.log(margin), math.log(margin) + 1.0
    while power_at(math.exp(high), sd, **rule) < power:
        high = 2 * high
        if high > 700:
            return math.inf
    for _ in range(50):
        middle = (low + high) / 2
        if power_at(math.exp(middle), sd, **rule) < power:
            low = middle
        else:
            high = middle
    return math.exp(high)


def seeds_for_ratio(ratio: float, sd: float, comparisons: int = 1, studies: int = 1, **rule) -> int:
    """The fewest paired seeds per study with which detectable_ratio reaches `ratio` (at most
    10,000; 0 where a ratio within the margin can never be "better")."""
    margin = rule.get("margin", MARGIN)
    if ratio <= margin:
        return 0
    for seeds in range(1, 10_001):
        if detectable_ratio(sd, seeds, comparisons, studies, **rule) <= ratio:
            return seeds
    return 0
