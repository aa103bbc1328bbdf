"""The leaderboard: every update rule of physgrad against Adam on the same physics-in-the-loop
scenes, at equal calibrated time, decided by `physgrad compare`'s own protocol
(docs/leaderboard.md).

Each scene is one `physgrad compare` of Adam and every rule that applies to it, with
compare.baseline=adam (each rule compared with Adam alone: Holm's correction over those
comparisons): every rule tuned on the same trial points in each of LEADERBOARD_STUDIES independent
tuning studies, evaluated on LEADERBOARD_SEEDS paired seeds per study, the budget the same number of
calibrated seconds for every rule (its iterations: budget / the rule's calibrated step cost). A
cell is the package's verdict over the tuning studies (physgrad.replication.across_studies) and the
median ratio rule / Adam of the test loss at the budget with its interval.

Usage (from the repository's root):
  make reproduce-figures PROFILE=leaderboard ARGS=--plan     # the parts and their expected time
  make reproduce-figures PROFILE=leaderboard ARGS="--part 1" # one part (resumable)
  python experiments/leaderboard.py --keep outputs/experiments/leaderboard docs/evidence/leaderboard
  python experiments/leaderboard.py docs/evidence/leaderboard docs  # docs/leaderboard.md and .png
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from evidence import (  # experiments/
    CLOCK,
    keep_clock_verdicts,
    read_json,
)
from leaderboard_detail import (
    FOLDER,
    MARKS,
    link,
    preset_line,
    scene_notes,
    scene_page,
    scheduled_cost_line,
    wall_line,
)
from leaderboard_figure import FEW_STEPS, plot
from leaderboard_keep import checked_record, keep
from leaderboard_scenes import (
    BASELINE,
    LEADERBOARD_SEEDS,
    LEADERBOARD_STUDIES,
    LEADERBOARD_TRIALS,
    LITERATURE,
    RERUN,
    RULES,
    SCENES,
    WHY_IT_MAY_DIFFER,
    planned_studies,
)
from scene_kinds import KINDS, both_pages_line, kinds_table, read_kinds
from study_runs import read_study
from tuned_settings import tuned_table

from physgrad.errors import UserError
from physgrad.files import clean_text, make_folder, replace_file
from physgrad.readout import fmt
from physgrad.replication import across_studies
from physgrad.verdict import (
    FRACTIONS,
    MARGIN,
    compare_variants,
    ratio_of,
)

# --- the cells
# -------------------------------------------------------------------------------------------


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


def cells(runs, about: dict | None = None) -> dict[str, Cell]:
    """rule -> Cell for every rule the study ran, by the package's rule: each tuning study decided
    with Holm's correction over the comparisons with Adam of the rules it ran (compare.baseline),
    a "better" its compare found undecided by the clock kept so (the kept record's
    undecided_by_the_clock), then each rule over the studies that ran it
    (physgrad.replication.across_studies; a rule added to the leaderboard after a scene's first
    studies is decided over the later ones)."""
    about = about or {}
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
    found = {}
    for rule in sorted({r for rules in ran for r in rules}):
        verdicts = [by_rule[rule] for by_rule in per_study if rule in by_rule]
        if not verdicts:
            continue
        result = across_studies([[v] for v in verdicts])[0]
        p = result.at[1.0]
        found[rule] = Cell(
            result.verdict,
            p.ratio,
            ratio_of(p.low),
            ratio_of(p.high),
            p.wins_a,
            p.pairs,
            tuple(s.verdicts[1.0][0] for s in (result.studies or [result])),
            (iterations or {}).get(rule, math.nan),
            tuple((k, by_rule[rule]) for k, by_rule in enumerate(per_study) if rule in by_rule),
        )
    return found


def board(root: Path) -> dict[str, tuple[dict[str, Cell], object, dict]]:
    """scene -> (its cells, its runs, its kept record) for every scene with runs under root (study
    folders or their kept evidence)."""
    found = {}
    for entry in SCENES:
        runs = read_study(root / entry.name)
        if runs is None:
            continue
        about_path = root / f"{entry.name}.json"
        about = read_json(about_path) if about_path.is_file() else {}
        checked_record(root / entry.name, runs, about, (BASELINE, *entry.rules))
        found[entry.name] = (cells(runs, about), runs, about)
    return found


# --- the page
# --------------------------------------------------------------------------------------------


def cell_text(cell: Cell, scene_studies: int = 0, to: str = "") -> str:
    """A cell as the table prints it, its verdict a link to its scene's page (to) where given;
    with the tuning studies that ran the rule where they are fewer than the scene's."""
    mark = MARKS.get(cell.verdict, "undecided")
    fewer = len(cell.studies) < scene_studies
    return (
        (f"[**{mark}**]({to})" if to else f"**{mark}**")
        + f" {fmt(cell.ratio)}x [{fmt(cell.low)}, {fmt(cell.high)}], {cell.wins}/{cell.pairs}"
        + (f" ({len(cell.studies)} of {scene_studies} studies ran it)" if fewer else "")
        + (
            f", {cell.iterations:.0f} steps: decided by a step's cost, not the rule"
            if cell.iterations < FEW_STEPS
            else ""
        )
    )


def protocol_text(found: dict) -> str:
    """The protocol the scenes' kept studies ran, as their records say: the tuning studies planned,
    whether the rules' own knobs were tuned beside the learning rate (compare.knobs), and whether
    line searches were charged per evaluation."""
    planned = max((planned_studies(runs) for _, runs, _ in found.values()), default=0)
    planned = planned or LEADERBOARD_STUDIES
    abouts = [about for *_, about in found.values()]
    knobs = bool(abouts) and all(about.get("knobs") for about in abouts)
    per_evaluation = any(
        record.get("charged_by_evaluations")
        for about in abouts
        for record in (about.get("tuning_studies") or {}).values()
    )
    return (
        f"{LEADERBOARD_TRIALS} trial points "
        + ("of the learning rate and the rule's knobs" if knobs else "of the learning rate")
        + f" per rule in each of {planned} independent tuning "
        f"studies, {LEADERBOARD_SEEDS} paired evaluation seeds per study, the verdict over the "
        f"studies by the package's rule (a majority of the {planned}, none against, and the "
        "studies as draws excluding 1"
        + (
            "; `physgrad compare` and the claims run 4 studies, so a verdict here rests on fewer"
            if planned < 4
            else ""
        )
        + ") with Holm's correction over each scene's comparisons with Adam "
        "(`compare.baseline=adam`). "
        + (
            "Each rule is tuned on its own knobs beside its learning rate (`compare.knobs=true`: "
            "docs/protocol.md lists them and their ranges), a knob that changes a step's cost "
            "charged at its value."
            if knobs
            else "Only the learning rate is tuned; every other setting stays at its preset (the "
            "rules' own knobs, tuned, are not tested here)."
        )
        + (
            " Line searches are charged the evaluations they made."
            if per_evaluation
            else " Line searches are charged each step's calibrated cost, whatever evaluations "
            "they made (the wall-clock ratios below)."
        )
    )


def page(found: dict, image: str, root: Path | None = None) -> str:
    """docs/leaderboard.md's text (root: the evidence, whose kept calibrations give the scenes'
    step costs)."""
    lines = [
        "# Leaderboard: which update rule, for which physics",
        "",
        "<!-- generated by experiments/leaderboard.py from docs/evidence/leaderboard: do not "
        "edit -->",
        "",
        "Every rule against Adam on the same scenes, each tuned and evaluated by `physgrad "
        "compare`'s protocol (docs/protocol.md) at the same calibrated training time: "
        + protocol_text(found)
        + " A cell: the "
        "verdict (a link to the scene's tuning studies one by one), the median ratio of the "
        "rule's test loss to Adam's at the budget with its interval, and the seeds where the rule "
        "was lower. Below 1: the rule reached a lower loss; "
        f"better and worse mean beyond a factor {MARGIN:g}, equivalent within it "
        "(docs/protocol.md).",
        "",
        f"![leaderboard]({image})",
        "",
    ]
    scenes = [e for e in SCENES if e.name in found]
    missing = [e for e in SCENES if e.name not in found]
    if scenes:
        lines += [
            "| rule | " + " | ".join(e.title for e in scenes) + " |",
            "|---|" + "---|" * len(scenes),
        ]
        for rule in RULES:
            row = []
            for entry in scenes:
                cell, runs = found[entry.name][0].get(rule), found[entry.name][1]
                if rule in entry.refused:
                    row.append(f"n/a: {entry.refused[rule]}")
                else:
                    ran = len(runs.tuning or (runs,))
                    row.append(cell_text(cell, ran, link(entry.name, rule)) if cell else "not run")
            lines.append(f"| {rule} | " + " | ".join(row) + " |")
        lines += ["", "## The scenes and their budgets", "", *scene_kind_lines(scenes, root), ""]
        for entry in scenes:
            lines += scene_budget_lines(entry, *found[entry.name][1:])
        scheduled = scheduled_cost_line(
            {e.name: found[e.name][2] for e in scenes}, {e.name: e.title for e in scenes}
        )
        lines += [
            *(("", scheduled) if scheduled else ()),
            "",
            "A verdict holds for the machine its scene was calibrated on: the budget is a time, "
            "and each rule's iterations in it follow from its step cost there. A GPU changes those "
            "costs against Adam's (on one H200 a Jacobian or dense quasi-Newton step on the "
            "oscillators costs 4 to 5 times fewer of Adam's than on 2 cores: docs/benchmarks.md, "
            '"On a GPU"); to answer for a GPU, run the profile there.',
        ]
    if missing:
        lines += [
            "",
            "Not run yet: " + ", ".join(f"{e.title} (`{e.name}`)" for e in missing) + ".",
        ]
    return "\n".join(lines + literature_lines(found)) + "\n"


LEADERBOARD_KINDS = {
    "ks": "ks_small"
}  # a scene's name here -> its row in scenes.csv, where it differs


def scene_kind_lines(scenes, root: Path | None) -> list[str]:
    """What kind of problem each scene is (experiments/scene_kinds.py), and why a scene on both
    this page and the claims' may have other verdicts there."""
    rows = [
        (
            LEADERBOARD_KINDS.get(e.name, e.name),
            e.title,
            root / CLOCK.format(name=e.name) if root is not None else None,
        )
        for e in scenes
    ]
    return [kinds_table(rows, read_kinds(KINDS)), both_pages_line("leaderboard")]


def scene_budget_lines(entry, runs, about: dict) -> list[str]:
    """A scene's item under "The scenes and their budgets": its overrides, budget, studies run and
    machine; each rule's iterations in the budget; its per-rule presets; its clocks' notes."""
    lines = []
    studies = len(runs.tuning or (runs,))
    its = about.get("iterations") or {}
    clock = "calibrated clock" if runs.axis == "calibrated_time" else runs.axis
    budget = f"{runs.budget:g} s ({clock})"
    lines.append(
        f"- **{entry.title}** (`{' '.join(entry.overrides)}`): {budget}; "
        f"{studies} of {planned_studies(runs)} tuning studies finished"
        + (
            " (its verdicts are those of the studies run so far: preliminary)"
            if studies < planned_studies(runs)
            else ""
        )
        + (f"; on {runs.machine}" if runs.machine else "")
        + "."
    )
    if its:
        lines.append(
            "  Iterations in the budget (median over the runs that reached it): "
            + ", ".join(f"{v} {its[v]:.0f}" for v in (BASELINE, *entry.rules) if v in its)
            + "."
        )
    presets, wall = preset_line(entry), wall_line(about)
    lines += [f"  {presets}"] if presets else []
    lines += [f"  {wall}"] if wall else []
    lines += [f"  {note}" for note in scene_notes(about)]
    return lines


def literature_lines(found: dict) -> list[str]:
    """What the rules' papers report on the leaderboard's problems, beside the cells measured
    here and the iterations the budget gave the rule and Adam (the papers compare at equal
    iterations)."""
    titles = {e.name: e.title for e in SCENES}
    lines = ["", "## What the literature reports, and the same rules here", ""]
    for claim, where in LITERATURE:
        measured = []
        for scene, rule in where:
            cell, _, about = found.get(scene, ({}, None, {}))
            cell = cell.get(rule)
            adam = (about.get("iterations") or {}).get(BASELINE, math.nan)
            its = (
                f" ({cell.iterations:,.0f} iterations in the budget, Adam {adam:,.0f})"
                if cell and math.isfinite(cell.iterations) and math.isfinite(adam)
                else ""
            )
            measured.append(
                f"{rule} on {titles[scene]}: " + (cell_text(cell) + its if cell else "not run yet")
            )
        lines.append(f"- {claim} In physgrad's setting: " + "; ".join(measured) + ".")
    return lines + ["", WHY_IT_MAY_DIFFER]


def rerun_text(root: Path) -> str:
    """The section on the re-run under the profile's current protocol, whose studies are kept in
    root (docs/evidence/leaderboard/rerun) until every scene has all of them: what the protocol
    is, each scene's studies kept, and the cells of those (preliminary); "" without such a
    folder."""
    if not root.is_dir():
        return ""
    found = board(root)
    lines = [
        "",
        "## The re-run under the current protocol (in progress)",
        "",
        f"The profile now runs {LEADERBOARD_STUDIES} tuning studies a scene, each rule tuned on "
        "its own knobs beside its learning rate (`compare.knobs=true`), every scene on a clock "
        "measured afresh that charges a line search its evaluations and a knob that changes a "
        "step's cost its cost at the tuned value (docs/protocol.md). Its studies are kept in "
        "docs/evidence/leaderboard/rerun; the table above moves to them once every scene has "
        "all of its studies, and until then the cells below are preliminary.",
        "",
    ]
    kept = {name: len(runs.tuning or (runs,)) for name, (_, runs, _) in found.items()}
    progress = [f"{e.title}: {kept.get(e.name, 0)} of {LEADERBOARD_STUDIES}" for e in SCENES]
    lines.append("Studies kept: " + "; ".join(progress) + ".")
    scenes = [e for e in SCENES if e.name in found]
    if scenes:
        lines += [
            "",
            "| rule | " + " | ".join(e.title for e in scenes) + " |",
            "|---|" + "---|" * len(scenes),
        ]
        for rule in RULES:
            row = [
                f"n/a: {e.refused[rule]}"
                if rule in e.refused
                else (
                    cell_text(found[e.name][0][rule], kept[e.name])
                    if rule in found[e.name][0]
                    else "not run"
                )
                for e in scenes
            ]
            lines.append(f"| {rule} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def write(root: Path, out: Path) -> str:
    """leaderboard.md and leaderboard.png (and .pdf) in out, from kept evidence under root or from
    the study folders under root (kept first, into a temporary folder); returns the markdown."""
    if any((root / entry.name).is_dir() for entry in SCENES):
        import tempfile

        with tempfile.TemporaryDirectory() as evidence:
            keep(root, Path(evidence))
            return write(Path(evidence), out)
    found = board(root)
    make_folder(out)  # through the write door: a link planted at the folder is refused
    if found:
        plot(found, out / "leaderboard")
    text = page(found, "leaderboard.png", root) + tuned_table(root) + rerun_text(root / RERUN.name)
    # through the write door: a link at a page's name, or at its folder, is not written through
    replace_file(out / "leaderboard.md", text.encode())
    make_folder(out / FOLDER)
    for entry in (e for e in SCENES if e.name in found):
        page_text = scene_page(entry, *found[entry.name])
        replace_file(out / FOLDER / f"{entry.name}.md", page_text.encode())
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python experiments/leaderboard.py")
    parser.add_argument("root", help="the study folders, or their kept evidence")
    parser.add_argument("out", nargs="?", default="docs")
    parser.add_argument("--keep", action="store_true", help="keep root's evidence in OUT")
    options = parser.parse_args(argv)
    try:
        if options.keep:
            kept = keep(Path(options.root), Path(options.out))
            print(f"leaderboard: kept {', '.join(kept) or 'nothing (no finished study)'}")
            return 0
        write(Path(options.root), Path(options.out))
    except UserError as error:  # evidence or a study folder that is not what it says: one line
        print(f"leaderboard: error: {clean_text(str(error), None)}", file=sys.stderr)
        return 2
    except OSError as error:  # a link planted at a folder the page goes into, a read-only disk
        print(f"leaderboard: error: {clean_text(str(error), 300)}", file=sys.stderr)
        return 2
    print(f"leaderboard: wrote {Path(options.out) / 'leaderboard.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
