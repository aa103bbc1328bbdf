"""The leaderboard's evidence: each finished tuning study of a scene kept in the scene's table
(experiments/evidence.py) with what the page states beside the losses: the machine, the commit,
each rule's iterations and wall-clock seconds at the budget, the overrides, the clock's notes and
what its calibration charged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from evidence import (  # experiments/
    CLOCK,
    commit,
    keep_clock,
    kept_row,
    merged_rows,
    read_json,
    read_table,
    undecided_by_the_clock,
    write_kept,
)
from leaderboard_detail import charged_by_clock, wall_seconds_in_budget, wall_seconds_together
from leaderboard_scenes import (
    LEADERBOARD_SEEDS,
    LEADERBOARD_STUDIES,
    LEADERBOARD_TRIALS,
    LONGER_FOLDER,
    LONGER_SUFFIX,
    SCENES,
)
from studies import STUDY_FOLDER
from study_runs import read_study, run_commits, study_overrides, tuned_trials

from physgrad.errors import UserError
from physgrad.files import clean_text


def keep(root: Path, dest: Path) -> list[str]:
    """Every finished tuning study of the leaderboard under root (<root>/<scene>/study-k) added to
    the scene's evidence table in dest (experiments/evidence.py), replacing that study's rows if
    it was kept before and keeping the others' (each study is kept whatever machine ran it): every
    run's test loss at the kept fractions of the budget; in the .json each study's machine, commit
    and each rule's median iterations at the budget, and the scene's calibration (its clock, for
    the studies still to run) beside it. A scene's studies at the longer budget
    (<scene>/longer-k) are kept alike as <scene>_longer. Returns the studies kept, as
    scene/study-k (or scene/longer-k)."""
    kept = []
    for entry in SCENES:
        kept += _keep_scene(root, dest, entry, entry.name, STUDY_FOLDER)
        kept += _keep_scene(root, dest, entry, entry.name + LONGER_SUFFIX, LONGER_FOLDER)
    return kept


def _keep_scene(root: Path, dest: Path, entry, name: str, pattern: str) -> list[str]:
    """keep for one scene's studies in folders named by pattern, as evidence `name`."""
    kept = []
    finished = {}
    for k in range(1, LEADERBOARD_STUDIES + 1):
        folder = root / entry.name / pattern.format(k=k)
        runs = read_study(folder) if (folder / "runs.csv").is_file() else None
        if runs is not None:
            finished[k] = (folder, runs)
    if not finished:
        return kept
    knobs = _same_protocol(dest, name, finished)
    records = {}
    for k, (folder, runs) in finished.items():
        if runs.tuning:
            raise UserError(
                f"{folder}: {len(runs.tuning)} tuning studies, where a leaderboard study "
                "folder holds one (compare.studies=1)"
            )
        rows = [
            kept_row(k - 1, variant, seed, "loss", curve, runs.budget)
            for variant in sorted(runs.paths)
            for seed, curve in sorted(runs.curves(variant).items())
        ]
        table = read_table(folder / "runs.csv")
        records[k] = (
            rows,
            {
                "machine": runs.machine,
                "commits": run_commits(runs),
                "kept_by": commit(),
                "iterations": iterations_in_budget(table),
                "wall_seconds": wall_seconds_in_budget(table),
                "wall_seconds_together": wall_seconds_together(table),
                "overrides": study_overrides(folder),
                "undecided_by_the_clock": undecided_by_the_clock(folder),
                **charged_by_clock(folder / "calibration.json"),
                # what its tuning chose per rule, and the trials it chose from
                **tuned_trials(folder),
            },
        )
    first = next(iter(finished.values()))[1]
    rows, by_study = merged_rows(dest, name, records, first.budget)
    for k, (folder, _) in finished.items():
        if pattern == STUDY_FOLDER:  # the longer studies run on the kept clock
            keep_clock(folder / "calibration.json", dest / CLOCK.format(name=entry.name))
        kept.append(f"{entry.name}/{pattern.format(k=k)}")
    machines = sorted({str(s.get("machine") or "") for s in by_study.values()} - {""})
    per_study = [s.get("iterations") or {} for s in by_study.values()]
    about = {
        "study": name,
        "axis": first.axis,
        "budget": first.budget,
        "trials": LEADERBOARD_TRIALS,
        "studies": len(by_study),
        "planned": LEADERBOARD_STUDIES,
        "knobs": knobs,
        "seeds": LEADERBOARD_SEEDS,
        "machine": "; ".join(machines),
        "kept_by": commit(),
        # each rule's iterations at the budget: the median of the studies' medians
        "iterations": {
            rule: float(np.median([its[rule] for its in per_study if rule in its]))
            for rule in sorted(set().union(*per_study))
        },
        "tuning_studies": by_study,
    }
    write_kept(dest, name, rows, about)
    return kept


def _same_protocol(dest: Path, scene: str, finished: dict) -> bool:
    """The finished studies checked to be of the profile's protocol (compare.knobs=true, whatever
    its spelling) and dest to hold no scene of another (its records' tuning studies planned and
    knobs), so that no table is decided on two protocols; UserError (one line) otherwise."""

    def knobs(folder: Path) -> bool:
        said = [
            o.partition("=")[2] for o in study_overrides(folder) if o.startswith("compare.knobs=")
        ]
        return bool(said) and said[-1].strip().lower() == "true"

    if not all(knobs(folder) for folder, _ in finished.values()):
        raise UserError(
            f"{scene}: a study run without compare.knobs=true, where the profile's protocol tunes "
            "each rule's knobs: run it with the current profile"
        )
    for about_path in sorted(dest.glob("*.json")) if dest.is_dir() else ():
        about = read_json(about_path)
        if not isinstance(about, dict) or "planned" not in about:
            continue  # a calibration, not a scene's record
        kept = (about.get("planned"), bool(about.get("knobs")))
        if kept != (LEADERBOARD_STUDIES, True):
            raise UserError(
                f"{about_path} keeps studies of another protocol ({kept[0]} tuning studies, "
                f"{'the rules own knobs' if kept[1] else 'the learning rate alone'} tuned): "
                f"keep {scene}'s in another folder (the current protocol's: "
                "docs/evidence/leaderboard/rerun)"
            )
    return True


def iterations_in_budget(table) -> dict[str, float]:
    """Each rule's median iterations over its runs that reached the budget: a run that diverged
    stopped early, and its iterations say when, not how many the budget gives (a rule none of whose
    runs reached the budget has none)."""
    if "status" in table.columns:
        table = table[table["status"] == "completed"]
    return {str(v): float(np.median(group["iterations"])) for v, group in table.groupby("variant")}


def checked_record(study: Path, runs, about: object, rules: tuple[str, ...]) -> None:
    """A scene's kept runs and record read as data: every variant one of the scene's rules, the
    record a mapping whose iterations (and each tuning study's) map those rules to finite numbers
    above 0; UserError (one line) naming the study and the field otherwise."""
    import math

    names = sorted({v for one in (runs.tuning or (runs,)) for v in one.paths})
    unknown = [n for n in names if n not in rules]
    if unknown:
        raise UserError(
            f"{study}: variant {clean_text(unknown[0], 60)!r} is none of the scene's rules "
            f"({', '.join(rules)}): not this scene's evidence"
        )
    if not isinstance(about, dict):
        raise UserError(f"{study}.json: a {type(about).__name__}, not a record")
    tuning = about.get("tuning_studies") or {}
    if not isinstance(tuning, dict) or not all(isinstance(s, dict) for s in tuning.values()):
        raise UserError(f"{study}.json: tuning_studies is not a record per tuning study")
    for where, record in (("", about), *((f"tuning_studies.{k}.", s) for k, s in tuning.items())):
        iterations = record.get("iterations") or {}
        if not isinstance(iterations, dict) or not all(
            rule in rules
            and isinstance(n, (int, float))
            and not isinstance(n, bool)
            and math.isfinite(n)
            and n > 0
            for rule, n in iterations.items()
        ):
            raise UserError(
                f"{study}.json: {clean_text(where, 60)}iterations must map the scene's rules to "
                "numbers above 0"
            )
