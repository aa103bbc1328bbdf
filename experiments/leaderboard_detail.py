"""The leaderboard's page per scene (docs/leaderboard/<scene>.md), which each cell of
docs/leaderboard.md links to: every rule against Adam in each tuning study (its verdict with why,
the median ratio with its interval, the seeds where the rule was lower, the ratios at 1/4 and 1/2 of
the budget, the iterations of both rules) and over the studies; and what a scene's studies ran on
(the clocks they share, the clock checks they kept). Generated from the kept evidence, as the
leaderboard is: the study folders' compare.md are not kept, this is what stands in for them.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from leaderboard_scenes import BASELINE, RULES, planned_studies

from physgrad.readout import fmt
from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT, MARGIN

FOLDER = "leaderboard"  # beside leaderboard.md
# a verdict of rule (A) against Adam (B) as the leaderboard says it
MARKS = {A_BETTER: "better", B_BETTER: "worse", EQUIVALENT: "equivalent"}


def mark(verdict: str) -> str:
    return MARKS.get(verdict, "undecided")


def link(scene: str, rule: str) -> str:
    """Where a cell of docs/leaderboard.md points: the rule's section of its scene's page."""
    return f"{FOLDER}/{scene}.md#{rule}"


def clock_groups(by_study: dict, tolerance: float = 0.01) -> list[list[str]]:
    """The kept tuning studies of a scene grouped by the clock they ran on, each group in order.

    On the calibrated clock a run's iterations are its rule's budget / step cost, the same for
    every seed that reaches the budget, so studies on one clock have the same median iterations
    per rule, except a rule that diverged in half its seeds (its runs stop early). Two studies are
    on one clock where most rules both ran agree within `tolerance` (relative); another clock (a
    calibration of its own, or a clock replaced when a rule was added) moves every rule's."""

    def same(a: dict, b: dict) -> bool:
        common = set(a) & set(b)
        agree = sum(abs(a[r] - b[r]) <= tolerance * max(abs(a[r]), abs(b[r])) for r in common)
        return 2 * agree > len(common) or not common

    groups: list[list[str]] = []
    for key, record in by_study.items():
        its = record.get("iterations") or {}
        for group in groups:
            if same(by_study[group[0]].get("iterations") or {}, its):
                group.append(key)
                break
        else:
            groups.append([key])
    return groups


ROOT = Path(__file__).resolve().parent.parent


def _value(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def _setting(key: str, value) -> str:
    """One preset setting as key=value; a schedule (a dict with _target_) as its optax function
    with its arguments, its init_value left out (that is what compare tunes)."""
    if isinstance(value, dict) and "_target_" in value:
        args = ", ".join(
            f"{k}={_value(v)}" for k, v in value.items() if k not in ("_target_", "init_value")
        )
        return f"{key}={str(value['_target_']).rsplit('.', 1)[-1]}({args})"
    return f"{key}={_value(value)}"


def preset_settings(entry) -> dict[str, list[str]]:
    """Per rule of a scene, the settings its per-scene preset (conf/tuning/<task>_<rule>.yaml,
    composed by physgrad's config for that task and optim: batch sizes, damping, a schedule's shape
    from the papers) gives it, the learning rate left out (compare tunes it); rules without one
    run at their conf/optim preset and the scene's settings."""
    from omegaconf import OmegaConf

    folders = [ROOT / "conf" / "tuning"]
    if entry.config_dir:
        folders.insert(0, ROOT / entry.config_dir / "tuning")
    found = {}
    for rule in (BASELINE, *entry.rules):
        paths = [f / f"{entry.name}_{rule}.yaml" for f in folders]
        path = next((p for p in paths if p.is_file()), None)
        if path is None:
            continue
        settings = []
        for group, values in (OmegaConf.to_container(OmegaConf.load(path)) or {}).items():
            if group == "search":  # the tuning's ranges, not a preset
                continue
            for key, value in (values or {}).items():
                if group == "optim" and key == "learning_rate" and not isinstance(value, dict):
                    continue
                settings.append(_setting(f"{group}.{key}", value))
        if settings:
            found[rule] = settings
    return found


def preset_line(entry) -> str | None:
    """The sentence that names a scene's per-rule presets (none where no rule has one)."""
    found = preset_settings(entry)
    if not found:
        return None
    return (
        f"Per-rule settings (conf/tuning/{entry.name}_<rule>.yaml at this commit; a study kept "
        "before a setting changed ran its own commit's, the evidence's `commits`; the learning "
        "rate, or a schedule's init_value, is tuned): "
        + "; ".join(f"{rule} {', '.join(settings)}" for rule, settings in found.items())
        + ". The other rules run at their presets (conf/optim) with the scene's settings."
    )


def wall_seconds_in_budget(table) -> dict[str, float]:
    """Each rule's median wall-clock training seconds over its runs that reached the budget (not
    compiling): what the calibrated budget cost it on the machine that ran it (none from a runs.csv
    without train_seconds). Runs trained alone only: a run whose job trained N seeds together
    records the job's time (wall_time_shared_by), and how much a vectorised step of N costs
    against N of one differs from rule to rule (SOAP's 10 seeds on guidance: 1.8 times Adam's
    10), which is not what the calibrated clock charged either rule."""
    if "train_seconds" not in table.columns:
        return {}
    if "status" in table.columns:
        table = table[table["status"] == "completed"]
    if "wall_time_shared_by" in table.columns:
        table = table[table["wall_time_shared_by"].fillna(1) <= 1]
    return {
        str(v): float(statistics.median(group["train_seconds"]))
        for v, group in table.groupby("variant")
    }


def charged_by_schedule(calibration: Path, key: str = "update_seconds") -> list[str]:
    """The rules a study's calibration charged a scheduled update at its expected cost (those with
    update_seconds: trainer.update_cost; with key "evaluation_seconds", those it charged the
    evaluations their line searches made), none where it has none or cannot be read."""
    from physgrad.comparison.calibration import read_calibration

    stored = read_calibration(calibration, [])
    costs = (stored or {}).get("costs") or {}
    return sorted(
        str(name) for name, cost in costs.items() if isinstance(cost, dict) and key in cost
    )


def charged_by_clock(calibration: Path) -> dict[str, list[str]]:
    """What a study's kept record says its clock charged beyond a step's cost: the rules charged a
    scheduled update at its expected cost, and those charged their line searches' evaluations."""
    return {
        "charged_by_schedule": charged_by_schedule(calibration),
        "charged_by_evaluations": charged_by_schedule(calibration, "evaluation_seconds"),
    }


def wall_ratios(about: dict) -> dict[str, float]:
    """Per rule, its median wall-clock seconds of training in a run over Adam's in the same tuning
    study, the median over the studies that recorded both (a study's load slows its rules alike,
    so the ratio within a study is what the rule's steps cost)."""
    ratios: dict[str, list[float]] = {}
    for record in (about.get("tuning_studies") or {}).values():
        wall = record.get("wall_seconds") or {}
        adam = wall.get(BASELINE, math.nan)
        for rule, seconds in wall.items():
            if rule != BASELINE and adam > 0 and math.isfinite(seconds / adam):
                ratios.setdefault(rule, []).append(seconds / adam)
    return {rule: statistics.median(values) for rule, values in ratios.items()}


WALL_FACTOR = 1.5  # a rule whose runs took this factor longer (or shorter) than Adam's is named


def wall_line(about: dict) -> str | None:
    """The sentence that names the rules whose runs took a different wall-clock time from Adam's
    at the same calibrated budget (none where every rule's is within WALL_FACTOR)."""
    ratios = wall_ratios(about)
    far = {r: x for r, x in ratios.items() if x >= WALL_FACTOR or x <= 1 / WALL_FACTOR}
    if not ratios:
        return None
    counted = sum(bool(s.get("wall_seconds")) for s in (about.get("tuning_studies") or {}).values())
    if not far:
        return (
            f"Wall-clock time of a run: every rule's within {WALL_FACTOR:g}x of {BASELINE}'s "
            f"(median over {counted} tuning {'study' if counted == 1 else 'studies'})."
        )
    return (
        f"Wall-clock time of a run against {BASELINE}'s at the same calibrated budget (median "
        f"over {counted} tuning {'study' if counted == 1 else 'studies'}): "
        + ", ".join(f"{r} {x:.2g}x" for r, x in sorted(far.items(), key=lambda i: -i[1]))
        + f"; the others within {WALL_FACTOR:g}x. The clock counts each step at its calibrated "
        "cost, and a step whose cost varies along a run (a line search's evaluations; PSGD "
        "Kron's preconditioner update, at every step for the first 500 and rarer after) can cost "
        "more or less in the runs than in the calibration, which times the first steps (and, "
        "where it charges PSGD Kron its expected cost, those at its schedule's floor): above 1x "
        f"the rule had more time than {BASELINE}, below 1x less. " + _evaluations_said(about)
    )


def _evaluations_said(about: dict) -> str:
    """Whether the scene's studies charged the line searches the evaluations they made."""
    studies = (about.get("tuning_studies") or {}).values()
    if any(s.get("charged_by_evaluations") for s in studies):
        return (
            "Where a study's clock timed a line search's evaluations, each run was charged those "
            "it made."
        )
    return (
        "This scene's clock predates the calibration's timing of a line search's evaluations: "
        "its line-search rules were charged each step at its calibrated cost."
    )


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


def _studies(keys: list[str]) -> str:
    return ("studies " if keys[1:] else "study ") + " and ".join(keys)


def scene_notes(about: dict) -> list[str]:
    """Sentences for a scene whose kept tuning studies ran on different clocks, or were kept
    before their clock check's outcome was (none if neither)."""
    by_study = about.get("tuning_studies") or {}
    notes = []
    groups = clock_groups(by_study)
    if len(groups) > 1:
        per_study = ", ".join(
            f"{(by_study[k].get('iterations') or {}).get(BASELINE, math.nan):.0f} (study {k})"
            for k in by_study
        )
        notes.append(
            f"Its tuning studies ran on {len(groups)} clocks ({'; '.join(map(_studies, groups))}): "
            f"{BASELINE}'s iterations in the budget are {per_study}. Each study compares its rules "
            "at equal time, but the scene's verdicts pool studies at different budgets in "
            "iterations."
        )
    unchecked = [k for k, r in by_study.items() if "undecided_by_the_clock" not in r]
    if unchecked:
        notes.append(
            f"{_studies(unchecked).capitalize()}: kept before the evidence recorded the clock "
            "check (a better that does not survive the step costs' uncertainty is undecided), so a "
            "better there may be one its compare called undecided."
        )
    return notes


def _its(iterations: dict, rule: str) -> str:
    value = iterations.get(rule, math.nan)
    return f"{value:.0f}" if math.isfinite(value) else "-"


def _ratio(p) -> str:
    from physgrad.verdict import ratio_of

    return f"{fmt(p.ratio)} [{fmt(ratio_of(p.low))}, {fmt(ratio_of(p.high))}]"


def scene_page(entry, cells: dict, runs, about: dict) -> str:
    """docs/leaderboard/<scene>.md: per rule a table of its tuning studies and their pooled
    verdict (the cell)."""
    by_study = about.get("tuning_studies") or {}
    studies = len(runs.tuning or (runs,))
    lines = [
        f"# {entry.title}: each rule against {BASELINE}, per tuning study",
        "",
        "<!-- generated by experiments/leaderboard.py from docs/evidence/leaderboard: do not "
        "edit -->",
        "",
        f"`physgrad compare {' '.join(entry.overrides)}` with `compare.baseline={BASELINE}`, "
        f"{runs.budget:g} s on the calibrated clock; {studies} of {planned_studies(runs)} tuning "
        f"studies kept; on {runs.machine or 'a machine not recorded'}. Back to the "
        "[leaderboard](../leaderboard.md).",
        "",
        *(note + "\n" for note in scene_notes(about)),
        "Per study: the verdict at the budget X with why (A: the rule, B: Adam; better: the "
        "rule's test loss below "
        f"{BASELINE}'s beyond a factor {MARGIN:g}; Holm over the study's comparisons with "
        f"{BASELINE}), the median ratio rule / {BASELINE} of the test loss with its 95% interval, "
        "the seeds where the rule was lower, the ratios at X/4 and X/2, and each rule's median "
        "iterations in the budget. The last row is the leaderboard's cell: the verdict over the "
        "studies (physgrad.replication.across_studies) with why, the median ratio over every "
        "study's seeds, and the span of the studies' intervals (lowest low to highest high: "
        "descriptive, not a confidence interval).",
    ]
    keys = sorted(by_study, key=int) if len(by_study) == studies else []
    for rule, cell in sorted(cells.items(), key=lambda item: RULES.index(item[0])):
        lines += [
            "",
            f"## {rule}",
            "",
            "| tuning study | verdict at X | ratio at X | lower in | at X/4 | at X/2 | iterations "
            "|",
            "|---|---|---|---|---|---|---|",
        ]
        for k, result in cell.detail:
            # each study's iterations where kept per study, else the scene's
            its = (by_study[keys[k]] if keys else about).get("iterations") or {}
            verdict, why = result.verdicts[1.0]
            p = result.at[1.0]
            lines.append(
                f"| {keys[k] if keys else k + 1} | {mark(verdict)} ({why}) | {_ratio(p)} | "
                f"{p.wins_a} of {p.pairs} | "
                + " | ".join(
                    f"{fmt(result.at[f].ratio)} ({mark(result.verdicts[f][0])})"
                    for f in (0.25, 0.5)
                )
                + f" | {rule} {_its(its, rule)}, {BASELINE} {_its(its, BASELINE)} |"
            )
        lines.append(
            f"| over the studies | **{mark(cell.verdict)}**"
            + (f" ({cell.why})" if cell.why else "")
            + f" | {fmt(cell.ratio)} [{fmt(cell.low)}, "
            f"{fmt(cell.high)}] | {cell.wins} of {cell.pairs} | | | |"
        )
        lines += ["", detectable_line(cell, len(cells))]
    return "\n".join(lines) + "\n"


def detectable_line(cell, comparisons: int) -> str:
    """The smallest ratio rule / Adam (either way) that a cell's design finds with 80% power
    (physgrad.power.detectable_ratio, as compare.md states it per pair), from what its tuning
    studies measured at the budget: the seeds' spread of the log ratios, the spread between the
    studies and both rules' divergence rates; for its seeds per study, its studies and Holm over
    the scene's comparisons with Adam."""
    from types import SimpleNamespace

    from physgrad.power import POWER, detectable_ratio, measured

    results = [result for _, result in cell.detail]
    sd, between, divergence, other = measured(SimpleNamespace(studies=results))
    ratio = (
        detectable_ratio(
            sd,
            results[0].at[1.0].seeds,
            comparisons,
            len(results),
            divergence=divergence,
            between=between,
            divergence_other=other,
        )
        if results
        else math.nan
    )
    if math.isnan(ratio):
        said = "not measured (fewer than 3 finite log ratios)"
    elif math.isinf(ratio):
        said = "none (too few seeds, or too many divergences)"
    else:
        said = f"{fmt(ratio)}x"
    return (
        f"Detectable: {said}: the smallest ratio either way that these {len(results)} tuning "
        f"{'study finds' if len(results) == 1 else 'studies find'} with {POWER:.0%} power (the "
        "seeds' spread, the spread between the studies and the divergences they measured); an "
        "undecided cell with a large detectable ratio says little."
    )
