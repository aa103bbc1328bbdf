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
from leaderboard_detail import FOLDER, link, scene_budget_lines, wall_ratios
from leaderboard_figure import plot
from leaderboard_keep import keep
from leaderboard_rerun import RERUN_IMAGE, earlier_protocol_banner, rerun_pages, rerun_text
from leaderboard_scene_page import scene_page
from leaderboard_scenes import (
    BASELINE,
    LEADERBOARD_SEEDS,
    LEADERBOARD_STUDIES,
    LEADERBOARD_TRIALS,
    LITERATURE,
    LONGER_SUFFIX,
    RERUN,
    RULES,
    SCENES,
    WHY_IT_MAY_DIFFER,
    planned_studies,
    where_scene_runs,
)
from scene_kinds import KINDS, both_pages_line, kinds_table, read_kinds
from study_runs import read_study
from tuned_settings import tuned_table

from physgrad.errors import UserError
from physgrad.files import clean_text, make_folder, replace_file
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
            clock = root / CLOCK.format(name=entry.name) if root is not None else None
            lines += scene_budget_lines(entry, *found[entry.name][1:], clock)
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
    # a scene the earlier protocol never ran may have studies in the re-run (its section below)
    in_rerun = [e for e in missing if root and read_study(root / RERUN.name / e.name) is not None]
    if in_rerun:
        lines += [
            "",
            "Run under the current protocol only (the re-run's section below): "
            + ", ".join(f"{e.title} (`{e.name}`)" for e in in_rerun)
            + ".",
        ]
    if not_run := [e for e in missing if e not in in_rerun]:
        lines += [
            "",
            "Not run yet: "
            + ", ".join(f"{e.title} (`{e.name}`: {where_scene_runs(e)})" for e in not_run)
            + ".",
        ]
    rerun = board(root / RERUN.name) if root and (root / RERUN.name).is_dir() else {}
    return "\n".join(lines + literature_lines(found, rerun)) + "\n"


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


SCHEDULED_COST = "psgd_kron"  # a rule whose step cost falls along a run by its own schedule
FIXED_COST = ("gd", "muon", "soap")  # element-wise rules whose every step costs the same


def scheduled_cost_line(abouts: dict[str, dict], titles: dict[str, str]) -> str | None:
    """The sentence on PSGD Kron and the clock: per scene, its runs' wall-clock time over Adam's at
    the same calibrated budget (wall_ratios), beside the range of the fixed-cost element-wise
    rules' as the noise of such a ratio; none where no scene recorded the rule's."""
    measured = []
    for scene, about in abouts.items():
        charged_alike = {  # the studies whose clock charged PSGD Kron's steps alike
            k: study
            for k, study in (about.get("tuning_studies") or {}).items()
            if SCHEDULED_COST not in (study.get("charged_by_schedule") or [])
        }
        ratios = wall_ratios({"tuning_studies": charged_alike})
        if SCHEDULED_COST not in ratios:
            continue
        fixed = [ratios[r] for r in FIXED_COST if r in ratios]
        span = sorted({f"{min(fixed):.2g}", f"{max(fixed):.2g}"}, key=float) if fixed else []
        beside = f" (gd, Muon, SOAP: {'-'.join(span)}x)" if fixed else ""
        measured.append(f"{titles.get(scene, scene)}: {ratios[SCHEDULED_COST]:.2g}x{beside}")
    if not measured:
        return None
    return (
        "PSGD Kron is charged more than its steps cost. It updates its preconditioner at every "
        "step for its first 500 and at a falling rate after (to 3% of its steps by step 4,000), "
        "and a calibration times its first steps (on most scenes a few hundred, nearly all of them "
        "updating): the clock charges every step about an updating step's cost. Its runs took "
        f"this much of {BASELINE}'s wall-clock time at the same "
        "calibrated budget (median over the tuning studies that recorded runs trained alone): "
        + "; ".join(measured)
        + ". Where that is below the fixed-cost rules' ratios, PSGD Kron had less time than "
        f"{BASELINE} by about that factor, and its cells understate it "
        '(docs/benchmarks.md, "PSGD Kron on the calibrated clock", measures what its update '
        "costs on each scene). A study whose calibration also timed PSGD Kron's step where its "
        "schedule is at its floor charges each step its expected cost instead "
        '(docs/decisions.md, "Timing") and is not counted here.'
    )


def literature_lines(found: dict, rerun: dict | None = None) -> list[str]:
    """What the rules' papers report on the leaderboard's problems, beside the cells measured
    here and the iterations the budget gave the rule and Adam (the papers compare at equal
    iterations); a scene only the re-run has (the full-batch ones) from its cells, said so."""
    titles = {e.name: e.title for e in SCENES}
    lines = ["", "## What the literature reports, and the same rules here", ""]
    for claim, where in LITERATURE:
        measured = []
        for scene, rule in where:
            again = scene not in found and scene in (rerun or {})
            cell, runs, about = (rerun if again else found).get(scene, ({}, None, {}))
            cell = cell.get(rule)
            planned = planned_studies(runs) if again and runs is not None else 0
            adam = (about.get("iterations") or {}).get(BASELINE, math.nan)
            its = (
                f" ({cell.iterations:,.0f} iterations in the budget, Adam {adam:,.0f})"
                if cell and math.isfinite(cell.iterations) and math.isfinite(adam)
                else ""
            )
            measured.append(
                f"{rule} on {titles[scene]}"
                + (" (the re-run, current protocol)" if again else "")
                + ": "
                + (cell_text(cell, planned=planned) + its if cell else "not run yet")
            )
        lines.append(f"- {claim} In physgrad's setting: " + "; ".join(measured) + ".")
    return lines + ["", WHY_IT_MAY_DIFFER]


def write(root: Path, out: Path) -> str:
    """leaderboard.md and leaderboard.png (and .pdf; leaderboard_rerun.png and .pdf for a re-run
    kept in root/rerun) in out, from kept evidence under root or from
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
    rerun = board(root / RERUN.name) if (root / RERUN.name).is_dir() else {}
    if rerun:  # its own heat map, every scene a column, so that what is still to run shows
        plot(rerun, out / RERUN_IMAGE, "the re-run under the current protocol, preliminary")
    text += rerun_text(root / RERUN.name, rerun)
    # through the write door: a link at a page's name, or at its folder, is not written through
    replace_file(out / "leaderboard.md", text.encode())
    make_folder(out / FOLDER)
    for entry in (e for e in SCENES if e.name in found):
        page_text = scene_page(entry, *found[entry.name], longer=longer.get(entry.name))
        replace_file(out / FOLDER / f"{entry.name}.md", page_text.encode())
    rerun_pages(root / RERUN.name, rerun, out)
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
