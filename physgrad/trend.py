"""The trend rule of the papers' claims (experiments/claims.py, "Grows"): whether A's advantage
over B grows from an easy setting to a hard one, with the verdict rule's margin, level and bootstrap
(physgrad.verdict; docs/protocol.md)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from physgrad.paired_stats import CONFIDENCE, MARGIN, RESAMPLES, ratio_of
from physgrad.readout import fmt
from physgrad.verdict import ALPHA, MIN_PAIRS, UNDECIDED


@dataclass(frozen=True)
class Interaction:
    """Whether A's advantage over B grows from an easy setting to a hard one: d = median r_hard -
    median r_easy of the per-seed log ratios log(loss_A / loss_B) of the two settings (each
    setting's pairs on its own)."""

    difference: (
        float  # d; exp(d) is how many times lower A/B is at the hard end than at the easy end
    )
    low: float
    high: float
    p: float  # one-sided Mann-Whitney U: r_hard stochastically below r_easy
    pairs_easy: int
    pairs_hard: int
    verdict: str
    why: str

    @property
    def factor(self) -> float:
        return ratio_of(self.difference)


GROWS, DOES_NOT_GROW = "grows", "does not grow"


def interaction(
    r_easy: Iterable[float],
    r_hard: Iterable[float],
    margin: float = MARGIN,
    alpha: float = ALPHA,
    seed: int = 0,
) -> Interaction:
    """The trend claim "A's advantage over B is larger at the hard end": d = median(r_hard) -
    median(r_easy), r the per-seed log ratios A/B of each setting (NaN: pair left out), with a
    percentile bootstrap 95% interval (the two settings resampled independently: their seeds train
    different problems) and a one-sided Mann-Whitney U test of r_hard < r_easy. grows: the interval
    lies below -log(margin) and p < alpha; does not grow: it lies above -log(margin) (the ratio at
    the hard end is not lower by the margin, with confidence); undecided otherwise (also with fewer
    than MIN_PAIRS pairs in a setting)."""
    from scipy.stats import bootstrap, mannwhitneyu

    easy, hard = (np.asarray([v for v in r if not math.isnan(v)], float) for r in (r_easy, r_hard))
    if min(easy.size, hard.size) < MIN_PAIRS:
        d = float(np.median(hard) - np.median(easy)) if easy.size and hard.size else math.nan
        return Interaction(
            d,
            math.nan,
            math.nan,
            math.nan,
            easy.size,
            hard.size,
            UNDECIDED,
            f"{easy.size} and {hard.size} pairs (at least {MIN_PAIRS} each needed)",
        )
    d = float(np.median(hard) - np.median(easy))
    if np.all(easy == easy[0]) and np.all(hard == hard[0]):
        low = high = d
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = bootstrap(
                (hard, easy),
                lambda h, e, axis=-1: np.median(h, axis=axis) - np.median(e, axis=axis),
                confidence_level=CONFIDENCE,
                n_resamples=RESAMPLES,
                method="percentile",
                vectorized=True,
                rng=np.random.default_rng(seed),
            )
        low, high = float(result.confidence_interval.low), float(result.confidence_interval.high)
    p = float(mannwhitneyu(hard, easy, alternative="less").pvalue)
    delta = math.log(margin)
    if high < -delta and p < alpha:
        verdict, why = GROWS, f"interval below 1/{margin:g}, p = {p:.2g}"
    elif low > -delta:
        verdict, why = DOES_NOT_GROW, f"interval above 1/{margin:g} (p = {p:.2g})"
    else:
        verdict, why = (
            UNDECIDED,
            f"p = {p:.2g}, interval [{fmt(ratio_of(low))}, {fmt(ratio_of(high))}]",
        )
    return Interaction(d, low, high, p, easy.size, hard.size, verdict, why)
