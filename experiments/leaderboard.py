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
from pathlib import Path

from evidence import (  # experiments/
    CLOCK,
)
from leaderboard_cells import board, cell_text, longer_lines
from leaderboard_detail import (
    FOLDER,
    link,
    preset_line,
    scene_notes,
    scene_page,
    scheduled_cost_line,
    wall_line,
)
from leaderboard_figure import plot
from leaderboard_keep import keep
from leaderboard_scenes import (
    BASELINE,
    EXPENSIVE,
    LEADERBOARD,
    LEADERBOARD_SEEDS,
    LEADERBOARD_STUDIES,
    LEADERBOARD_TRIALS,
    LITERATURE,
    LONGER,
    LONGER_SUFFIX,
    RERUN,
    RULES,
    SCENES,
    WHY_IT_MAY_DIFFER,
    kept_clock,
    planned_studies,
    where_scene_runs,
)
from scene_kinds import KINDS, both_pages_line, kinds_table, read_kinds
from tuned_settings import tuned_table

from physgrad.errors import UserError
from physgrad.files import clean_text, make_folder, replace_file
from physgrad.replication import majority
from physgrad.verdict import (
    MARGIN,
)

# --- the page
# --------------------------------------------------------------------------------------------


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
        "studies as draws excluding 1 at 99%, so that a cell can stay undecided with every study "
        "worse or better where their sizes differ: its scene page says why"
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


def page(found: dict, image: str, root: Path | None = None, longer: dict | None = None) -> str:
    """docs/leaderboard.md's text (root: the evidence, whose kept calibrations give the scenes'
    step costs; longer: the scenes' studies at the longer budget, board(root, LONGER_SUFFIX))."""
    lines = [
        "# Leaderboard: which update rule, for which physics",
        "",
        "<!-- generated by experiments/leaderboard.py from docs/evidence/leaderboard: do not "
        "edit -->",
        "",
        *earlier_protocol_banner(root),
        "Every rule against Adam on the same scenes, each tuned and evaluated by `physgrad "
        "compare`'s protocol (docs/protocol.md) at the same calibrated training time: "
        + protocol_text(found)
        + " A cell: the "
        "verdict (a link to the scene's tuning studies one by one), the median ratio of the "
        "rule's test loss to Adam's at the budget with the span of its studies' 95% intervals "
        "(lowest low to highest high, descriptive), and the seeds where the rule "
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
            lines += longer_lines(entry, (longer or {}).get(entry.name), entry.budget)
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
            "Not run yet: "
            + ", ".join(f"{e.title} (`{e.name}`: {where_scene_runs(e)})" for e in missing)
            + ".",
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
            f" (preliminary: a verdict needs {majority(planned_studies(runs))} of the "
            f"{planned_studies(runs)}, and each study's verdict so far is said beside it)"
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


def earlier_protocol_banner(root: Path | None) -> list[str]:
    """The lines that head the page while its table is from the earlier protocol, because the
    re-run under the current one (kept in root/rerun) has not finished every scene; none
    otherwise."""
    if root is None or not (root / RERUN.name).is_dir():
        return []
    found = board(root / RERUN.name)
    kept = sum(len(runs.tuning or (runs,)) for _, runs, _ in found.values())
    return [
        "**The table and figure below are from an earlier protocol**: 3 tuning studies a scene, "
        "the learning rate alone tuned, and a line search charged what the first steps cost. "
        f"The re-run under the current protocol ({LEADERBOARD_STUDIES} tuning studies, each rule "
        "tuned on its own knobs, line-search evaluations charged) has kept "
        f"{kept} of {LEADERBOARD_STUDIES * len(SCENES)} studies so far (its section at the end); "
        "until it has all of them, a cell here is the earlier protocol's.",
        "",
    ]


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
        "all of its studies"
        + (
            ", and until then the cells below are preliminary: a cell is decided when "
            f"{majority(LEADERBOARD_STUDIES)} of the {LEADERBOARD_STUDIES} studies agree, none "
            "against, as a claim is, and each kept study's verdict is said beside it."
            if found
            else "."
        ),
        "",
    ]
    kept = {name: len(runs.tuning or (runs,)) for name, (_, runs, _) in found.items()}
    progress = [f"{e.title}: {kept.get(e.name, 0)} of {LEADERBOARD_STUDIES}" for e in SCENES]
    expensive = {e.title: e.expensive(kept_clock(e, root)) for e in SCENES}
    hours = sum(study.seconds() for study in LEADERBOARD) / 3600
    lines += [
        "Studies kept: " + "; ".join(progress) + ".",
        "",
        f"Read again at {LONGER}x the budget (a step above {EXPENSIVE:g} of Adam's on the scene's "
        "clock, at the settings tuned at the budget: docs/protocol.md, section 7): "
        + "; ".join(f"{title}: {', '.join(rules)}" for title, rules in expensive.items() if rules)
        + f". The profile's {len(LEADERBOARD)} parts are planned at about {hours:.0f} h on 2 cores "
        "(an upper bound: `make reproduce-figures PROFILE=leaderboard ARGS=--plan`).",
    ]
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
                    cell_text(found[e.name][0][rule], kept[e.name], planned=LEADERBOARD_STUDIES)
                    if rule in found[e.name][0]
                    else "not run"
                )
                for e in scenes
            ]
            lines.append(f"| {rule} | " + " | ".join(row) + " |")
    longer = board(root, LONGER_SUFFIX)
    for entry in (e for e in SCENES if e.name in longer):
        lines += ["", f"{entry.title}:", *longer_lines(entry, longer[entry.name], entry.budget)]
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
        earlier = "earlier protocol: 3 tuning studies, the learning rate alone tuned"
        plot(found, out / "leaderboard", earlier if earlier_protocol_banner(root) else "")
    longer = board(root, LONGER_SUFFIX)
    text = page(found, "leaderboard.png", root, longer) + tuned_table(root)
    text += rerun_text(root / RERUN.name)
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
