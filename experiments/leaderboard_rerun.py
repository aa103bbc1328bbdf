"""The leaderboard's re-run under the profile's current protocol while it is in progress: the
banner that heads docs/leaderboard.md while its table is the earlier protocol's, the re-run's
section at the page's end (its studies kept, its preliminary cells, each scene's budget and
clock) and its scene pages in docs/leaderboard/rerun (experiments/leaderboard.py writes them)."""

from __future__ import annotations

from pathlib import Path

from leaderboard_cells import board, cell_text, longer_lines
from leaderboard_detail import FOLDER, RERUN_PAGES, link, scene_budget_lines
from leaderboard_scene_page import scene_page
from leaderboard_scenes import (
    EXPENSIVE,
    LEADERBOARD,
    LEADERBOARD_SEEDS,
    LEADERBOARD_STUDIES,
    LEADERBOARD_TRIALS,
    LONGER,
    LONGER_SUFFIX,
    RERUN,
    RULES,
    SCENES,
    kept_clock,
    scene_clock,
)
from study_runs import read_study

from physgrad.comparison.coverage import FEW_STEPS
from physgrad.files import make_folder, replace_file
from physgrad.replication import majority

PAGE = "leaderboard.md"
RERUN_IMAGE = "leaderboard_rerun"  # beside the page: .png and .pdf (experiments/leaderboard.py)
RERUN_HEADING = "The re-run under the current protocol (in progress)"
RERUN_ANCHOR = "the-re-run-under-the-current-protocol-in-progress"  # GitHub's anchor of it


def earlier_protocol_banner(root: Path | None) -> list[str]:
    """The lines that head the page while its table is from the earlier protocol, because the
    re-run under the current one (kept in root/rerun) has not finished every scene; none
    otherwise."""
    if root is None or not (root / RERUN.name).is_dir():
        return []
    # the studies alone, without deciding their cells (the re-run's section does that, once)
    found = (read_study(root / RERUN.name / entry.name) for entry in SCENES)
    kept = sum(len(runs.tuning or (runs,)) for runs in found if runs is not None)
    return [
        "**The table and figure below are from an earlier protocol**: 3 tuning studies a scene, "
        "the learning rate alone tuned, and a line search charged what the first steps cost. "
        f"The re-run under the current protocol ({LEADERBOARD_STUDIES} tuning studies, each rule "
        "tuned on its own knobs, line-search evaluations charged) has kept "
        f"{kept} of {LEADERBOARD_STUDIES * len(SCENES)} studies so far (its section at the end); "
        "until it has all of them, a cell here is the earlier protocol's.",
        "",
    ]


def rerun_text(root: Path, found: dict) -> str:
    """The section on the re-run under the profile's current protocol, whose studies are kept in
    root (docs/evidence/leaderboard/rerun) until every scene has all of them: what the protocol
    is, each scene's studies kept, the cells of those (preliminary, each a link to its scene's
    page: rerun_pages), and each scene's budget, iterations, presets and wall-clock times; found:
    board(root). "" without such a folder."""
    if not root.is_dir():
        return ""
    lines = [
        "",
        f"## {RERUN_HEADING}",
        "",
        f"The profile now runs {LEADERBOARD_STUDIES} tuning studies a scene, each rule tuned on "
        f"its own knobs beside its learning rate (`compare.knobs=true`; {LEADERBOARD_TRIALS} "
        f"trial points a rule in each study, shared by its knobs, and {LEADERBOARD_SEEDS} "
        "evaluation seeds), every scene on a clock "
        "measured afresh that charges a line search its evaluations and a knob that changes a "
        "step's cost its cost at the tuned value (docs/protocol.md). Its studies are kept in "
        "docs/evidence/leaderboard/rerun; the table above moves to them once every scene has "
        "all of its studies"
        + (
            ", and until then the cells below are preliminary: a cell is decided when "
            f"{majority(LEADERBOARD_STUDIES)} of the {LEADERBOARD_STUDIES} studies agree, none "
            "against, every study's median ratio on the verdict's side and the studies taken as "
            "draws excluding a ratio of 1 at 99%, as a claim is (docs/protocol.md, section 2, "
            '"Independent tuning studies"), and each kept study\'s verdict is said beside it.'
            if found
            else "."
        ),
        "",
    ]
    kept = {name: len(runs.tuning or (runs,)) for name, (_, runs, _) in found.items()}
    progress = [f"{e.title}: {kept.get(e.name, 0)} of {LEADERBOARD_STUDIES}" for e in SCENES]
    hours = sum(study.seconds() for study in LEADERBOARD) / 3600
    lines += [
        "Studies kept: " + "; ".join(progress) + ".",
        "",
        reading_again(root)
        + f" The profile's {len(LEADERBOARD)} parts are planned at about {hours:.0f} h on 2 cores "
        "(an estimate, not a bound: `make reproduce-figures PROFILE=leaderboard ARGS=--plan`).",
    ]
    scenes = [e for e in SCENES if e.name in found]
    if scenes:
        lines += [
            "",
            f"![the re-run, preliminary]({RERUN_IMAGE}.png)",
            "",
            "| rule | " + " | ".join(e.title for e in scenes) + " |",
            "|---|" + "---|" * len(scenes),
        ]
        for rule in RULES:
            row = [
                f"n/a: {e.refused[rule]}"
                if rule in e.refused
                else (
                    cell_text(
                        found[e.name][0][rule],
                        kept[e.name],
                        link(e.name, rule, RERUN_PAGES),
                        planned=LEADERBOARD_STUDIES,
                    )
                    if rule in found[e.name][0]
                    else "not run"
                )
                for e in scenes
            ]
            lines.append(f"| {rule} | " + " | ".join(row) + " |")
        lines += ["", "The re-run's scenes so far:", ""]
    longer = board(root, LONGER_SUFFIX)
    for entry in scenes:
        lines += scene_budget_lines(entry, *found[entry.name][1:], scene_clock(entry, root))
        lines += longer_lines(entry, longer.get(entry.name), entry.budget, found[entry.name][0])
    for entry in (e for e in SCENES if e.name in longer and e.name not in found):
        lines += ["", f"{entry.title}:", *longer_lines(entry, longer[entry.name], entry.budget)]
    return "\n".join(lines) + "\n"


def reading_again(root: Path) -> str:
    """Which rules each scene reads again at LONGER times the budget (expensive on its clock in
    root), and those it does not, fewer than FEW_STEPS steps even there, with what FEW_STEPS of
    their steps take."""
    clocks = {e.name: scene_clock(e, root) for e in SCENES}
    beyond = {e.name: e.beyond_reach(clocks[e.name]) for e in SCENES}
    expensive = [
        (e, [r for r in e.expensive(clocks[e.name]) if r not in beyond[e.name]]) for e in SCENES
    ]

    def listed(scenes) -> str:
        return "; ".join(f"{e.title}: {', '.join(rules)}" for e, rules in scenes)

    settled = [(e, rules) for e, rules in expensive if rules and kept_clock(e, root)]
    provisional = [(e, rules) for e, rules in expensive if rules and not kept_clock(e, root)]
    return (
        f"Read again at {LONGER}x the budget (a step above {EXPENSIVE:g} of Adam's on the scene's "
        "clock, at the preset or at a knob's value the tuning may choose; each at the settings "
        "tuned at the budget: docs/protocol.md, section 7): "
        + listed(settled)
        + (
            ("; and, " if settled else "")
            + "provisional, from clocks each scene's first study measures again: "
            + listed(provisional)
            if provisional
            else ""
        )
        + "."
        + "".join(
            f" On {e.title}, {_and(list(far))} {'are' if len(far) > 1 else 'is'} not read again: "
            f"even at {LONGER}x the budget ({LONGER * e.budget:g} s) "
            f"{'they get' if len(far) > 1 else 'it gets'} fewer than {FEW_STEPS} steps ("
            + ", ".join(f"{FEW_STEPS} of {rule}'s take {s:,.0f} s" for rule, s in far.items())
            + f"), so {'their cells measure' if len(far) > 1 else 'its cell measures'} a step's "
            "cost, not the rule."
            for e in SCENES
            if (far := beyond[e.name])
        )
    )


def rerun_pages(root: Path, found: dict, out: Path) -> None:
    """The re-run's page per scene in out/RERUN_PAGES (each scene of found: board(root), with
    its reading at LONGER times the budget where root has one), beside the published table's;
    written through the write door."""
    if not found:
        return
    make_folder(out / FOLDER)
    make_folder(out / RERUN_PAGES)
    longer = board(root, LONGER_SUFFIX)
    for entry in (e for e in SCENES if e.name in found):
        text = scene_page(
            entry,
            *found[entry.name],
            back=f"../../{PAGE}#{RERUN_ANCHOR}",
            longer=longer.get(entry.name),
        )
        replace_file(out / RERUN_PAGES / f"{entry.name}.md", text.encode())


def _and(names: list[str]) -> str:
    """a; a and b; a, b and c."""
    return ", ".join(names[:-1]) + " and " + names[-1] if len(names) > 1 else "".join(names)
