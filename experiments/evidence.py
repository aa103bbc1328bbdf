"""The claims' evidence, kept in the repository: each finished claims study as a table of the
numbers its verdicts are decided from (kilobytes), so that docs/claims.md can be regenerated and
checked without the study folders (hours of computing, gigabytes of results files).

<name>.csv, one row per (tuning study, variant, seed, column): the run's held-out `column` at its
first evaluation (`start`) and at 1/8, 1/4, 1/2 and all of the study's budget X (`at_0.125` ...
`at_1`), as physgrad.readout.Curve.at reads them: inf where the run had diverged by then, NaN where
it ended before without diverging. <name>.json: the study's budget and its axis, the protocol it
ran (trials, tuning studies, seeds), the machine, the physgrad commits its runs recorded and the one
that kept it, and the compare overrides that ran it. The verdicts read these values only at those
fractions (a value asked for at another fraction is missing, NaN), with the same rules as from the
study folder.

Usage (from the repository's root):
  python experiments/claims.py --keep outputs/experiments/claims docs/evidence/claims
  python experiments/claims.py docs/evidence/claims docs        # docs/claims.md from the evidence
"""

from __future__ import annotations

import json
import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FRACTIONS = (0.125, 0.25, 0.5, 1.0)
COLUMNS = ("study", "variant", "seed", "column", "start", *(f"at_{f:g}" for f in FRACTIONS))


@dataclass(frozen=True)
class KeptCurve:
    """A run's held-out values at the kept fractions of the budget; at(x) reads one of them (NaN at
    any other x), loss[0] is its first evaluation (as physgrad.readout.Curve)."""

    budget: float
    values: dict = field(default_factory=dict)  # fraction -> value
    start: float = math.nan

    @property
    def loss(self) -> np.ndarray:
        return np.array([self.start])

    def at(self, x: float) -> float:
        for fraction, value in self.values.items():
            if math.isclose(fraction * self.budget, x, rel_tol=1e-9):
                return value
        return math.nan


def kept_row(study: int, variant: str, seed: int, column: str, curve, budget: float) -> dict:
    """One row of the table from a run's curve (physgrad.readout.Curve)."""
    start = float(curve.loss[0]) if len(curve.loss) else math.nan
    return {
        "study": study,
        "variant": variant,
        "seed": seed,
        "column": column,
        "start": start,
        **{f"at_{f:g}": curve.at(budget * f) for f in FRACTIONS},
    }


def commit(root: Path | None = None) -> str:
    """The commit of the checkout that keeps the evidence (`unknown` outside a git checkout), with
    '+dirty:<hash>' where it has uncommitted changes (the hash of their diff,
    physgrad.machine.checkout_commit): the evidence then says so rather than naming a commit whose
    code did not read it."""
    from physgrad.machine import checkout_commit

    found = checkout_commit(root or Path(__file__).resolve().parent.parent)
    head, _, dirty = found.partition("+")
    return (head[:12] + (f"+{dirty}" if dirty else "")) or "unknown"


# --- the doors: every file read from a study folder or evidence folder (someone else's, maybe) is
# opened without following a link, a regular file only and bounded (physgrad.files.read_own_file);
# every file written into one replaces its target by a rename (physgrad.files.replace_file)
FILE_LIMIT = 64 << 20  # a study's tables are kilobytes to megabytes


def read_table(path: Path, **options: object) -> object:
    """A CSV file as a pandas DataFrame, through the reading door; ValueError (one line) for a link,
    a FIFO, a folder or text that is not a table, OSError where it cannot be read."""
    import io

    import pandas as pd

    from physgrad.files import read_own_file

    return pd.read_csv(io.BytesIO(read_own_file(path, FILE_LIMIT)), **options)


def read_json(path: Path) -> object:
    """A JSON file as data, through the reading door (ValueError, OSError as read_table)."""
    from physgrad.files import load_json, read_own_file

    return load_json(read_own_file(path, FILE_LIMIT))


def write_kept(dest: Path, name: str, rows: list[dict], about: dict) -> None:
    """dest/<name>.csv and dest/<name>.json."""
    import pandas as pd

    from physgrad.files import replace_file

    dest.mkdir(parents=True, exist_ok=True)
    table = pd.DataFrame(rows, columns=list(COLUMNS)).sort_values(
        ["column", "variant", "study", "seed"], kind="stable"
    )
    # every digit: the verdicts read back exactly
    replace_file(dest / f"{name}.csv", table.to_csv(index=False).encode())
    replace_file(dest / f"{name}.json", (json.dumps(about, indent=1) + "\n").encode())


STUDY_FOLDER = "study-{k}"  # tuning study k (1, 2, ...) of a study run one compare per tuning study
CLOCK = "{name}.calibration.json"  # a study's kept calibration, beside its evidence


def merged_rows(dest: Path, name: str, finished: dict, budget: float) -> tuple[list, dict]:
    """The rows and the per-study record (`tuning_studies`: "k" -> its machine, commit, ...) of
    dest/<name> once the finished tuning studies are added: finished[k] = (its rows, with study
    k - 1, and its record); a study kept before is replaced, the others kept (each tuning study
    is kept whatever machine ran it). Evidence kept before studies were recorded on their own
    gets a record per study from its one. A budget other than the kept one is a UserError."""

    from physgrad.errors import UserError

    table_path, about_path = dest / f"{name}.csv", dest / f"{name}.json"
    rows, about = [], {}
    if table_path.is_file():
        about = read_json(about_path)
        if not math.isclose(float(about["budget"]), budget, rel_tol=1e-9):
            raise UserError(
                f"{name}: a budget of {budget:g}, where {table_path} keeps "
                f"{float(about['budget']):g}; keep it in another folder"
            )
        old = read_table(table_path, dtype={"variant": str, "column": str})
        rows = old[~old["study"].isin([k - 1 for k in finished])].to_dict("records")
    by_study = about.get("tuning_studies") or {
        str(int(k) + 1): {
            key: about[key]
            for key in ("machine", "kept_by", "commits", "iterations", "overrides")
            if key in about
        }
        for k in sorted({row["study"] for row in rows})
    }
    for k, (new_rows, record) in finished.items():
        rows += new_rows
        by_study[str(k)] = record
    return rows, dict(sorted(by_study.items(), key=lambda item: int(item[0])))


def clock_rules(path: Path) -> set[str]:
    """The variants a calibration.json has a step cost for (none if it cannot be read)."""
    try:
        costs = read_json(path).get("costs")
    except (OSError, ValueError, AttributeError):
        return set()
    return set(costs) if isinstance(costs, dict) else set()


def busy_clock(path: Path) -> str:
    """Why a calibration.json was measured on a busy machine (its load average against its cores,
    physgrad's rule), or "" (also where it cannot be read)."""
    from physgrad.comparison.clock_text import busy_calibration

    try:
        return busy_calibration(read_json(path))
    except (OSError, ValueError, AttributeError, KeyError, TypeError):
        return ""


def keep_clock(measured: Path, clock: Path) -> None:
    """A study's calibration kept as its clock (for its tuning studies still to run, on any
    machine): the first kept, or one with a variant the kept one lacks, or a quiet one where the
    kept one was measured on a busy machine; never one measured on a busy machine, which would
    charge every later study's steps what they cost beside other work."""
    from physgrad.files import read_own_file, replace_file

    if busy_clock(measured) or not measured.is_file():
        return
    if not clock_rules(measured) <= clock_rules(clock) or busy_clock(clock):
        clock.parent.mkdir(parents=True, exist_ok=True)
        replace_file(clock, read_own_file(measured, FILE_LIMIT))


@dataclass
class Kept:
    """An evidence table read back: the study's budget, axis, machine and protocol, and per tuning
    study {(variant, column): {seed: KeptCurve}}."""

    path: Path
    axis: str
    budget: float
    machine: str
    protocol: tuple  # (trials, tuning studies, seeds)
    studies: list
    planned: int = 0  # the tuning studies the study is to have (0: those kept)


def kept_table(folder: Path) -> Path | None:
    """The evidence table of a study folder's name (`<root>/<name>.csv`), if there is one; a name
    that holds something else (a FIFO, a folder) is a UserError, not a study that did not run."""
    from physgrad.errors import UserError
    from physgrad.files import file_kind

    path = folder.parent / f"{folder.name}.csv"
    try:
        mode = os.stat(path).st_mode  # a link is read (and refused) by read_kept's door
    except OSError:
        return None
    if not stat.S_ISREG(mode):
        raise UserError(f"{path}: {file_kind(mode)}, not a file: not an evidence table")
    return path


def read_kept(path: Path) -> Kept:
    """An evidence table and its .json, checked: anything else is a UserError naming the file."""
    import pandas as pd

    from physgrad.errors import UserError

    about_path = path.with_suffix(".json")
    reading = about_path
    try:
        about = read_json(about_path)
        axis, budget = str(about["axis"]), float(about["budget"])
        protocol = tuple(int(about[k]) for k in ("trials", "studies", "seeds"))
        for key, value, top in zip(("trials", "studies", "seeds"), protocol, PROTOCOL_TOPS):
            low = 0 if key == "trials" else 1  # no trials: an untuned evaluation (a presets' twin)
            if not low <= value <= top or value != about[key]:
                raise ValueError(f"{key}={about[key]!r} is not a whole number in [{low}, {top}]")
        reading = path
        table = read_table(path, dtype={"variant": str, "column": str})
    except (OSError, ValueError, KeyError, TypeError) as error:
        why = f"{type(error).__name__}: {error}".splitlines()[0][:200]
        what = "an evidence table" if reading == path else "an evidence table's record"
        raise UserError(f"{reading}: not {what} ({why})") from None
    if list(table.columns) != list(COLUMNS) or not math.isfinite(budget) or budget <= 0:
        raise UserError(f"{path}: not an evidence table (columns {list(table.columns)})")
    numbers = table.drop(columns=["variant", "column"])
    if not all(pd.api.types.is_numeric_dtype(t) for t in numbers.dtypes):
        raise UserError(f"{path}: a value that is not a number")
    _check_kept(path, table, axis)
    studies: list = [dict() for _ in range(int(table["study"].max()) + 1 if len(table) else 0)]
    for row in table.itertuples(index=False):
        values = {f: float(row[5 + i]) for i, f in enumerate(FRACTIONS)}
        curve = KeptCurve(budget, values, float(row.start))
        studies[int(row.study)].setdefault((row.variant, row.column), {})[int(row.seed)] = curve
    planned = about.get("planned", 0)
    planned = planned if isinstance(planned, int) and 0 <= planned <= 1000 else 0
    return Kept(path, axis, budget, str(about.get("machine", "")), protocol, studies, planned)


# bounds on kept evidence, read as data: a study's table is kilobytes (10 seeds x variants x
# columns x tuning studies); beyond these it is not one of physgrad's
# (a leaderboard scene: 4 tuning studies x 12 rules x 10 seeds = 480 rows; a claims study about
# 1,000)
KEPT_ROWS, KEPT_STUDIES, KEPT_SEED, KEPT_NAME = 20_000, 100, 2**32, 200
# the largest trials per tuning study, tuning studies and seeds a study's record may state
PROTOCOL_TOPS = (10_000, KEPT_STUDIES, 1024)
AXES = ("iteration", "wall_time", "calibrated_time")


def _check_kept(path: Path, table: object, axis: str) -> None:
    """An evidence table's fields within their bounds (rows, the study and seed numbers whole and in
    range, names short text without control characters, the axis known); UserError (one line)
    naming the file and the field otherwise."""
    import numpy as np

    from physgrad.errors import UserError
    from physgrad.files import clean_text

    def refuse(name: str, why: str) -> None:
        raise UserError(f"{path}: {name}: {why}; not an evidence table")

    if axis not in AXES:
        refuse("axis", f"{clean_text(axis, 40)!r} is none of {', '.join(AXES)}")
    if len(table) > KEPT_ROWS:
        refuse("rows", f"{len(table)}, more than {KEPT_ROWS}")
    for column, top in (("study", KEPT_STUDIES), ("seed", KEPT_SEED)):
        values = np.asarray(table[column], float)
        whole = np.isfinite(values) & (values == np.round(values))
        if not whole.all() or (values < 0).any() or (values >= top).any():
            bad = values[~whole | (values < 0) | (values >= top)][0]
            refuse(column, f"{bad:g} is not a whole number in [0, {top})")
    for column in ("variant", "column"):
        for name in table[column]:
            if not isinstance(name, str) or len(name) > KEPT_NAME or clean_text(name) != name:
                refuse(column, f"{clean_text(str(name), 40)!r} is not a name")


def undecided_by_the_clock(folder: Path) -> dict[str, list[float]]:
    """ "A vs B" -> the fractions of the budget where the study's compare (its comparisons.csv)
    found A's or B's "better" undecided by the clock (physgrad.verdict.clock_check). The check
    reads each run's loss at a shifted time, which the kept fractions do not hold, so a study's
    record keeps its outcome."""
    from physgrad.errors import UserError
    from physgrad.verdict import UNDECIDED_BY_THE_CLOCK

    path = folder / "comparisons.csv"
    if not path.is_file():
        return {}
    try:
        table = read_table(path, dtype=str)
        rows = table[table["why"].fillna("").str.startswith(UNDECIDED_BY_THE_CLOCK)]
        found: dict[str, list[float]] = {}
        for a, b, fraction in zip(rows["a"], rows["b"], rows["fraction"].astype(float)):
            found.setdefault(f"{a} vs {b}", []).append(fraction)
    except (KeyError, ValueError, AttributeError) as error:
        raise UserError(f"{path}: not a table of comparisons ({error})") from None
    return found


def keep_clock_verdicts(per_study: list, records: dict) -> None:
    """Each tuning study's verdicts (per_study[k]: its PairVerdicts, a list or a dict of them)
    with the "better" its compare found undecided by the clock made undecided again, from its
    kept record (records: the .json's tuning_studies, "1", "2", ... -> a record whose
    undecided_by_the_clock is "A vs B" -> fractions; nothing where they are not one per study,
    as in the one-study format)."""
    from physgrad.errors import UserError
    from physgrad.verdict import A_BETTER, B_BETTER, UNDECIDED, UNDECIDED_BY_THE_CLOCK

    if len(records) != len(per_study):
        return
    for results, key in zip(per_study, sorted(records, key=int)):
        record = records[key]
        flagged = record.get("undecided_by_the_clock") or {}
        if not isinstance(flagged, dict) or not all(
            isinstance(f, list) and all(isinstance(x, (int, float)) for x in f)
            for f in flagged.values()
        ):
            raise UserError("undecided_by_the_clock: not pairs and fractions; keep the study again")
        for result in results.values() if isinstance(results, dict) else results:
            for fraction in flagged.get(f"{result.a} vs {result.b}", ()):
                if result.verdicts.get(fraction, ("",))[0] in (A_BETTER, B_BETTER):
                    why = f"the study's compare: {UNDECIDED_BY_THE_CLOCK}"
                    result.verdicts[fraction] = (UNDECIDED, why)
