"""A claim's study and budget: the study that gives a claim its budget (its first part's), that
budget in words and against the paper's, the variants of a claim in a study, and whether they have
left their start at the budget (the regime guard of physgrad.claim_words)."""

from __future__ import annotations

import inspect
import math
from contextlib import contextmanager

import numpy as np
from evidence import CLOCK, busy_clock
from study_runs import StudyRuns, read_study, study_protocol

from physgrad.claim import (
    NOT_RUN,
    Claim,
    Decision,
    Grows,
    Reaches,
    Stalls,
    studies_of,
    tuning_studies,
)
from physgrad.claim_words import left_start
from physgrad.readout import fmt


def budget_text(runs: StudyRuns) -> str:
    return {
        "iteration": f"{runs.budget:g} iterations",
        "wall_time": f"{runs.budget:g} s (measured clock)",
        "calibrated_time": f"{runs.budget:g} s (calibrated clock)",
    }.get(runs.axis, f"{runs.budget:g}")


def busy_clock_text(root, main: str) -> str:
    """ "; its clock was calibrated on a busy machine (...)" where the study's kept clock
    (root/<main>.calibration.json) or its folder's calibration was measured beside other work,
    "" otherwise: every step was then charged more than it costs, and the budget bought fewer
    steps than it says."""
    for path in (root / CLOCK.format(name=main), root / main / "calibration.json"):
        why = busy_clock(path) if path.is_file() else ""
        if why:
            return (
                f"; its clock was calibrated on a busy machine ({why}): every step was charged "
                "more than it costs, so the budget bought fewer steps than it says"
            )
    return ""


def part_study(part) -> str:
    return getattr(part, "study", None) or f"{part.easy} -> {part.hard}"


def main_study(claim: Claim) -> str:
    """The study that gives a claim its budget: the first part's (a trend's hard end)."""
    part = claim.parts[0]
    return part.hard if isinstance(part, Grows) else part.study


def share_text(claim: Claim, runs: StudyRuns) -> str:
    """The budget here against the paper's, e.g. "1500 iterations: 4.7% of the paper's 32,000
    iterations"."""
    here = budget_text(runs)
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return f"{here}; the paper's: {claim.paper_budget_text}"
    share = 100 * runs.budget / claim.paper_budget
    percent = f"{share:.2g}" if share < 10 else f"{share:.0f}"
    return f"{here}: {percent}% of {claim.budget_of} {claim.paper_budget_text}"


def share(claim: Claim, runs: StudyRuns) -> float:
    """The budget here over the paper's (NaN where the paper states none in these units)."""
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return math.nan
    return runs.budget / claim.paper_budget


def claim_variants(claim: Claim, study: str) -> list[str]:
    names = []
    for part in claim.parts:
        if part_study(part) == study:
            found = [part.variant] if isinstance(part, (Stalls, Reaches)) else [part.a, part.b]
            names += [n for n in found if n not in names]
    return names


def variants_left_start(claim: Claim, runs: StudyRuns, fraction: float = 1.0) -> tuple[bool, str]:
    """Whether every variant of the claim's main study has left its start by `fraction` of X (the
    median over its seeds of loss there / at its first evaluation,
    physgrad.claim_words.left_start), and each variant's factor."""
    said, trained = [], True
    for variant in claim_variants(claim, main_study(claim)):
        if variant not in runs.paths:
            continue
        starts, finals = [], []
        for study in tuning_studies(runs):
            for curve in study.curves(variant).values():
                starts.append(float(curve.loss[0]) if len(curve.loss) else math.nan)
                finals.append(curve.at(study.budget * fraction))
        trained &= left_start(starts, finals)
        ratios = [f / s for s, f in zip(starts, finals) if s > 0 and not math.isnan(f)]
        factor = 1 / float(np.median(ratios)) if ratios else math.nan
        said.append(f"{variant} {fmt(factor)}x")
    return trained and bool(said), ", ".join(said)


def untrained_failures_open(claim: Claim, runs: StudyRuns, verdicts: dict) -> dict:
    """The claim's verdicts at X/4 and X/2 (fraction -> verdict) with a "does not hold" between
    variants that had not left their start there read as not settled: it says nothing of the
    claim (as claim_word reads X)."""
    from physgrad.claim import FAILS, OPEN

    return {
        f: f"{OPEN} (a variant had not left its start)"
        if f < 1.0 and v == FAILS and not variants_left_start(claim, runs, f)[0]
        else v
        for f, v in verdicts.items()
    }


def of_planned(runs: StudyRuns) -> str:
    """ " of N" where fewer of a study's N tuning studies have run (the majority is of N)."""
    ran = len(runs.tuning) or 1
    return f" of {runs.planned}" if runs.planned > ran else ""


def measured_briefly(part, decision) -> str:
    """ " (numbers)" of a part as a longer profile's cell shows it: a pair's ratio and seeds, a
    trend's two ratios and its hard / easy factor; "" where it has none."""
    if decision.measured == "-":
        return ""
    return f" ({', '.join(decision.measured.split('; ')[: 2 if isinstance(part, Grows) else 1])})"


def presets_at_paper_budget(
    claim: Claim, further: tuple, decide
) -> dict[str, tuple[str, str, str]]:
    """{part's text: (verdict, "with the presets at the paper's budget (claims-paper, 32000
    iterations)", " (numbers)")} of the parts a longer profile ran untuned at the paper's budget or
    beyond (further: (folder, that profile's studies) pairs; decide: claims.decide_claim): a
    presets' cell here that did not run a part (the twin fixes an axis the paper's runs sweep), or
    a part that fails here, says it."""
    found: dict[str, tuple[str, str, str]] = {}
    for folder, there in further:
        main = main_study(claim)
        if not studies_of(claim) <= {s.name for s in there}:
            continue
        runs = read_study(folder / main)
        if runs is None or study_protocol(folder / main)[0] or not share(claim, runs) >= 1.0:
            continue  # tuned, or short of the paper's budget (NaN: none stated)
        where = f"with the presets at {claim.budget_of} budget ({folder.name}, {budget_text(runs)})"
        for part, d in decide(claim, folder, "", 1.0, there)[1]:
            if d.verdict != NOT_RUN:
                found.setdefault(part.text(), (d.verdict, where, measured_briefly(part, d)))
    return found


def fixed_by_twin(decision: Decision, fixed: list[str]) -> Decision:
    """A part the presets' twin does not run because the twin fixes an axis (optim.clip=none, the
    one clipping mode of the three the reference sweeps, to save time) says that, not which
    variants are missing."""
    if decision.verdict != NOT_RUN or not fixed:
        return decision
    return Decision(
        NOT_RUN,
        "-",
        f"the presets' twin runs {fixed[0]} only (to save time; the tuned study runs the others)",
    )


def failing_text(decided: list, at_paper: dict) -> str:
    """ "part: does not hold" for each part decided (part, Decision) to fail, with its verdict at
    the paper's budget where a longer profile ran it (at_paper: presets_at_paper_budget)."""
    from physgrad.claim import FAILS

    return "; ".join(
        f"{part.text()}: does not hold"
        + (f" ({paper[0]} {paper[1]})" if (paper := at_paper.get(part.text())) else "")
        for part, d in decided
        if d.verdict == FAILS
    )


class PageMemo:
    """A pure function of the evidence (claims.decide_claim) whose calls are remembered while one
    page is written (`with memo.page():`), and only then: the evidence does not change within a
    page (its headline and its parts' table decide a claim at the same budgets again), but may
    between two pages written in one process."""

    def __init__(self, function):
        self.function, self.signature, self.memo = function, inspect.signature(function), None

    def __call__(self, *args, **kwargs):
        if self.memo is None:
            return self.function(*args, **kwargs)
        bound = self.signature.bind(*args, **kwargs)
        bound.apply_defaults()
        key = tuple(bound.arguments.values())
        if key not in self.memo:
            self.memo[key] = self.function(*args, **kwargs)
        return self.memo[key]

    @contextmanager
    def page(self):
        self.memo = {}
        try:
            yield
        finally:
            self.memo = None
