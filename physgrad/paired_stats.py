"""The paired statistics of the verdict rule (physgrad.verdict): per seed the log ratio of two
variants' losses at a budget, with divergence and tiny losses mapped onto it; the median with a
percentile bootstrap interval; one-sided Wilcoxon signed-rank tests (exact up to EXACT_PAIRS pairs)
for a difference and two one-sided ones for equivalence; Holm's correction."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

MARGIN = 1.1  # "better" means at least 10% lower; "equivalent" means within 10%
CONFIDENCE = 0.95
RESAMPLES = 10_000
# |log ratio| standing for "one side diverged": beyond every finite log ratio of float64 losses
# (< 1500), and far enough that its average with any of them (a median of an even count) is too
LOG_CAP = 1e4

# one floor for tiny losses: every loss below float32's smallest normal number (1.2e-38, which a
# float32 run cannot tell from 0) counts as that number, so losses under it tie whatever their
# precision (1e-320 against 1e-310, or 0 against 1e-39), and a loss of 0 beats a positive one above
# it by a finite ratio (0 against 1e-30: 1.2e-8), which reads as a ratio, not as a divergence
LOSS_FLOOR = float(np.finfo(np.float32).tiny)


def log_ratio(a: float, b: float) -> float:
    """log(a / b) for two losses at a budget (inf: diverged; NaN: missing or negative): NaN if
    either is missing or below 0 (a signed loss has no ratio); 0 if both diverged; +-LOG_CAP if one
    side diverged; a loss below LOSS_FLOOR (0 included) counts as LOSS_FLOOR."""
    if math.isnan(a) or math.isnan(b) or a < 0 or b < 0:
        return math.nan
    if math.isinf(a) and math.isinf(b):
        return 0.0
    if math.isinf(a):
        return LOG_CAP
    if math.isinf(b):
        return -LOG_CAP
    return float(np.clip(math.log(max(a, LOSS_FLOOR) / max(b, LOSS_FLOOR)), -LOG_CAP, LOG_CAP))


def snap(log_value: float, log_ratios: np.ndarray) -> float:
    """A median or interval end of log_ratios that lies beyond every finite one (|value| above the
    largest |ratio| short of LOG_CAP) can only come from a diverged side's +-LOG_CAP, averaged with
    a finite ratio (a median of an even count) or interpolated towards one (a bootstrap
    percentile): it is reported as the divergence, +-LOG_CAP, not as a ratio of e^300."""
    size = np.abs(np.asarray(log_ratios, float))
    finite = size[size < LOG_CAP]
    bound = float(finite.max()) if finite.size else 0.0
    return math.copysign(LOG_CAP, log_value) if abs(log_value) > bound else log_value


def ratio_of(log_value: float) -> float:
    """exp(log_value), with a log ratio past what float64 holds (+-LOG_CAP: one side diverged) as
    0 or infinity; NaN stays NaN."""
    if math.isnan(log_value):
        return math.nan
    return math.exp(log_value) if abs(log_value) < 700 else (0.0 if log_value < 0 else math.inf)


EXACT_PAIRS = (
    13  # up to here the signed-rank test enumerates all 2^n sign flips (scipy's own limit)
)


def _exact_signed_rank(r: np.ndarray, alternative: str) -> float:
    """The exact one-sided p of W+ (zeros split) over all 2^n sign flips of r, the enumeration
    scipy.stats.wilcoxon makes (one call 0.6 s with ties or zeros), as a distribution: the flips
    leave a zero's half rank in W+ and add each nonzero value's rank with probability 1/2, so W+
    minus the zeros' part is a sum of independent rank-or-nothing terms, whose distribution is
    built one term at a time over the doubled ranks (integers, as tied ranks are halves)."""
    from scipy.stats import rankdata

    doubled = np.rint(2 * rankdata(np.abs(r))).astype(np.int64)
    nonzero = r != 0
    observed = int(doubled[r > 0].sum())
    distribution = np.ones(1)
    for rank in doubled[nonzero]:
        longer = np.zeros(distribution.size + rank)
        longer[: distribution.size] += 0.5 * distribution
        longer[rank:] += 0.5 * distribution
        distribution = longer
    if alternative == "less":
        return float(min(1.0, distribution[: observed + 1].sum()))
    return float(min(1.0, distribution[observed:].sum()))


def _wilcoxon(r: np.ndarray, alternative: str) -> float:
    """One-sided p-value of the Wilcoxon signed-rank test of r (scipy.stats.wilcoxon, zero_method
    'zsplit'): up to EXACT_PAIRS pairs the exact enumeration of the sign flips
    (_exact_signed_rank, equal to scipy's), beyond them scipy's own method."""
    from scipy.stats import wilcoxon

    if not r.size or not np.any(r):
        return 1.0
    if 2 <= r.size <= EXACT_PAIRS:
        return _exact_signed_rank(r, alternative)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(wilcoxon(r, zero_method="zsplit", alternative=alternative).pvalue)


def median_interval(
    r: np.ndarray, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the median of r (scipy.stats.bootstrap, RESAMPLES
    resamples)."""
    from scipy.stats import bootstrap

    if r.size < 2 or np.all(r == r[0]):
        return float(np.median(r)) if r.size else math.nan, float(
            np.median(r)
        ) if r.size else math.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = bootstrap(
            (r,),
            np.median,
            confidence_level=confidence,
            n_resamples=RESAMPLES,
            method="percentile",
            rng=np.random.default_rng(seed),
        )
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


@dataclass(frozen=True)
class Paired:
    """The paired comparison of A and B at one budget: per-seed log ratios (NaN: pair left out),
    their median with its interval, and the raw one-sided p-values (before Holm's correction). A
    pair where both runs diverged says nothing about which variant trains better, nor that they
    train alike: it is left out of every statistic and counted as both_diverged."""

    log_ratios: tuple[float, ...]
    median: float
    low: float
    high: float
    p_a: float  # one-sided: A lower
    p_b: float  # one-sided: B lower
    p_equivalent: float  # two one-sided tests: |log ratio| < log(margin)
    diverged_a: int
    diverged_b: int
    missing: int  # pairs left out (a run without a loss at this budget)
    both_diverged: int = 0  # pairs left out because both runs diverged
    negative: int = 0  # pairs left out because a loss is below 0 (no ratio)

    @property
    def seeds(self) -> int:
        """Every seed of the comparison: pairs, missing ones, those where both diverged and those
        with a negative loss."""
        return self.pairs + self.missing + self.both_diverged + self.negative

    @property
    def pairs(self) -> int:
        return sum(not math.isnan(r) for r in self.log_ratios)

    @property
    def wins_a(self) -> int:
        return sum(r < 0 for r in self.log_ratios if not math.isnan(r))

    @property
    def p_difference(self) -> float:
        return min(1.0, 2 * min(self.p_a, self.p_b))

    @property
    def ratio(self) -> float:
        return ratio_of(self.median)


def paired(a: list[float], b: list[float], margin: float = MARGIN, seed: int = 0) -> Paired:
    """Paired statistics of the losses a[i], b[i] of seed i at one budget (inf: diverged, NaN:
    missing)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    below = (a < 0) | (b < 0)
    both = np.isinf(a) & np.isinf(b)
    r_all = np.array([math.nan if gone else log_ratio(x, y) for x, y, gone in zip(a, b, both)])
    r = r_all[~np.isnan(r_all)]
    delta = math.log(margin)
    low, high = (snap(v, r) for v in median_interval(r, seed=seed))
    return Paired(
        log_ratios=tuple(float(v) for v in r_all),
        median=snap(float(np.median(r)), r) if r.size else math.nan,
        low=low,
        high=high,
        p_a=_wilcoxon(r, "less"),
        p_b=_wilcoxon(r, "greater"),
        p_equivalent=max(_wilcoxon(r + delta, "greater"), _wilcoxon(r - delta, "less"))
        if r.size
        else 1.0,
        diverged_a=int(np.sum(np.isinf(a))),
        diverged_b=int(np.sum(np.isinf(b))),
        missing=int(np.sum(np.isnan(r_all) & ~both & ~below)),
        both_diverged=int(np.sum(both)),
        negative=int(np.sum(below)),
    )


def holm(pvalues: list[float]) -> list[float]:
    """Holm's step-down adjustment: the i-th smallest p times (m - i), made monotone, capped at
    1."""
    order = np.argsort(pvalues, kind="stable")
    m, adjusted, running = len(pvalues), [1.0] * len(pvalues), 0.0
    for rank, index in enumerate(order):
        running = max(running, min(1.0, (m - rank) * float(pvalues[index])))
        adjusted[index] = running
    return adjusted
