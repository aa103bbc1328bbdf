"""The leaderboard's cells: each rule against Adam on a scene, decided over its tuning studies by
the package's rule, read from the study folders or their kept evidence, and a cell as the page
prints it (experiments/leaderboard.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from evidence import keep_clock_verdicts, read_json  # experiments/
from leaderboard_detail import MARKS, WALL_FACTOR, wall_ratios
from leaderboard_figure import FEW_STEPS
from leaderboard_keep import checked_record
from leaderboard_scenes import BASELINE, EXPENSIVE, LONGER, SCENES, planned_studies
from study_runs import read_study
from tuned_settings import at_the_edge

from physgrad.readout import fmt
from physgrad.replication import across_studies, majority, over_studies
from physgrad.verdict import FRACTIONS, compare_variants, ratio_of


@dataclass(frozen=True)
class Cell:
    """A rule against Adam on one scene: the verdict over the tuning studies, the median ratio rule
    / Adam at the budget with its interval, seeds where the rule was lower, and each study's own
    verdict."""

    verdict: str
    ratio: float
    low: float
    high: float
    wins: int
    pairs: int
    studies: tuple[str, ...]
    iterations: float = math.nan
    detail: tuple = ()  # (k, the rule's PairVerdict in tuning study k) for the studies that ran it
    why: str = ""  # why the verdict over the studies is what it is (the package's rule)
    # the rule's runs' wall-clock time over Adam's at the same calibrated budget (median)
    wall_ratio: float = math.nan
    edge: int = 0  # the tuning studies whose tuned value sits at the edge of what they tried
    edge_of: int = 0  # of how many tuning studies (0: the cell's own)


def cells(runs, about: dict | None = None) -> dict[str, Cell]:
    """rule -> Cell for every rule the study ran, by the package's rule: each tuning study decided
    with Holm's correction over the comparisons with Adam of the rules it ran (compare.baseline),
    a "better" its compare found undecided by the clock kept so (the kept record's
    undecided_by_the_clock), then each rule over the studies that ran it
    (physgrad.replication.across_studies; a rule added to the leaderboard after a scene's first
    studies is decided over the later ones). Of a scene with fewer tuning studies kept than its
    protocol plans (about's `planned`: a re-run in progress), a verdict needs a majority of those
    planned, as a claim's does (physgrad.replication.over_studies), so that a cell of one study is
    not shown decided."""
    about = about or {}
    planned = int(about.get("planned") or 0)
    iterations = about.get("iterations")
    studies = runs.tuning or (runs,)
    ran = [sorted(r for r in study.paths if r != BASELINE) for study in studies]
    per_study = [
        dict(
            zip(
                rules,
                compare_variants(
                    {name: study.curves(name) for name in (*rules, BASELINE)},
                    runs.budget,
                    pairs=[(rule, BASELINE) for rule in rules],
                    fractions=FRACTIONS,
                ),
            )
        )
        if rules and BASELINE in study.paths
        else {}
        for study, rules in zip(studies, ran)
    ]
    keep_clock_verdicts(per_study, about.get("tuning_studies") or {})
    # a rule timed alone, else its seeds' share of their job against Adam's share of its own
    walls = {**wall_ratios(about, "wall_seconds_together"), **wall_ratios(about)}
    found = {}
    for rule in sorted({r for rules in ran for r in rules}):
        verdicts = [by_rule[rule] for by_rule in per_study if rule in by_rule]
        if not verdicts:
            continue
        result = across_studies([[v] for v in verdicts])[0]
        p = result.at[1.0]
        verdict, why = result.verdicts[1.0]
        if planned > len(studies):
            verdict, why = over_studies(
                [v.verdict for v in verdicts],
                need=majority(planned),
                medians=[v.at[1.0].median for v in verdicts],
            )
            why += f" ({len(verdicts)} of {planned} tuning studies run)"
        found[rule] = Cell(
            verdict,
            p.ratio,
            ratio_of(p.low),
            ratio_of(p.high),
            p.wins_a,
            p.pairs,
            tuple(s.verdicts[1.0][0] for s in (result.studies or [result])),
            (iterations or {}).get(rule, math.nan),
            tuple((k, by_rule[rule]) for k, by_rule in enumerate(per_study) if rule in by_rule),
            why,
            walls.get(rule, math.nan),
            at_the_edge(about.get("tuning_studies") or {}, rule),
        )
    return found


def board(root: Path, suffix: str = "") -> dict[str, tuple[dict[str, Cell], object, dict]]:
    """scene -> (its cells, its runs, its kept record) for every scene with runs under root (study
    folders or their kept evidence); with suffix LONGER_SUFFIX, its studies at the longer
    budget."""
    found = {}
    for entry in SCENES:
        runs = read_study(root / (entry.name + suffix))
        if runs is None:
            continue
        about_path = root / f"{entry.name}{suffix}.json"
        about = read_json(about_path) if about_path.is_file() else {}
        checked_record(root / (entry.name + suffix), runs, about, (BASELINE, *entry.rules))
        found[entry.name] = (cells(runs, about), runs, about)
    return found


def longer_lines(entry, found: tuple | None, budget: float, tuned: dict | None = None) -> list[str]:
    """A scene's expensive rules against Adam at LONGER times the budget, at the settings tuned at
    the budget (its <scene>_longer evidence): each rule's cell and its steps there, with the edge
    of its tuning from its cell at the budget (tuned: rule -> Cell)."""
    if found is None:
        return []
    longer, runs, _ = found
    tuned = tuned or {}
    said = [
        # its settings' tuning is the budget's: the edge of the tuning studies there
        f"{rule} "
        + cell_text(
            replace(cell, edge=tuned[rule].edge, edge_of=len(tuned[rule].studies))
            if rule in tuned
            else cell,
            planned_studies(runs),
        )
        + (f", {cell.iterations:,.0f} steps" if math.isfinite(cell.iterations) else "")
        for rule, cell in sorted(longer.items())
    ]
    return [
        f"  At {LONGER}x the budget ({LONGER * budget:g} s; the rules whose step costs more than "
        f"{EXPENSIVE:g} of Adam's, at the settings tuned at the budget, on the same seeds; "
        f"{len(runs.tuning or (runs,))} of {planned_studies(runs)} studies): "
        + "; ".join(said)
        + "."
    ]


def cell_text(cell: Cell, scene_studies: int = 0, to: str = "", planned: int = 0) -> str:
    """A cell as the table prints it, its verdict a link to its scene's page (to) where given;
    with the tuning studies that ran the rule where they are fewer than the scene's, and each
    study's verdict where fewer than the `planned` have run."""
    mark = MARKS.get(cell.verdict, "undecided")
    fewer = len(cell.studies) < scene_studies
    edge_of = cell.edge_of or len(cell.studies)
    so_far = ", ".join(MARKS.get(v, "undecided") for v in cell.studies)
    return (
        (f"[**{mark}**]({to})" if to else f"**{mark}**")
        + f" {fmt(cell.ratio)}x [{fmt(cell.low)}, {fmt(cell.high)}], {cell.wins}/{cell.pairs}"
        + (f" ({len(cell.studies)} of {scene_studies} studies ran it)" if fewer else "")
        + (
            f" ({len(cell.studies)} of {planned} studies run: {so_far})"
            if len(cell.studies) < planned
            else ""
        )
        + few_steps(cell.iterations)
        + (
            f", tuned at the edge of what its trials tried in {cell.edge} of {edge_of} studies "
            "(the best setting may lie beyond)"
            # in most of 2 or more studies: one edge among 8 quasi-random points is common
            if edge_of > 1 and cell.edge >= majority(max(planned, scene_studies, edge_of))
            else ""
        )
        + (
            f", its runs {cell.wall_ratio:.2g}x Adam's wall-clock time"
            if not 1 / WALL_FACTOR < cell.wall_ratio < WALL_FACTOR  # NaN: not recorded
            and math.isfinite(cell.wall_ratio)
            else ""
        )
    )


def few_steps(iterations: float) -> str:
    """What a cell decided on fewer than FEW_STEPS steps says: the steps that ended within the
    budget (a run's last step crosses it, and its loss is read before that step: docs/protocol.md,
    section 6), and where none did, that the cell compares Adam with the untrained network."""
    if not iterations < FEW_STEPS:
        return ""
    within = math.floor(iterations - 1)  # a median over the runs can be a half
    if within < 1:
        return (
            ", no step within the budget (its first ends after it): Adam against the untrained "
            "network, a step's cost and not the rule"
        )
    plural = "" if within == 1 else "s"
    return f", {within:.0f} step{plural} within the budget: decided by a step's cost, not the rule"
