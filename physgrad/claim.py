"""A paper's claim decided by physgrad's rules: its parts (A lower than B, A close to B, A's
advantage grows from an easy setting to a hard one, A stalls, A reaches a level), each decided from
a study's evaluation runs at a fraction of its budget, in each tuning study and then over them
(physgrad.replication.over_studies: a majority of the studies planned, none against).

- "A lower than B": the paired verdict (Holm over the study's comparisons), A better holds it,
  B better or equivalent goes against it;
- "A close to B": A better or equivalent within the stated margin holds it, B better goes against;
- "A's advantage over B grows": physgrad.trend.interaction on the two settings' per-seed log
  ratios;
- "A stalls": its loss at the budget against its loss at half the budget, paired by seed,
  equivalent within the margin (neither still falling nor rising);
- "A reaches a level": the seeds below it, by the sign test (physgrad.claim_words.against_level).
A claim holds if every part holds, does not hold if one does not, and is not settled otherwise.
This module holds the parts and decides the pairs; physgrad.claim_parts the trends, stalls and
levels, and a claim's verdict from its parts.

The runs a part is read from are any object with the study's `budget`, `axis`, `folder`, `paths`
(variant -> seed -> where), `curves(variant, column)` (seed -> physgrad.readout.Curve), its
repeated tuning studies in `tuning` and the number it is to have in `planned`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from physgrad.claim_words import (
    LEANS_AGAINST,
    SEEDS_DISAGREE,
    STUDIES_DISAGREE,
    STUDIES_TO_RUN,
    TUNING_LUCK,
)
from physgrad.paired_stats import Paired
from physgrad.readout import fmt
from physgrad.replication import (
    STUDY_ALPHA,
    across_studies,
    between_studies,
    majority,
    over_studies,
)
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    FRACTIONS,
    MARGIN,
    PairVerdict,
    compare_variants,
    paired,
    ratio_of,
)

HOLDS, FAILS, OPEN = "holds", "does not hold", "not settled"
# a part whose variants the study does not have (the presets' twin of a clipping sweep)
NOT_RUN = "not run"


class Runs(Protocol):
    """A study's evaluation runs, as the parts read them."""

    folder: Path
    axis: str
    budget: float
    paths: dict  # variant -> seed -> where its run is
    tuning: tuple  # with repeated tuning studies: each one's runs, the first included
    planned: int  # the tuning studies the study is to have (0: those it has)

    def curves(self, variant: str, column: str = "loss") -> dict: ...


# --- the parts
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lower:
    """A reaches a lower held-out `column` than B at the budget of `study` (variant names as compare
    gives them)."""

    study: str
    a: str
    b: str
    column: str = "loss"

    def text(self) -> str:
        return f"{self.a} below {self.b}" + (f" ({self.column})" if self.column != "loss" else "")


@dataclass(frozen=True)
class Close:
    """A is better than B or within `margin` of it (equivalence at that margin)."""

    study: str
    a: str
    b: str
    margin: float

    def text(self) -> str:
        return f"{self.a} within {100 * (self.margin - 1):.0f}% of {self.b} (or below)"


@dataclass(frozen=True)
class Grows:
    """A's advantage over B (loss A / B) is larger in study `hard` than in study `easy`."""

    easy: str
    hard: str
    a: str
    b: str

    def text(self) -> str:
        return f"{self.a} / {self.b} lower at {self.hard} than at {self.easy}"


@dataclass(frozen=True)
class Stalls:
    """The variant's `column` at the budget is within the margin of its value at half the budget."""

    study: str
    variant: str
    column: str = "loss"

    def text(self) -> str:
        return f"{self.variant} stalls ({self.column}: budget vs half of it)"


@dataclass(frozen=True)
class Reaches:
    """The variant's `column` at the budget lies below an absolute level (the seeds below it, by
    the package's sign test, physgrad.claim_words.against_level); with above, at or above it (a
    loss that stays above a level the book names, hidden units that saturate)."""

    study: str
    variant: str
    level: float
    column: str = "loss"
    above: bool = False

    def text(self) -> str:
        side = "stays at or above" if self.above else "reaches"
        return f"{self.variant} {side} {self.column} {'' if self.above else 'below '}{self.level:g}"


Part = Lower | Close | Grows | Stalls | Reaches


@dataclass(frozen=True)
class Claim:
    name: str
    paper: str  # the claim as the paper states it, and where
    parts: tuple
    note: str = ""  # how the comparison is made, where it departs from the paper's
    # the paper's training: iterations, or seconds of training time on the paper's hardware
    # (paper_seconds); nan: not stated as a number
    paper_budget: float = math.nan
    paper_budget_text: str = "-"
    paper_seconds: bool = False
    # whose budget paper_budget is, where the paper states none and its reference code does
    budget_of: str = "the paper's"
    # where physgrad's scene or comparison departs from the paper's in a way that matters: how
    # (the claim's word is then "different setup", physgrad.claim_words.claim_word)
    departs: str = ""
    own: bool = False  # physgrad's own question, not a claim of the papers: its own table


@dataclass(frozen=True)
class Decision:
    verdict: str  # HOLDS, FAILS, OPEN
    measured: str  # the numbers: median ratio [interval], k of n, ...
    why: str
    # where OPEN: why it is not settled, if the evidence shows it (claim_words.SEEDS_DISAGREE or
    # STUDIES_DISAGREE, and what it shows)
    cause: tuple[str, str] = ("", "")


def fraction_text(fraction: float) -> str:
    """1/4 of the budget: "X/4"; the budget: "X"."""
    if fraction == 1.0:
        return "X"
    whole = round(1 / fraction)
    return f"X/{whole}" if math.isclose(whole * fraction, 1.0) else f"{fraction:g} X"


def _compare_group(runs: Runs, group: list, column: str, margin: float, fractions: tuple) -> list:
    """The parts of one study that read one column at one margin, compared together (Holm's
    correction over them): each tuning study decided alone, then over the studies by the package's
    rule (physgrad.replication.across_studies); one result per part, in the group's order."""
    names = {v for p in group for v in (p.a, p.b)}
    per_study = [
        compare_variants(
            {n: study.curves(n, column) for n in names},
            runs.budget,
            pairs=[(p.a, p.b) for p in group],
            margin=margin,
            fractions=fractions,
        )
        for study in (runs.tuning or (runs,))
    ]
    return across_studies(per_study)


def decide_pairs(runs: Runs, parts: list, fraction: float = 1.0) -> list[Decision]:
    """The Lower and Close parts of one study at `fraction` of its budget, with Holm's correction
    over them."""
    fractions = tuple(sorted({*FRACTIONS, fraction}))
    decisions = []
    present = [p for p in parts if p.a in runs.paths and p.b in runs.paths]
    compared: dict[tuple, list] = {}  # (column, margin) -> the group's results, Holm over it
    for part in parts:
        if part not in present:
            missing = [n for n in (part.a, part.b) if n not in runs.paths]
            decisions.append(
                Decision(NOT_RUN, "-", f"no runs of {' and '.join(missing)} in {runs.folder}")
            )
            continue
        group = (getattr(part, "column", "loss"), getattr(part, "margin", MARGIN))
        others = [
            p
            for p in present
            if (getattr(p, "column", "loss"), getattr(p, "margin", MARGIN)) == group
        ]
        if group not in compared:  # the group's comparisons once: every part of it reads them
            compared[group] = _compare_group(runs, others, *group, fractions)
        result = compared[group][others.index(part)]
        p = result.at[fraction]
        found = [v.verdicts[fraction] for v in (result.studies or [result])]
        claim, why = _over_studies(
            [_pair_outcome(part, verdict) for verdict, _ in found],
            [f"{verdict}: {why}" for verdict, why in found],
            [verdict for verdict, _ in found],
            runs.planned,
        )
        if claim == HOLDS and isinstance(part, Lower) and result.studies:
            # "A lower" is "A better" over the studies, by the whole rule: every median on its
            # side and the studies taken as draws (physgrad.replication.across_studies)
            combined, reason = result.verdicts[fraction]
            if combined != A_BETTER:
                claim, why = OPEN, reason
        diverged = "".join(
            f"; {name} diverged in {k} of {p.seeds}"
            for name, k in ((part.a, p.diverged_a), (part.b, p.diverged_b))
            if k
        )
        earlier = "; ".join(
            f"at {fraction_text(f)} {fmt(result.at[f].ratio)} ({result.verdicts[f][0]})"
            for f in fractions
            if f < fraction
        )
        measured = (
            f"{part.a} / {part.b} = {_ratio_said(p, part.a, part.b)} "
            f"[{fmt(ratio_of(p.low))}, {fmt(ratio_of(p.high))}], "
            f"{part.a} lower in {p.wins_a} of {p.pairs}{diverged}"
            + (f"; {earlier}" if earlier else "")
            + (f"; over {len(runs.tuning)} tuning studies" if runs.tuning else "")
        )
        cause = (
            (studies_to_run(runs) or _pair_cause(part, result, fraction))
            if claim == OPEN
            else ("", "")
        )
        decisions.append(Decision(claim, measured, why, cause))
    return decisions


def _pair_cause(part: Lower | Close, result: PairVerdict, fraction: float) -> tuple[str, str]:
    """Why a pair part is not settled, where the evidence says: the tuning studies reached
    opposite outcomes (STUDIES_DISAGREE); they agree, but taken as one draw each their interval
    (Hartung-Knapp at 1 - STUDY_ALPHA) still holds a ratio of 1, so tuning luck could have made
    them agree (TUNING_LUCK); a study went against the claim and none for it (LEANS_AGAINST); the
    pooled median on the claim's side with a tenth or more of the seeds against it or the claimed
    winner diverged on some (SEEDS_DISAGREE, with the counts); else none (the budget or the
    seeds' number)."""
    studies = result.studies or [result]
    verdicts = [v.verdicts[fraction][0] for v in studies]
    outcomes = {_pair_outcome(part, v) for v in verdicts}
    listed = f"{part.a} vs {part.b} in {len(studies)} tuning studies: {', '.join(verdicts)}"
    p = result.at[fraction]
    seeds = f"{part.a} lower in {p.wins_a} of {p.pairs} seeds"
    if {HOLDS, FAILS} <= outcomes:
        return STUDIES_DISAGREE, listed
    if "taken as draws" in result.verdicts[fraction][1]:
        draws = between_studies([v.at[fraction].median for v in studies])
        return TUNING_LUCK, (
            f"{listed}; taken as draws, {fmt(ratio_of(draws.mean))} "
            f"[{fmt(ratio_of(draws.low))}, {fmt(ratio_of(draws.high))}] "
            f"({100 * (1 - STUDY_ALPHA):.0f}% interval, Hartung-Knapp), which holds 1"
        )
    if FAILS in outcomes:
        return LEANS_AGAINST, f"{listed}; {seeds}"
    against = p.pairs - p.wins_a
    if (
        not isinstance(part, Close)
        and p.median < 0
        and (against >= max(1, p.pairs / 10) or p.diverged_a)
    ):
        return SEEDS_DISAGREE, (
            f"{seeds} ({against} against)"
            + (f", diverged in {p.diverged_a}" if p.diverged_a else "")
        )
    return "", ""


def _ratio_said(p: Paired, a: str, b: str) -> str:
    """The median ratio A / B, saying why where a divergence makes it 0 or inf (the median seed's
    B or A diverged), so that "0" is not read as a measured ratio."""
    if p.ratio == 0 and p.diverged_b:
        return f"0 (the median seed's {b} diverged)"
    if math.isinf(p.ratio) and p.diverged_a:
        return f"inf (the median seed's {a} diverged)"
    return fmt(p.ratio)


def _pair_outcome(part: Lower | Close, verdict: str) -> str:
    """What a pair's verdict says of a Lower part (A better: holds; B better or equivalent: does
    not hold) or a Close part (A better or equivalent: holds; B better: does not hold)."""
    if isinstance(part, Close):
        return {A_BETTER: HOLDS, EQUIVALENT: HOLDS, B_BETTER: FAILS}.get(verdict, OPEN)
    return {A_BETTER: HOLDS, EQUIVALENT: FAILS, B_BETTER: FAILS}.get(verdict, OPEN)


def log_ratios_at_budget(runs: Runs, a: str, b: str, fraction: float = 1.0) -> list[float]:
    ca, cb = runs.curves(a), runs.curves(b)
    seeds = sorted(set(ca) | set(cb))
    x = runs.budget * fraction
    p = paired(
        [ca[s].at(x) if s in ca else math.nan for s in seeds],
        [cb[s].at(x) if s in cb else math.nan for s in seeds],
    )
    return list(p.log_ratios)


def studies_to_run(runs: Runs) -> tuple[str, str] | None:
    """Why a part is not settled while tuning studies of the study are still to run
    (STUDIES_TO_RUN, with how many have run): what the seeds of those run show is not yet the
    study's; None when every planned study has run."""
    ran = len(tuning_studies(runs))
    if runs.planned > ran:
        return STUDIES_TO_RUN, f"{ran} of {runs.planned} tuning studies run"
    return None


def tuning_studies(runs: Runs) -> tuple:
    """Each tuning study's runs (the study itself where it has one)."""
    return runs.tuning or (runs,)


def _over_studies(
    outcomes: list[str], whys: list[str], verdicts: list[str], planned: int = 0
) -> tuple[str, str]:
    """A part's outcome (holds, does not hold, not settled) from each tuning study's, with why:
    one study's as it is; several by the package's rule over tuning studies
    (physgrad.replication.over_studies: a majority, none against) applied to what each study's
    verdict says of the part, so that two verdicts that both support it (A better and equivalent,
    for "A close to B") do not count as a disagreement; why lists each study's verdict. Of a study
    with `planned` tuning studies of which fewer have run, the majority is of those planned."""
    if len(outcomes) == 1 and planned <= 1:
        return outcomes[0], whys[0]
    found, why = over_studies(
        outcomes, undecided=OPEN, labels=verdicts, need=majority(max(planned, len(outcomes)))
    )
    if planned > len(outcomes):
        why += f" ({len(outcomes)} of {planned} tuning studies run)"
    return found, why


def studies_of(claim: Claim) -> set[str]:
    """The studies a claim's parts are read from."""
    return {
        name
        for part in claim.parts
        for name in ([part.easy, part.hard] if isinstance(part, Grows) else [part.study])
    }


def claim_of_part(part: Part) -> Claim:
    """The claim of one part (to decide it alone)."""
    return Claim("", "", (part,))
