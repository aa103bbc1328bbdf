"""The decisions of a claim's parts beyond a pair at one budget: a trend between an easy and a hard
study (Grows), a variant's loss no longer falling (Stalls) or against a level (Reaches), each in
every tuning study and then over the studies by the package's rule; and a claim's verdict from its
parts (decide_parts, claim_verdict). The parts and the pairs' decisions: physgrad.claim."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from physgrad.claim import (
    FAILS,
    HOLDS,
    NOT_RUN,
    OPEN,
    Claim,
    Close,
    Decision,
    Grows,
    Lower,
    Reaches,
    Runs,
    Stalls,
    _over_studies,
    decide_pairs,
    log_ratios_at_budget,
    studies_to_run,
    tuning_studies,
)
from physgrad.claim_words import ABOVE, BELOW, SEEDS_DISAGREE, STUDIES_DISAGREE, against_level
from physgrad.readout import fmt
from physgrad.trend import GROWS, interaction
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    UNDECIDED,
    decide,
    paired,
    ratio_of,
)


def decide_grows(easy: Runs, hard: Runs, part: Grows, fraction: float = 1.0) -> Decision:
    """The trend in each tuning study (its easy and its hard setting's runs), then over the
    studies."""
    for runs in (easy, hard):
        if not {part.a, part.b} <= set(runs.paths):
            return Decision(NOT_RUN, "-", f"no runs of {part.a} and {part.b} in {runs.folder}")
    if len(tuning_studies(easy)) != len(tuning_studies(hard)):
        return Decision(
            OPEN,
            "-",
            f"{part.easy} has {len(tuning_studies(easy))} tuning studies and {part.hard} "
            f"{len(tuning_studies(hard))}: decided when both have finished the same number",
        )
    pairs = list(zip(tuning_studies(easy), tuning_studies(hard)))
    ratios = [
        (
            log_ratios_at_budget(e, part.a, part.b, fraction),
            log_ratios_at_budget(h, part.a, part.b, fraction),
        )
        for e, h in pairs
    ]
    results = [interaction(r_easy, r_hard) for r_easy, r_hard in ratios]
    trend = {GROWS: HOLDS, UNDECIDED: OPEN}
    verdict, why = _over_studies(
        [trend.get(r.verdict, FAILS) for r in results],
        [f"{r.verdict}: {r.why}" for r in results],
        [r.verdict for r in results],
        max(easy.planned, hard.planned),
    )
    cause = ("", "")
    if verdict == OPEN:
        cause = studies_to_run(easy) or studies_to_run(hard) or cause
        if not cause[0] and why.startswith("the tuning studies disagree"):
            cause = (STUDIES_DISAGREE, f"{part.text()}: {why.split(': ', 1)[1]}")
    finite = lambda r: [v for v in r if not math.isnan(v)]  # noqa: E731
    pooled_easy = finite([v for r, _ in ratios for v in r])
    pooled_hard = finite([v for _, r in ratios for v in r])
    median = lambda r: fmt(ratio_of(float(np.median(r)))) if r else "-"  # noqa: E731
    measured = (
        f"{part.a} / {part.b}: {median(pooled_easy)} at {part.easy}, {median(pooled_hard)} at "
        f"{part.hard}; hard / easy = "
        + ", ".join(
            f"{fmt(r.factor)} [{fmt(ratio_of(r.low))}, {fmt(ratio_of(r.high))}]" for r in results
        )
        + (f" in {len(results)} tuning studies" if len(results) > 1 else "")
    )
    return Decision(verdict, measured, why, cause)


def _stall_in(runs: Runs, part: Stalls, fraction: float) -> tuple:
    """One tuning study's stall test: (paired loss at the fraction / at half of it, losses there,
    losses at the start, verdict, why)."""

    curves = runs.curves(part.variant, part.column)
    seeds = sorted(curves)
    full = [curves[s].at(runs.budget * fraction) for s in seeds]
    half = [curves[s].at(runs.budget * fraction / 2) for s in seeds]
    first = [float(curves[s].loss[0]) if len(curves[s].loss) else math.nan for s in seeds]
    # a run that diverged by half the budget has no level there: it counts as rising from its start
    # (a tie of two infinities would read as "stalled")
    half = [h if not math.isinf(h) else f for h, f in zip(half, first)]
    p = paired(full, half)
    verdict, why = decide(p, p.p_difference, p.p_equivalent)
    return p, full, first, verdict, why


def decide_stall(runs: Runs, part: Stalls, fraction: float = 1.0) -> Decision:
    """Stalled by `fraction` of the budget: the loss there against the loss at half of it, paired
    by seed, in each tuning study, then over the studies."""
    if part.variant not in runs.paths:
        return Decision(NOT_RUN, "-", f"no runs of {part.variant} in {runs.folder}")
    tests = [_stall_in(study, part, fraction) for study in tuning_studies(runs)]
    # falling (A better: the loss at the budget lower) is slow, rising (B better) unstable: neither
    # is stalled
    says = {EQUIVALENT: "stalled", A_BETTER: "still falling", B_BETTER: "rising, not stalled"}
    claim, why = _over_studies(
        [{EQUIVALENT: HOLDS, A_BETTER: FAILS, B_BETTER: FAILS}.get(t[3], OPEN) for t in tests],
        [f"{t[3]}{f': {says[t[3]]}' if t[3] in says else ''} ({t[4]})" for t in tests],
        [says.get(t[3], t[3]) for t in tests],
        runs.planned,
    )
    full = [v for t in tests for v in t[1]]
    first = [v for t in tests for v in t[2]]
    diverged = sum(math.isinf(v) for v in full)
    measured = (
        f"{part.column} at the budget / at half of it = "
        + ", ".join(
            f"{fmt(p.ratio)} [{fmt(ratio_of(p.low))}, {fmt(ratio_of(p.high))}]" for p, *_ in tests
        )
        + (f" in {len(tests)} tuning studies" if len(tests) > 1 else "")
        + f"; at the budget / at the start: {fmt(float(np.nanmedian(np.divide(full, first))))}"
        + (f"; diverged in {diverged} of {len(full)}" if diverged else "")
    )
    return Decision(claim, measured, why)


def decide_reach(runs: Runs, part: Reaches, fraction: float = 1.0) -> Decision:
    """Below the level at `fraction` of the budget, by the package's sign test over the seeds, in
    each tuning study, then over the studies."""
    if part.variant not in runs.paths:
        return Decision(NOT_RUN, "-", f"no runs of {part.variant} in {runs.folder}")
    found = []
    for study in tuning_studies(runs):
        curves = study.curves(part.variant, part.column)
        found.append([curves[s].at(study.budget * fraction) for s in sorted(curves)])
    tests = [against_level(values, part.level) for values in found]
    holds, fails = (ABOVE, BELOW) if part.above else (BELOW, ABOVE)
    claim, why = _over_studies(
        [{holds: HOLDS, fails: FAILS}.get(verdict, OPEN) for verdict, _ in tests],
        [f"{verdict}: {why}" for verdict, why in tests],
        [verdict for verdict, _ in tests],
        runs.planned,
    )
    pooled = [v for values in found for v in values]
    diverged = sum(math.isinf(v) for v in pooled)
    below = sum(v < part.level for v in pooled)
    known = sum(not math.isnan(v) for v in pooled)
    cause = ("", "")
    if claim == OPEN and studies_to_run(runs):
        cause = studies_to_run(runs)
    elif claim == OPEN and 0 < below < known:
        stuck = known - below - diverged
        cause = (
            SEEDS_DISAGREE,
            f"{part.variant}: {below} of {known} seeds below {part.level:g}, {stuck} stuck at or "
            "above it" + (f", {diverged} diverged" if diverged else ""),
        )
    measured = (
        f"{part.column} at the budget: median "
        + ", ".join(fmt(_median(values)) for values in found)
        + (f" in {len(found)} tuning studies" if len(found) > 1 else "")
        + f"; below {part.level:g} in {sum(v < part.level for v in pooled)} of {len(pooled)}"
        + (f"; diverged in {diverged}" if diverged else "")
    )
    return Decision(claim, measured, why, cause)


def _median(values: list[float]) -> float:
    """The median of the values that are not missing; NaN where none is (a column not kept)."""
    known = [v for v in values if not math.isnan(v)]
    return float(np.median(known)) if known else math.nan


def decide_parts(
    claim: Claim, study: Callable[[str], object], fraction: float = 1.0
) -> list[tuple[object, Decision]]:
    """Each part of the claim at `fraction` of its budget, from study(name): a study's runs, or a
    Decision (why it cannot be decided: not finished, not run) where there are none. The Lower and
    Close parts of one study are decided together (Holm's correction over them)."""
    by_study: dict[str, list] = {}
    for part in claim.parts:
        if isinstance(part, (Lower, Close)):
            by_study.setdefault(part.study, []).append(part)
    decided = {}
    for name, parts in by_study.items():
        runs = study(name)
        found = (
            [runs] * len(parts)
            if isinstance(runs, Decision)
            else decide_pairs(runs, parts, fraction)
        )
        decided.update(zip(parts, found))
    rows = []
    for part in claim.parts:
        if part in decided:
            rows.append((part, decided[part]))
            continue
        names = [part.easy, part.hard] if isinstance(part, Grows) else [part.study]
        found = [study(n) for n in names]
        missing = next((r for r in found if isinstance(r, Decision)), None)
        if missing is not None:
            rows.append((part, missing))
        elif isinstance(part, Grows):
            rows.append((part, decide_grows(*found, part, fraction)))
        else:
            decide_part = decide_reach if isinstance(part, Reaches) else decide_stall
            rows.append((part, decide_part(found[0], part, fraction)))
    return rows


def claim_verdict(rows: list[tuple[object, Decision]], twin: bool = False) -> str:
    """A claim holds if every part that was run holds, does not hold if one does not, is not
    settled otherwise. A part whose variants a study does not run (a presets' twin that fixes the
    clipping) is left out: the verdict speaks for the parts that were run; of a presets' twin
    (twin) that ran none of them, NOT_RUN."""
    verdicts = [d.verdict for _, d in rows if d.verdict != NOT_RUN]
    if rows and not verdicts and twin:
        return NOT_RUN
    if verdicts and all(v == HOLDS for v in verdicts):
        return HOLDS
    return FAILS if FAILS in verdicts else OPEN
