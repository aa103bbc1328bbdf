"""What docs/leaderboard.md and its scene pages say about each scene beyond its cells: the links
to the scene pages, the per-rule presets less what was tuned, each rule's wall-clock time against
Adam's, what a study's clock charged, the scene's budget line, and what its studies ran on (the
clocks they share, the clock checks they kept), all from the kept evidence.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from leaderboard_scenes import BASELINE, planned_studies

from physgrad.replication import majority
from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT

FOLDER = "leaderboard"  # beside leaderboard.md
RERUN_PAGES = f"{FOLDER}/rerun"  # the re-run's scene pages, while it is in progress
# a verdict of rule (A) against Adam (B) as the leaderboard says it
MARKS = {A_BETTER: "better", B_BETTER: "worse", EQUIVALENT: "equivalent"}


def mark(verdict: str) -> str:
    return MARKS.get(verdict, "undecided")


def link(scene: str, rule: str, folder: str = FOLDER) -> str:
    """Where a cell of docs/leaderboard.md points: the rule's section of its scene's page (in
    folder: FOLDER, or RERUN_PAGES for the re-run's)."""
    return f"{folder}/{scene}.md#{rule}"


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


def preset_settings(entry, tuned: dict | None = None) -> dict[str, list[str]]:
    """Per rule of a scene, the settings its per-scene preset (conf/tuning/<task>_<rule>.yaml,
    composed by physgrad's config for that task and optim: batch sizes, damping, a schedule's shape
    from the papers) gives it, the learning rate left out (compare tunes it), and the rule's keys
    its studies tuned (tuned: rule -> keys, tuned_keys); rules without one run at their conf/optim
    preset and the scene's settings."""
    tuned = tuned or {}
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
                if group == "optim" and key in tuned.get(rule, ()):
                    continue  # tuned: what a study ran is in its tuned settings
                settings.append(_setting(f"{group}.{key}", value))
        if settings:
            found[rule] = settings
    return found


def tuned_keys(about: dict) -> dict[str, set[str]]:
    """rule -> the keys a scene's kept tuning studies tuned it on (their trials' keys)."""
    found: dict[str, set[str]] = {}
    for record in (about.get("tuning_studies") or {}).values():
        for trial in record.get("trials") or ():
            keys = set(trial) - {"variant", "validation_loss"}
            found.setdefault(str(trial.get("variant")), set()).update(keys)
    return found


def preset_line(entry, tuned: dict | None = None) -> str | None:
    """The sentence that names a scene's per-rule presets, less the keys tuned (tuned_keys); none
    where no rule has one."""
    found = preset_settings(entry, tuned)
    if not found:
        return None
    knobs = any(keys - {"learning_rate"} for keys in (tuned or {}).values())
    return (
        f"Per-rule settings (conf/tuning/{entry.name}_<rule>.yaml at this commit; a study kept "
        "before a setting changed ran its own commit's, the evidence's `commits`; the learning "
        "rate, or a schedule's init_value, is tuned"
        + (", and so are the rules' knobs: each study's values are on the scene's page" * knobs)
        + "): "
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


def wall_seconds_together(table) -> dict[str, float]:
    """Each rule's median wall-clock training seconds per seed over its completed runs whose job
    trained N seeds together (the job's time over N): a vectorised step of N costs against N of
    one differently from rule to rule, so this is read against Adam's own job of N seeds, never
    against a run alone; none from a runs.csv without train_seconds."""
    if not {"train_seconds", "wall_time_shared_by"} <= set(table.columns):
        return {}
    if "status" in table.columns:
        table = table[table["status"] == "completed"]
    table = table[table["wall_time_shared_by"].fillna(1) > 1]
    share = (table["train_seconds"] / table["wall_time_shared_by"]).dropna()
    by_rule = share.groupby(table["variant"][share.index])
    return {str(v): float(statistics.median(group)) for v, group in by_rule}


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


def wall_ratios(about: dict, key: str = "wall_seconds") -> dict[str, float]:
    """Per rule, its median wall-clock seconds of training in a run over Adam's in the same tuning
    study, the median over the studies that recorded the rule's (a study's load slows its rules
    alike, so the ratio within a study is what the rule's steps cost). Where Adam's seeds trained
    together (the job's time is not a run's: wall_seconds_in_budget), Adam's is the budget: its
    steps cost the same all along, which is what the calibration timed, so a run of it alone
    takes the budget (10.0 to 11.1 s of 10 s, 15.3 s of 15, where the leaderboard's first studies
    timed Adam's runs alone). With key "wall_seconds_together": a seed's share of a job of seeds
    trained together over Adam's share of its own such job (wall_seconds_together)."""
    budget = float(about.get("budget") or math.nan) if key == "wall_seconds" else math.nan
    ratios: dict[str, list[float]] = {}
    for record in (about.get("tuning_studies") or {}).values():
        wall = record.get(key) or {}
        adam = wall.get(BASELINE, budget)
        for rule, seconds in wall.items():
            if rule != BASELINE and adam > 0 and math.isfinite(seconds / adam):
                ratios.setdefault(rule, []).append(seconds / adam)
    return {rule: statistics.median(values) for rule, values in ratios.items()}


WALL_FACTOR = 1.5  # a rule whose runs took this factor longer (or shorter) than Adam's is named


def wall_line(about: dict) -> str | None:
    """The sentence that names the rules whose runs took a different wall-clock time from Adam's
    at the same calibrated budget (none where every rule's is within WALL_FACTOR), and which rules
    were timed: a rule whose seeds trained together was not timed one run at a time."""
    ratios, together = wall_ratios(about), wall_ratios(about, "wall_seconds_together")
    together = {r: x for r, x in together.items() if r not in ratios}
    if not ratios and not together:
        return None
    far = {
        r: x for r, x in {**ratios, **together}.items() if x >= WALL_FACTOR or x <= 1 / WALL_FACTOR
    }
    records = (about.get("tuning_studies") or {}).values()
    timed = [s.get("wall_seconds") for s in records]
    counted = sum(bool(s.get("wall_seconds") or s.get("wall_seconds_together")) for s in records)
    # a study whose Adam runs trained together: its budget stands for a run of Adam's
    budget = (
        f"; for {BASELINE}, whose seeds trained in one job, its run's time is taken as the "
        "budget itself (its steps cost what the calibration timed)"
        if any(wall and BASELINE not in wall for wall in timed)
        else ""
    )
    over = f"median over {counted} tuning {'study' if counted == 1 else 'studies'}{budget}"
    untimed = sorted(set(about.get("iterations") or {}) - set(ratios) - set(together) - {BASELINE})
    if untimed:  # their runs trained together: a vectorised step's time is not one run's
        over += (
            f"; not timed one run at a time (their seeds trained in one job): {', '.join(untimed)}"
        )
    said = ", ".join(f"{r} {x:.2g}x" for r, x in sorted(ratios.items(), key=lambda i: -i[1]))
    if together:  # a job of N seeds against Adam's job of N: what the budget cost them together
        said += ("; " if said else "") + (
            f"seeds trained in one job, its job's time per seed over {BASELINE}'s job's time per "
            "seed: "
            + ", ".join(f"{r} {x:.2g}x" for r, x in sorted(together.items(), key=lambda i: -i[1]))
        )
    if not far:
        return (
            f"Wall-clock time of a run against {BASELINE}'s at the same calibrated budget "
            f"({over}): {said}; every one within {WALL_FACTOR:g}x."
        )
    return (
        f"Wall-clock time of a run against {BASELINE}'s at the same calibrated budget ({over}): "
        f"{said}; beyond {WALL_FACTOR:g}x either way: {', '.join(sorted(far))}. "
        "The clock counts each step at its calibrated "
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


def scene_budget_lines(entry, runs, about: dict, clock_file: Path | None = None) -> list[str]:
    """A scene's item under "The scenes and their budgets": its overrides, budget, studies run and
    machine (and the clock's, kept beside the evidence, where the runs ran on another kind);
    each rule's iterations in the budget; its per-rule presets; its clocks' notes."""
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
        + clock_machine_note(clock_file, runs.machine)
        + "."
    )
    if its:
        lines.append(
            "  Iterations in the budget (median over the runs that reached it): "
            + ", ".join(f"{v} {its[v]:.0f}" for v in (BASELINE, *entry.rules) if v in its)
            + "."
        )
    presets, wall = preset_line(entry, tuned_keys(about)), wall_line(about)
    lines += [f"  {presets}"] if presets else []
    lines += [f"  {wall}"] if wall else []
    lines += [f"  {note}" for note in scene_notes(about)]
    return lines


def clock_machine_note(clock: Path | None, machine: str) -> str:
    """Where a scene's kept clock was measured on another kind of machine than its runs ran on
    (its iterations follow that machine's step costs), the clause that says so; "" otherwise."""
    from evidence import read_json

    try:
        measured = read_json(clock).get("machine") or {} if clock and clock.is_file() else {}
    except (OSError, ValueError, AttributeError):
        return ""
    cpu = measured.get("cpu_model") if isinstance(measured, dict) else None
    if not isinstance(cpu, str) or not machine or cpu in machine:
        return ""
    cores = measured.get("cpu_count")
    return (
        f"; its clock was calibrated on {cpu}"
        + (f" ({cores} cores)" if isinstance(cores, int) else "")
        + ", so each rule's iterations in the budget follow that machine's step costs"
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
