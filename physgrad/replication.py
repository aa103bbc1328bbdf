"""Verdicts over repeated tuning studies: a pair's verdict holds where a majority of the studies
reach it, none reaches another, and, for "better", the studies' estimates taken as one draw each
agree (between_studies). docs/protocol.md ("Independent tuning studies") gives the rule's error
rates and power on simulated studies (experiments/study_luck.py, experiments/tuning_power.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from physgrad.readout import fmt
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    UNDECIDED,
    Paired,
    PairVerdict,
    ratio_of,
    snap,
)

# the level of the test between studies (between_studies), two-sided: the highest of 0.05, 0.02
# and 0.01 that keeps false "better" at or below 1% per pair with study offsets up to 0.5 at a seed
# spread of 0.3, simulated by experiments/study_luck.py (docs/protocol.md, "Studies as draws")
STUDY_ALPHA = 0.01


# a study's median counts up to this ratio either way in the test between studies: beyond it, by
# how much one variant is better says nothing of whether it is (a study where B diverged on most
# seeds, +-LOG_CAP, counts as this); symmetric, so it keeps the test's level under the null
STUDY_CAP = math.log(10.0)


@dataclass(frozen=True)
class Draws:
    """The tuning studies' estimates of one pair taken as one draw each: each study's median log
    ratio clipped to +-STUDY_CAP (estimates), their mean with its interval and two-sided p (studies:
    how many had a median)."""

    estimates: tuple[float, ...]
    mean: float
    low: float
    high: float
    p: float

    @property
    def studies(self) -> int:
        return len(self.estimates)


def between_studies(medians: Sequence[float], alpha: float = STUDY_ALPHA) -> Draws:
    """The random-effects estimate of a pair's log ratio over K tuning studies with the
    Hartung-Knapp interval, each study one draw: with the studies' equal designs (the same seeds
    and trials each) the weights are equal, and the interval is mean(y) +- t_{K-1, 1 - alpha/2} x
    s(y) / sqrt(K) over the study medians y_k (clipped to +-STUDY_CAP), whose spread s(y) holds
    both the seeds' noise and the tuning's luck (a study's offset from its two tuned settings), as
    the one-sample t interval. Studies without a median are left out. p is the two-sided p of mean
    0; with every y equal and nonzero, 0."""
    from scipy.stats import t as student

    y = np.clip([float(m) for m in medians if not math.isnan(m)], -STUDY_CAP, STUDY_CAP)
    if y.size < 2:
        return Draws(tuple(y), float(y.mean()) if y.size else math.nan, -math.inf, math.inf, 1.0)
    mean, error = float(y.mean()), float(y.std(ddof=1)) / math.sqrt(y.size)
    if error == 0.0:
        p = 0.0 if mean != 0.0 else 1.0
        return Draws(tuple(y), mean, mean, mean, p)
    half = float(student.ppf(1 - alpha / 2, y.size - 1)) * error
    p = float(2 * student.sf(abs(mean) / error, y.size - 1))
    return Draws(tuple(y), mean, mean - half, mean + half, p)


def majority(studies: int) -> int:
    """How many of the tuning studies a verdict must hold in: more than half of them."""
    return studies // 2 + 1


def across_studies(
    per_study: Sequence[Sequence[PairVerdict]],
    need: int | None = None,
    same_side: bool = True,
    study_alpha: float | None = STUDY_ALPHA,
    study_margin: float = 1.0,
) -> list[PairVerdict]:
    """Every pair decided over repeated tuning studies (per_study[k]: study k's compare_variants,
    the same pairs in the same order). A verdict holds at a fraction of the budget where more than
    half of the studies (need) reached it there, no study reached another (A better against B
    better, or either against equivalent) and, with same_side, every study's median log ratio lies
    on the side of a "better" and, with study_alpha, the studies taken as one draw each exclude a
    ratio of study_margin on that side (between_studies); otherwise the pair is undecided there,
    and why names each study's verdict. Each study tunes anew and evaluates on its own seeds (its
    own tuning seed, trial points and evaluation seeds), so a difference that one tuning draw
    produces, two equally good rules tuned to settings of different quality, must recur in other
    draws to count; docs/protocol.md gives the rule's error rates and power on simulated studies.
    The
    corrected p-values are those of the weakest study of the majority (the majority-th smallest).
    at[fraction] pools the pairs of all studies: counts, divergences and the median of the pooled
    log ratios; its interval spans the studies' intervals (from the lowest low to the highest
    high), descriptive, as a study's pairs share one tuning."""
    if len(per_study) == 1:
        return list(per_study[0])
    need = need or majority(len(per_study))
    combined = []
    for pair in zip(*per_study):
        first = pair[0]
        result = PairVerdict(first.a, first.b, first.budget, studies=list(pair))
        for fraction in first.at:
            at = [v.at[fraction] for v in pair]
            ratios = [r for p in at for r in p.log_ratios]
            finite = np.array([r for r in ratios if not math.isnan(r)])
            result.at[fraction] = Paired(
                log_ratios=tuple(ratios),
                median=snap(float(np.median(finite)), finite) if finite.size else math.nan,
                low=min(p.low for p in at),
                high=max(p.high for p in at),
                p_a=sorted(p.p_a for p in at)[need - 1],
                p_b=sorted(p.p_b for p in at)[need - 1],
                p_equivalent=sorted(p.p_equivalent for p in at)[need - 1],
                diverged_a=sum(p.diverged_a for p in at),
                diverged_b=sum(p.diverged_b for p in at),
                missing=sum(p.missing for p in at),
                both_diverged=sum(p.both_diverged for p in at),
                negative=sum(p.negative for p in at),
            )
            result.p_difference[fraction] = sorted(v.p_difference[fraction] for v in pair)[need - 1]
            result.p_equivalent[fraction] = sorted(v.p_equivalent[fraction] for v in pair)[need - 1]
            result.verdicts[fraction] = over_studies(
                [v.verdicts[fraction][0] for v in pair],
                need=need,
                medians=[p.median for p in at] if same_side else (),
                study_alpha=study_alpha if study_alpha is not None else 1.0,
                study_margin=study_margin,
            )
        combined.append(result)
    return combined


def over_studies(
    found: Sequence[str],
    undecided: str = UNDECIDED,
    labels: Sequence[str] = (),
    need: int | None = None,
    medians: Sequence[float] = (),
    study_alpha: float = STUDY_ALPHA,
    study_margin: float = 1.0,
) -> tuple[str, str]:
    """One verdict from each repeated tuning study's (found[k]) by across_studies' rule: the
    verdict more than half (need) of the studies reached when no study reached another and, given
    each study's median log ratio A/B (medians[k]), a "better" whose every study's median lies on
    its side (a study undecided with its median the other way goes against it; a study without a
    median, no pair at the budget, neither counts for nor against) and whose studies, taken as one
    draw each (between_studies at study_alpha), give an interval that excludes study_margin on
    that side; `undecided` otherwise, with why naming each study's verdict (or its label,
    labels[k])."""
    need = need or majority(len(found))
    decided = set(found) - {undecided}
    listed = ", ".join(labels or found)
    if len(decided) == 1 and found.count(next(iter(decided))) >= need:
        verdict = next(iter(decided))
        held = f"{found.count(verdict)} of {len(found)} tuning studies: {listed}"
        side = {A_BETTER: -1.0, B_BETTER: 1.0}.get(verdict)
        if not side or not medians:
            return verdict, held
        against = [k for k, m in enumerate(medians) if not math.isnan(m) and not m * side > 0]
        if against:
            return (
                undecided,
                f"{held}; but study {against[0] + 1}'s median ratio is not on that side",
            )
        draws = between_studies(medians, study_alpha)
        edge = side * math.log(study_margin)
        beyond = draws.high < edge if side < 0 else draws.low > edge
        if not beyond:
            return undecided, (
                f"{held}; but the studies taken as draws do not exclude a ratio of "
                f"{study_margin:g}: {_ratio(draws.mean)} [{_ratio(draws.low)}, "
                f"{_ratio(draws.high)}] ({1 - study_alpha:.0%} interval over {draws.studies} "
                f"stud{'y' if draws.studies == 1 else 'ies'}, Hartung-Knapp; p = {draws.p:.2g}"
                + (f", not below {study_alpha:g}" if study_margin == 1 else "")
                + "): which tuning study ran could make the difference"
            )
        if all(abs(e) >= STUDY_CAP for e in draws.estimates):
            return verdict, f"{held}; every study's median ratio 10x or more from 1 on that side"
        return verdict, f"{held}; over the studies {_ratio(draws.mean)} (p = {draws.p:.2g})"
    if len(decided) > 1:
        return undecided, f"the tuning studies disagree: {listed}"
    return (
        undecided,
        f"{len(found) - found.count(undecided)} of {len(found)} tuning studies decided, "
        f"{need} needed: {listed}",
    )


def _ratio(log_value: float) -> str:
    return fmt(ratio_of(log_value))
