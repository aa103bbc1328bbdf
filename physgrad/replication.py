"""Verdicts over repeated tuning studies: a pair's verdict holds where a majority of the studies
reach it, none reaches another, and, for "better", the studies' estimates taken as one draw each
agree (between_studies). docs/protocol.md ("Independent tuning studies") gives the rule's error
rates and power on simulated studies (experiments/study_luck.py, experiments/tuning_power.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from physgrad.verdict import A_BETTER, B_BETTER, UNDECIDED, Paired, PairVerdict, snap


def majority(studies: int) -> int:
    """How many of the tuning studies a verdict must hold in: more than half of them."""
    return studies // 2 + 1


def across_studies(
    per_study: Sequence[Sequence[PairVerdict]], need: int | None = None, same_side: bool = True
) -> list[PairVerdict]:
    """Every pair decided over repeated tuning studies (per_study[k]: study k's compare_variants,
    the same pairs in the same order). A verdict holds at a fraction of the budget where more than
    half of the studies (need) reached it there, no study reached another (A better against B
    better, or either against equivalent) and, with same_side, every study's median log ratio lies
    on the side of a "better"; otherwise the pair is undecided there, and why names each study's
    verdict. Each study tunes anew and evaluates on its own seeds (its own tuning seed, trial points
    and evaluation seeds), so a difference that one tuning draw produces, two equally good rules
    tuned to settings of different quality, must recur in other draws to count;
    docs/protocol.md gives the rule's error rates and power on simulated studies. The
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
            )
            result.p_difference[fraction] = sorted(v.p_difference[fraction] for v in pair)[need - 1]
            result.p_equivalent[fraction] = sorted(v.p_equivalent[fraction] for v in pair)[need - 1]
            result.verdicts[fraction] = over_studies(
                [v.verdicts[fraction][0] for v in pair],
                need=need,
                medians=[p.median for p in at] if same_side else (),
            )
        combined.append(result)
    return combined


def over_studies(
    found: Sequence[str],
    undecided: str = UNDECIDED,
    labels: Sequence[str] = (),
    need: int | None = None,
    medians: Sequence[float] = (),
) -> tuple[str, str]:
    """One verdict from each repeated tuning study's (found[k]) by across_studies' rule: the
    verdict more than half (need) of the studies reached when no study reached another and, given
    each study's median log ratio A/B (medians[k]), a "better" whose every study's median lies on
    its side (a study undecided with its median the other way goes against it); `undecided`
    otherwise, with why naming each study's verdict (or its label, labels[k])."""
    need = need or majority(len(found))
    decided = set(found) - {undecided}
    listed = ", ".join(labels or found)
    if len(decided) == 1 and found.count(next(iter(decided))) >= need:
        verdict = next(iter(decided))
        side = {A_BETTER: -1.0, B_BETTER: 1.0}.get(verdict)
        against = [k for k, m in enumerate(medians) if side and not m * side > 0]
        if against:
            return undecided, (
                f"{found.count(verdict)} of {len(found)} tuning studies: {listed}; but study "
                f"{against[0]}'s median ratio is not on that side"
            )
        return verdict, f"{found.count(verdict)} of {len(found)} tuning studies: {listed}"
    if len(decided) > 1:
        return undecided, f"the tuning studies disagree: {listed}"
    return (
        undecided,
        f"{len(found) - found.count(undecided)} of {len(found)} tuning studies decided, "
        f"{need} needed: {listed}",
    )
