"""What a comparison could have found: the spread of its per-seed log ratios (spread) and the
smallest loss ratio its design finds with probability POWER (detectable_ratio, seeds_for_ratio)."""

from __future__ import annotations

import functools
import math

import numpy as np

from physgrad.replication import majority
from physgrad.verdict import ALPHA, CONFIDENCE, LOG_CAP, MARGIN, Paired, seeds_needed

POWER = 0.8  # the chance of finding an effect that "detectable" promises


def spread(p: Paired) -> float:
    """The spread of a comparison's per-seed log ratios: 1.4826 x their median absolute deviation
    (the standard deviation where they are normal, robust to a few wild seeds), over the pairs
    where neither side diverged; NaN with fewer than 3 such pairs."""
    finite = np.array([r for r in p.log_ratios if not math.isnan(r) and abs(r) < LOG_CAP])
    if finite.size < 3:
        return math.nan
    return float(1.4826 * np.median(np.abs(finite - np.median(finite))))


@functools.lru_cache(maxsize=256)
def study_power_needed(studies: int, need: int, power: float = POWER) -> float:
    """The power each of `studies` independent tuning studies must have for `need` of them to reach
    a verdict with probability `power` (the binomial tail, solved by bisection)."""
    from scipy.stats import binom

    low, high = 0.0, 1.0
    for _ in range(60):
        middle = (low + high) / 2
        if binom.sf(need - 1, studies, middle) < power:
            low = middle
        else:
            high = middle
    return high


def detectable_ratio(
    sd: float,
    seeds: int,
    comparisons: int = 1,
    studies: int = 1,
    need: int | None = None,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    power: float = POWER,
) -> float:
    """The smallest loss ratio (above 1) a study finds with probability `power`, for log ratios
    of spread sd on `seeds` paired seeds per study, `comparisons` comparisons (Holm's strictest
    step, alpha / comparisons, two-sided) and `need` of `studies` tuning studies agreeing. A normal
    approximation of both halves of "better": the signed-rank test (asymptotic efficiency 3 / pi
    of the t test: sd x sqrt(pi / 3) / sqrt(n)) and the bootstrap interval of the median beyond
    the margin (the median's standard error, sd x sqrt(pi / 2) / sqrt(n)); the larger of the two.
    Infinite where the seeds are too few for any verdict (seeds_needed), NaN without a spread. The
    tuning's own spread between studies is not in it: the simulated table of docs/protocol.md is
    what the whole procedure finds."""
    from scipy.stats import norm

    if math.isnan(sd):
        return math.nan
    if seeds < seeds_needed(alpha, comparisons):
        return math.inf
    need = need or majority(studies)
    z_power = norm.ppf(study_power_needed(studies, need, power))
    root = math.sqrt(seeds)
    test = (norm.ppf(1 - alpha / (2 * comparisons)) + z_power) * sd * math.sqrt(math.pi / 3) / root
    interval = (
        math.log(margin)
        + (norm.ppf(1 - (1 - CONFIDENCE) / 2) + z_power) * sd * math.sqrt(math.pi / 2) / root
    )
    return math.exp(max(test, interval))


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
