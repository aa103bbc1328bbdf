"""A study's evaluation runs, read from its folder (the tables `physgrad compare` writes), from its
tuning studies' folders (<study>/study-k, one compare each), or from its kept evidence
(experiments/evidence.py); and a finished study kept as evidence.

A study folder is data from someone else: each run's file is looked for in the folder's own eval/,
never at the path its table records, and a linked folder is not read.
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from evidence import (  # experiments/
    busy_clock,
    commit,
    keep_clock,
    kept_row,
    kept_table,
    merged_rows,
    read_json,
    read_kept,
    read_table,
    write_kept,
)
from studies import CLOCK, PROFILES, STUDY_FOLDER

from physgrad.claim import tuning_studies
from physgrad.errors import UserError
from physgrad.files import inside


@dataclass
class StudyRuns:
    """A study's evaluation runs: variant -> seed -> results file, with the budget and its axis."""

    folder: Path
    axis: str
    budget: float
    paths: dict
    machine: str = ""
    # with repeated tuning studies: every study's runs, the first (this one's paths) included
    tuning: tuple = ()
    # read from kept evidence (experiments/evidence.py): {(variant, column): {seed: KeptCurve}}
    kept: dict | None = None
    protocol: tuple | None = None  # kept evidence: (trials, tuning studies, seeds)
    # the tuning studies the study is to have (0: those it has); a part is decided by a majority
    # of them, so that two of four run cannot decide it alone
    planned: int = 0

    def also_known_as(self, token: str) -> None:
        """Every variant, in every tuning study, also known by its name with token appended
        ("backprop=C" as "backprop=C clip=none"); kept evidence's curves too."""
        for study in (self, *self.tuning[1:]):
            study.paths.update({f"{v} {token}": by for v, by in list(study.paths.items())})
            if study.kept is not None:
                study.kept.update(
                    {(f"{v} {token}", c): by for (v, c), by in list(study.kept.items())}
                )

    def join(self, other: StudyRuns) -> None:
        """other's variants as more variants of this study (a study that `joins` this one: the
        same budget on the same seeds, run as a compare of its own); a variant both have is
        this one's."""
        if (other.kept is None) != (self.kept is None):
            raise UserError(
                f"{other.folder} joins {self.folder}, but one is kept evidence and the other a "
                "study folder: keep both (experiments/claims.py --keep) or neither"
            )
        if (other.axis, other.budget) != (self.axis, self.budget) or len(other.tuning) != len(
            self.tuning
        ):
            raise UserError(
                f"{other.folder} joins {self.folder} but runs {other.budget:g} ({other.axis}) in "
                f"{max(len(other.tuning), 1)} tuning studies where it runs {self.budget:g} "
                f"({self.axis}) in {max(len(self.tuning), 1)}; run them alike"
            )
        pairs = zip(self.tuning or (self,), other.tuning or (other,))
        for mine, theirs in pairs:
            mine.paths.update({v: p for v, p in theirs.paths.items() if v not in mine.paths})
            if mine.kept is not None:
                mine.kept.update({k: c for k, c in theirs.kept.items() if k not in mine.kept})

    def curves(self, variant: str, column: str = "loss") -> dict:
        from physgrad.readout import run_curve
        from physgrad.results import read_run

        if self.kept is not None:
            return dict(self.kept.get((variant, column), {}))

        found, unreadable = {}, []
        for seed, path in self.paths.get(variant, {}).items():
            try:
                found[seed] = run_curve(read_run(Path(path)), self.axis, column)
            except ValueError as error:
                unreadable.append(str(error))
        if unreadable:
            print(
                f"claims: {variant} in {self.folder}: left out {len(unreadable)} runs, e.g. "
                f"{unreadable[0]}",
                file=sys.stderr,
            )
        return found


def read_study(folder: Path) -> StudyRuns | None:
    """The study's runs.csv (written by physgrad compare) as StudyRuns of its first tuning study,
    with every tuning study's in `tuning` where it has several (Lower and Close parts are decided
    over them by the package's rule, physgrad.replication.across_studies; the trend and stall parts
    are decided in each and over them by the same rule, physgrad.replication.over_studies; the
    regime map reads the first); None if the study has not finished. The table is data from a folder
    that may come from someone else: each run's file is looked for in the folder's own eval/ (the
    part of its recorded path from "eval" on), never at the path as written (an absolute path or
    "..": anywhere); a row whose seed, budget or path cannot be read so is a UserError (one
    line)."""

    table = folder / "runs.csv"
    if not table.is_file():
        kept = kept_table(folder)
        if kept is not None:
            return _kept_runs(read_kept(kept))
        return _tuning_study_runs(folder)
    try:
        table_runs = read_table(table, dtype=str)
    except ValueError as error:  # pandas' parse errors, an empty file, bytes that are no text
        why = (str(error).splitlines() or [type(error).__name__])[0][:200]
        raise UserError(f"{table}: not a table of runs ({why})") from None
    if "study" not in table_runs:  # written before repeated tuning studies: one study
        return _study_runs(folder, table, table_runs)
    found = [
        _study_runs(folder, table, table_runs[table_runs["study"].astype(str) == str(k)])
        for k in sorted(set(table_runs["study"].astype(str)), key=lambda k: (len(k), k))
    ]
    if not found or any(study is None for study in found):
        return None
    if len(found) == 1:
        return found[0]
    return replace(found[0], tuning=tuple(found))


def _planned(name: str) -> int:
    """The tuning studies a study of the profiles is to have (0: not one of theirs)."""
    return max((s.studies for p in PROFILES.values() for s in p if s.name == name), default=0)


def _tuning_study_runs(folder: Path) -> StudyRuns | None:
    """A study run one compare per tuning study (<folder>/study-k, slices) as StudyRuns: the
    first finished study's, with every finished one in `tuning`, in the order of k; None if none
    has finished. A study folder that is a link is not read (someone else's)."""

    subs = list(folder.iterdir()) if folder.is_dir() and not folder.is_symlink() else []
    found = {}
    numbered = (re.fullmatch(STUDY_FOLDER.format(k=r"([1-9][0-9]{0,5})"), p.name) for p in subs)
    for k in sorted(int(m[1]) for m in numbered if m):
        sub = folder / STUDY_FOLDER.format(k=k)
        if sub.is_symlink():
            raise UserError(f"{sub}: a link: refused (a study may come from someone else)")
        runs = read_study(sub) if (sub / "runs.csv").is_file() else None
        if runs is not None:
            if runs.tuning:
                raise UserError(
                    f"{sub}: {len(runs.tuning)} tuning studies, where a study-k folder holds one"
                )
            found[k] = runs
    if not found:
        return None
    studies = [replace(runs, planned=_planned(folder.name)) for runs in found.values()]
    return replace(studies[0], tuning=tuple(studies) if len(studies) > 1 else ())


def _kept_runs(kept) -> StudyRuns | None:
    """Kept evidence (experiments/evidence.py) as StudyRuns: every tuning study's, the first's
    with the others in `tuning`."""
    found = [
        StudyRuns(
            kept.path,
            kept.axis,
            kept.budget,
            {variant: {seed: str(kept.path) for seed in by} for (variant, _), by in curves.items()},
            kept.machine,
            kept=curves,
            protocol=kept.protocol,
            # an untuned evaluation (no trials) has no tuning studies to be a majority of
            planned=kept.planned if kept.protocol[0] else len(kept.studies),
        )
        for curves in kept.studies
        if curves  # a tuning study not kept (yet)
    ]
    if not found:
        return None
    if len(found) > 1:
        found[0].tuning = tuple(found)
    return found[0]


def _study_runs(folder: Path, table: Path, runs: object) -> StudyRuns | None:
    """One tuning study's rows of runs.csv as StudyRuns (read_study)."""

    if not len(runs) or not {"variant", "seed", "axis", "budget", "path"} <= set(runs.columns):
        return None
    if (folder / "eval").is_symlink():  # resolving it would make anywhere "inside"
        raise UserError(f"{folder / 'eval'}: a link: refused (a study may come from someone else)")
    paths = {}
    for row in runs.itertuples():
        number = int(row.Index) + 2  # the table's line (a header, then rows from 0)
        parts = Path(str(row.path)).parts
        seed = str(row.seed)
        # a seed as physgrad writes one: ASCII digits below 2^32 ("²" is a digit to str.isdigit)
        if "eval" not in parts or not (seed.isascii() and seed.isdecimal() and len(seed) <= 10):
            raise UserError(f"{table} line {number}: not a run of this study (seed {seed!r})")
        path = folder.joinpath(*parts[len(parts) - 1 - parts[::-1].index("eval") :])
        if ".." in path.relative_to(folder).parts or not inside(path, folder / "eval"):
            raise UserError(f"{table} line {number}: its path leaves {folder / 'eval'}")
        paths.setdefault(str(row.variant), {})[int(seed)] = str(path)
    try:
        budget = float(runs["budget"].iloc[0])
    except ValueError:
        raise UserError(f"{table}: budget {runs['budget'].iloc[0]!r} is not a number") from None
    machines = sorted(set(runs["machine"].astype(str))) if "machine" in runs else []
    return StudyRuns(folder, str(runs["axis"].iloc[0]), budget, paths, "; ".join(machines))


def study_protocol(folder: Path) -> tuple[int, int, int] | None:
    """What a finished study ran: (trials per variant and tuning study, tuning studies, seeds),
    read from its trials.csv and runs.csv (0 trials: untuned); None if it has not finished."""
    import pandas as pd

    runs = read_study(folder)
    if runs is None:
        return None
    if runs.protocol is not None:  # kept evidence says what the study ran
        return runs.protocol
    studies = len(runs.tuning) or 1
    seeds = max((len(by) for by in runs.paths.values()), default=0)
    trials = 0
    # one compare, or one per tuning study (<folder>/study-k)
    for table in [folder / "trials.csv", *(s.folder / "trials.csv" for s in tuning_studies(runs))]:
        if not table.is_file():
            continue
        try:
            rows = read_table(table)
        except ValueError:  # empty: an untuned study (the presets' twin) tried no trials
            rows = pd.DataFrame()
        if {"variant", "trial"} <= set(rows.columns) and len(rows):
            keys = ["variant", "study"] if "study" in rows.columns else ["variant"]
            trials = max(trials, int(rows.groupby(keys)["trial"].nunique().max()))
    return trials, studies, seeds


def _study_record(folder: Path, runs: StudyRuns, study: int = 0) -> dict:
    """What a kept tuning study records of itself: its machine, the physgrad commits its runs
    recorded, the commit that kept it, the compare overrides that ran it, and its tuning
    (tuned_trials), so that what the tuning chose can be audited from the evidence."""
    return {
        "machine": runs.machine,
        "commits": run_commits(runs),
        "kept_by": commit(),
        "overrides": study_overrides(folder),
        **tuned_trials(folder, study),
    }


def run_commits(runs: StudyRuns) -> list[str]:
    """The physgrad commits a study's evaluation runs recorded in their results files ("+dirty"
    where the tree had changes), so that the evidence says which code ran it."""
    from physgrad.results import read_final

    ran = set()
    for by_seed in runs.paths.values():
        for path in by_seed.values():
            try:
                ran.add(str(read_final(Path(path))[0].get("git_commit", "unknown")))
            except (OSError, ValueError):
                ran.add("unreadable")
    return sorted(ran)


def tuned_trials(folder: Path, study: int = 0) -> dict:
    """{"trials": [...], "tuned": {variant: {key: value}}} of tuning study `study` from the folder's
    trials.csv (each trial's variant, values and validation loss; a variant's tuned setting is its
    complete trial of lowest validation loss); {} without a readable trials.csv."""
    import math

    try:
        table = read_table(folder / "trials.csv")
    except (OSError, ValueError):
        return {}
    if "study" not in table or "validation_loss" not in table:
        return {}
    mine = table[table["study"] == study]
    keys = [
        c
        for c in mine.columns
        if c not in ("variant", "study", "trial", "validation_loss", "state")
    ]
    trials, tuned = [], {}
    for row in mine.to_dict("records"):
        values = {
            k: float(row[k])
            for k in keys
            if isinstance(row.get(k), (int, float)) and math.isfinite(row[k])
        }
        loss = (
            float(row["validation_loss"])
            if isinstance(row["validation_loss"], (int, float))
            else math.nan
        )
        trials.append({"variant": str(row["variant"]), **values, "validation_loss": loss})
    for variant in sorted({t["variant"] for t in trials}):
        scored = [
            t for t in trials if t["variant"] == variant and math.isfinite(t["validation_loss"])
        ]
        if scored:
            best = min(scored, key=lambda t: t["validation_loss"])
            tuned[variant] = {
                k: v for k, v in best.items() if k not in ("variant", "validation_loss")
            }
    return {"trials": trials, "tuned": tuned} if trials else {}


def study_overrides(folder: Path) -> list[str]:
    """The compare overrides a study folder's study.json records ([] without one); UserError (one
    line) for a study.json that is a link, no regular file, not JSON or not a record of them."""
    path = folder / "study.json"
    if not os.path.lexists(path):
        return []
    try:
        overrides = read_json(path).get("overrides", [])
    except (OSError, ValueError, AttributeError) as error:
        raise UserError(f"{path}: not a study record ({type(error).__name__}: {error})") from None
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise UserError(f"{path}: its overrides are not a list of text")
    return overrides


def keep_studies(root: Path, dest: Path, columns: dict[str, set]) -> list[str]:
    """Every finished study under root named in columns (study -> the columns read of it), and its
    presets' twin, as evidence tables in dest (experiments/evidence.py): those columns at the kept
    fractions of its budget, for every tuning study, variant and seed. A study run one compare per
    tuning study (<name>/study-k) adds each finished one to the kept table, replacing its rows if
    it was kept before and keeping the others' (each is kept whatever machine ran it), and keeps
    the first's calibration as the study's clock; a study run in one compare replaces every study
    it has. Returns the studies kept (<name>, or <name>/study-k)."""
    kept = []
    for name in sorted(columns):
        for folder in (root / name, root / f"{name}-preset"):
            runs = read_study(folder) if folder.is_dir() and not folder.is_symlink() else None
            if runs is None or runs.kept is not None:
                continue
            split = not (folder / "runs.csv").is_file()  # one compare per tuning study
            finished = {}
            for k, study in enumerate(tuning_studies(runs), 1):
                where = study.folder if split else folder
                k = int(where.name.partition("-")[2]) if split else k
                finished[k] = (
                    [
                        kept_row(k - 1, variant, seed, column, curve, runs.budget)
                        for variant in sorted(study.paths)
                        for column in sorted(columns[name])
                        for seed, curve in sorted(study.curves(variant, column).items())
                    ],
                    _study_record(where, study, 0 if split else k - 1),
                )
                kept.append(f"{folder.name}/{where.name}" if split else folder.name)
            kept = list(dict.fromkeys(kept))  # a study run in one compare: its name once
            clock = dest / CLOCK.format(name=name)
            if split and 1 in finished and busy_clock(clock):
                # the first study run again replaces a busy kept clock, and every tuning study
                # kept on it: their budget bought fewer steps than it says (they run again)
                for suffix in (".csv", ".json"):
                    (dest / f"{folder.name}{suffix}").unlink(missing_ok=True)
            if split:
                rows, by_study = merged_rows(dest, folder.name, finished, runs.budget)
            else:  # one compare: it replaces what was kept
                rows = [row for found, _ in finished.values() for row in found]
                by_study = {str(k): record for k, (_, record) in finished.items()}
            trials, _, seeds = study_protocol(folder)
            about = {
                "study": folder.name,
                "axis": runs.axis,
                "budget": runs.budget,
                "trials": trials,
                "studies": len(by_study),
                "planned": max(
                    _planned(name) if folder.name == name and trials else 1, len(by_study)
                ),
                "seeds": seeds,
                "machine": "; ".join(
                    sorted({str(r.get("machine") or "") for r in by_study.values()} - {""})
                ),
                # of physgrad, as the runs recorded it
                "commits": sorted({c for r in by_study.values() for c in r.get("commits", [])}),
                "kept_by": commit(),
                "overrides": by_study[min(by_study, key=int)].get("overrides", []),
                "tuning_studies": by_study,
            }
            write_kept(dest, folder.name, rows, about)
            if split:
                keep_clock(folder / "study-1" / "calibration.json", clock)
    return kept


def uncommitted_note(root: Path, *others: Path) -> str:
    """ "; runs from uncommitted changes: NAME (COMMIT), ..." for the kept studies under root (and
    under each of others, named FOLDER/NAME) whose runs recorded a commit with uncommitted changes
    ('+dirty'), "" where none did."""
    from evidence import read_json

    found = []
    paths = [(p, p.stem) for p in sorted(root.glob("*.json"))]
    paths += [
        (p, f"{other.name}/{p.stem}") for other in others for p in sorted(other.glob("*.json"))
    ]
    for path, name in paths:
        try:
            record = read_json(path)
        except (OSError, ValueError):
            continue
        studies = record.get("tuning_studies", {}) if isinstance(record, dict) else {}
        commits = {
            str(c)
            for r in [record, *(studies.values() if isinstance(studies, dict) else [])]
            if isinstance(r, dict)
            for c in (r.get("commits") or [])
            if "+dirty" in str(c)
        }
        found += [f"{name} ({c[:12]}{c[c.index('+') :]})" for c in sorted(commits)]
    return "; runs from uncommitted changes: " + ", ".join(found) if found else ""
