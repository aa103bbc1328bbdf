"""What a measurement says of a paper's claim: a variant's losses against a level (against_level),
whether a variant has left its start (left_start), and the claim's word (claim_word)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from physgrad.verdict import ALPHA, UNDECIDED

BELOW, ABOVE = "below", "above"


def against_level(values: Sequence[float], level: float, alpha: float = ALPHA) -> tuple[str, str]:
    """Whether a variant's losses at a budget, one per seed, lie below an absolute level (a paper's
    "reaches 1e-2", "still solves the task"): the two-sided sign test of the seeds below the level
    against half of them (scipy.stats.binomtest). BELOW where more than half are below and p <
    alpha, ABOVE where more than half are at or above and p < alpha, UNDECIDED otherwise (with 10
    seeds: 9 or 10 of 10 on one side). A diverged seed (inf) is above; a missing one (NaN) is left
    out and counted."""
    from scipy.stats import binomtest

    known = [v for v in values if not math.isnan(v)]
    missing = len(values) - len(known)
    below = sum(v < level for v in known)
    n = len(known)
    p = binomtest(below, n, 0.5).pvalue if n else 1.0
    verdict = UNDECIDED if p >= alpha else BELOW if 2 * below > n else ABOVE
    why = f"{below} of {n} seeds below {level:g} (sign test p = {p:.2g})" + (
        f", {missing} missing" if missing else ""
    )
    return verdict, why


# what a claim's measurement says of the paper's claim (claim_word)
SUPPORTED, CONTRADICTED = "supported", "contradicted"
NOT_TESTED, DIFFERENT_SETUP = "not tested at the paper's budget", "different setup"
# "not settled", split by its cause (claim_word)
SEEDS_DISAGREE, STUDIES_DISAGREE, STUDIES_TO_RUN = (
    "not settled: seeds disagree",
    "not settled: tuning studies disagree",
    "not settled: tuning studies still to run",
)
# the tuning studies agree, but their spread leaves no difference inside the interval over them
TUNING_LUCK = "not settled: tuning luck not excluded"
LEANS_AGAINST = "not settled: leans against the claim"  # studies against it, none for it
NOT_SETTLED = "not settled"
# a variant that did not leave its start where the paper states no budget to blame
UNTRAINED = "not tested: a variant did not leave its start"
TRAINED_FACTOR = 2.0  # a variant has left its start when its median loss fell by this factor


def left_start(starts: Sequence[float], finals: Sequence[float]) -> bool:
    """Whether a variant has trained: its median over seeds of final / start loss at most
    1 / TRAINED_FACTOR (a diverged seed counts as not trained; missing seeds are left out)."""
    ratios = [f / s for s, f in zip(starts, finals) if s > 0 and not math.isnan(f)]
    return bool(ratios) and float(np.median(ratios)) <= 1.0 / TRAINED_FACTOR


def share_text(share: float) -> str:
    """X / the paper's budget as a percentage ("4.7% of the paper's budget"); "" where the paper
    states none (NaN)."""
    if math.isnan(share):
        return ""
    percent = 100 * share
    return (
        f"{percent:.2g}% of the paper's budget"
        if percent < 10
        else f"{percent:.0f}% of the paper's budget"
    )


def claim_word(
    holds: bool,
    fails: bool,
    fails_at_half: bool,
    trained: bool,
    share: float,
    departs: str = "",
    cause: tuple[str, str] = ("", ""),
    failing: str = "",
) -> tuple[str, str]:
    """What a measurement says of a paper's claim, and why:
    - DIFFERENT_SETUP where the comparison departs from the paper's in a way that matters;
    - SUPPORTED where it holds at the budget X, every variant the claim is about has left its start
      (left_start, `trained`) and it did not fail at X/2; held at X with a variant that has not
      trained, or turned between X/2 and X, the budget is the cause: NOT_TESTED;
    - CONTRADICTED where it does not hold at X and either X is the paper's budget or more (share =
      X / the paper's, NaN where the paper states none) or every variant has left its start and it
      did not hold at X/2 either; not holding before that is NOT_TESTED;
    - not settled at X, by its cause: NOT_TESTED where X is below a budget the paper states and a
      variant has not left its start (seeds or studies that disagree about untrained networks say
      nothing of the claim; their cause is added to the reason); else `cause` (STUDIES_TO_RUN,
      SEEDS_DISAGREE or STUDIES_DISAGREE, and what the evidence shows: the tuning studies run of
      those planned, stuck or diverged seeds with counts, studies that reached opposite verdicts
      or whose sizes differ beyond what tuning luck explains) where the parts found one; else
      NOT_TESTED where the paper states no budget and a variant has not left its start; else
      NOT_SETTLED (the seeds could not resolve it at this budget). Where the paper states no
      budget (share NaN), a variant that has not left its start makes the word UNTRAINED, not
      NOT_TESTED: there is no paper's budget to fall short of.
    Every reason names the share of the paper's budget where the paper states one; a "does not
    hold" names the parts that do not (failing), so that a claim contradicted in one part (its
    mechanism) is not read as contradicted in all."""
    if departs:
        return DIFFERENT_SETUP, departs
    budget = share_text(share)
    within = f"; {budget}" if budget else ""
    below_paper = math.isnan(share) or share < 1.0
    not_holding = f" ({failing})" if failing else ""
    untested = UNTRAINED if math.isnan(share) else NOT_TESTED
    if holds:
        if trained and not fails_at_half:
            return SUPPORTED, "holds at X, every variant having left its start" + within
        if not trained:
            return untested, (
                f"holds at X, but a variant fell less than {TRAINED_FACTOR:g}x from its start"
                + within
            )
        return NOT_TESTED, "holds at X but not at X/2: it turns with the budget" + within
    at_paper = not below_paper
    if fails and (at_paper or (trained and fails_at_half)):
        return CONTRADICTED, (
            "does not hold at the paper's budget"
            if at_paper
            else "does not hold at X/2 and X, every variant having left its start"
        ) + not_holding
    if fails:
        why = (
            f"does not hold at X, but a variant fell less than {TRAINED_FACTOR:g}x from its start"
            if not trained
            else "does not hold at X, but did not fail at X/2 (it turned with the budget)"
        )
        return (untested if not trained else NOT_TESTED), why + not_holding + within
    word, shown = cause
    untrained = f"not settled at X, and a variant fell less than {TRAINED_FACTOR:g}x from its start"
    if not trained and share < 1.0:  # below a budget the paper states: the budget comes first
        return NOT_TESTED, untrained + within + (
            f"; {word.removeprefix(NOT_SETTLED + ': ')} as well" + (f": {shown}" if shown else "")
            if word
            else ""
        )
    if word:
        return word, shown
    if below_paper and not trained:
        return untested, untrained + within
    return NOT_SETTLED, "not settled at X: the seeds could not resolve it" + within


def combined_causes(causes: list[tuple[str, str]]) -> tuple[str, str]:
    """The parts' causes of "not settled" as one, for claim_word: the first's word, and every
    distinct cause's evidence (the others named "... as well")."""
    found = [c for c in causes if c[0]]
    if not found:
        return "", ""
    word, shown = found[0]
    for other, evidence in found[1:]:
        if evidence not in shown:
            shown += f"; {other.removeprefix(NOT_SETTLED + ': ')} as well: {evidence}"
    return word, shown
