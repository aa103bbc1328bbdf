"""Results files: one HDF5 file per run, written incrementally, and reading many of them into one
table.

Layout (see docs/results.md):
  root attributes: task, optim, unroll (temporal scenes only), seed, status, reason, config,
                   physgrad_version, jax_version, compile_seconds, created, and a few descriptive
                   extras;
  /train/{iteration, wall_time, loss, grad_norm, ...}: one row per iteration;
  /eval/{iteration, wall_time, loss, <scene metrics>}: held-out evaluations;
  /params: the final network as one flat vector (every run that did not diverge or fail).
At every flush the whole file is written beside results.h5 and renamed onto it, so a run killed at
any moment leaves a complete file holding every row flushed so far, and readers never share a file
with the writer. A file is read as foreign data, every attribute and column checked before it is
used (physgrad.foreign).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from physgrad.errors import ResultsWriteError
from physgrad.files import (
    clean_text,
    load_yaml,
    make_folder,
    owner_tag,
    replace_file,
    timestamp,
    walk_files,
)
from physgrad.foreign import (
    STATUSES,
    checked_attrs,
    checked_columns,
    checked_params,
    checked_tables,
    open_results,
    read_columns,
)

GROUPS = ("train", "eval")
# a re-run's file while a completed results.h5 it would replace stays valid
ASIDE_SUFFIX = ".overwriting.h5"


def holds_completed(path: Path) -> bool:
    try:
        return read_final(path)[0].get("status") == "completed"
    except (ValueError, OSError):
        return False


class ResultsWriter:
    """Keeps every row of a run in memory (one tuple per row, so an interrupt can never leave a row
    half appended) and writes the whole file at each flush() into a temporary file beside it, which
    then replaces results.h5 by an atomic rename. So the file on disk is always a complete,
    consistent earlier state: a kill at any instant loses at most the rows since the last flush, a
    write cut short by a signal or a full disk leaves the previous version, and a reader (any
    reader, with or without HDF5 file locking) keeps the version it opened and never blocks the
    writer. A completed results.h5 is not replaced before its successor has completed: until then
    the run writes results.overwriting.h5 beside it."""

    def __init__(self, path: str | os.PathLike, attrs: dict, write: bool = True) -> None:
        self.path = Path(path)
        make_folder(self.path.parent)  # a run's seed=N/ or trial=N/: a link there is refused
        self.live = (
            self.path.with_name(self.path.stem + ASIDE_SUFFIX)
            if holds_completed(self.path)
            else self.path
        )
        attrs = {**attrs, "status": "running", "created": timestamp(), "owner": owner_tag()}
        self.attrs = {key: value for key, value in attrs.items() if value is not None}
        self._columns: dict[str, tuple[str, ...] | None] = {group: None for group in GROUPS}
        self._rows: dict[str, list[tuple]] = {group: [] for group in GROUPS}  # not yet flushed
        # flushed chunks
        self._data: dict[str, dict[str, list[np.ndarray]]] = {group: {} for group in GROUPS}
        self._params: np.ndarray | None = None
        for stale in self.live.parent.glob(f".{self.live.name}.*.tmp"):  # a killed writer's
            stale.unlink(missing_ok=True)
        if write:  # (not for a file that is finished at once: see record_outcome)
            self._write()

    def set_columns(self, group: str, names: Iterable[str]) -> None:
        """Fix the columns of a group; append_row() then takes values in this order."""
        names = tuple(names)
        if self._columns[group] is not None and set(self._columns[group]) != set(names):
            raise ValueError(
                f"/{group} row has columns {sorted(names)}, expected {sorted(self._columns[group])}"
            )
        if self._columns[group] is None:
            self._columns[group] = names

    def append(self, group: str, row: dict) -> None:
        self.set_columns(group, row)
        self._rows[group].append(tuple(row[name] for name in self._columns[group]))

    def append_row(self, group: str, values: tuple) -> None:
        """The hot path of the training loop: values in the order given to set_columns()."""
        self._rows[group].append(values)

    def shift_buffered_time(self, seconds: float) -> None:
        """Add seconds to the wall_time of every row not yet flushed (the runner moves the first
        step's one-off cost out of the training time this way)."""
        for group, rows in self._rows.items():
            if rows and "wall_time" in self._columns[group]:
                at = self._columns[group].index("wall_time")
                rows[:] = [(*row[:at], row[at] + seconds, *row[at + 1 :]) for row in rows]

    def flush(self, sync: bool = False) -> None:
        """Write the file with every row so far and the attributes set since (sync: to the disk
        itself, not only to the operating system, which a killed process cannot lose anyway)."""
        for group, rows in self._rows.items():
            if rows:
                columns = self._data[group]
                for key, column in zip(self._columns[group], zip(*rows)):
                    columns.setdefault(key, []).append(np.asarray(column))
                rows.clear()
        self._write(sync)

    def set_attrs(self, **attrs: Any) -> None:
        """Set (None: remove) root attributes; they reach the file with the next flush()."""
        for key, value in attrs.items():
            if value is None:
                self.attrs.pop(key, None)
            else:
                self.attrs[key] = value

    def save_params(self, flat: np.ndarray) -> None:
        """The network's final parameters as one flat vector (ravel_pytree order) in /params, with
        the next flush()."""
        self._params = np.asarray(flat)

    def finish(
        self, status: str, reason: str | None = None, sync: bool = True, **attrs: Any
    ) -> None:
        """Record the final status (and the reason for anything but completed) and write the file,
        synced to disk (sync). A completed run written aside replaces the completed results.h5 only
        now."""
        if status not in STATUSES:
            raise ValueError(f"unknown status {status!r}")
        self.set_attrs(status=status, reason=reason, finished=timestamp(), **attrs)
        self.flush(sync=sync)
        if self.live != self.path and status == "completed":
            os.replace(self.live, self.path)
            self.live = self.path

    def mark_failed_in_place(self, reason: str) -> bool:
        """Last resort when a full write fails (disk full): set status failed and the reason on the
        file as it is, a few bytes of attributes. True if that worked."""
        try:  # never through a link put at the file's name (its folder may be someone else's)
            stream = os.fdopen(os.open(self.live, os.O_RDWR | os.O_NOFOLLOW), "r+b")
            with stream, h5py.File(stream, "r+", locking=False) as f:
                f.attrs.update(status="failed", reason=reason, finished=timestamp())
            return True
        except (OSError, ValueError):
            return False

    def _write(self, sync: bool = False) -> None:
        """The file is built in memory (HDF5's core driver) and its bytes written by Python: a
        failing write() (disk full, quota, size limit) is then an OSError here, where HDF5 writing
        to disk itself crashed the process when a write failed as it closed the file."""
        self.attrs["heartbeat"] = timestamp()
        try:
            with h5py.File(f"physgrad-{id(self)}.h5", "w", driver="core", backing_store=False) as f:
                for key, value in self.attrs.items():
                    f.attrs[key] = value
                for group in GROUPS:
                    g = f.create_group(group)
                    for key, chunks in self._data[group].items():
                        g.create_dataset(key, data=np.concatenate(chunks), maxshape=(None,))
                if self._params is not None:
                    f.create_dataset("params", data=self._params)
                f.flush()
                image = f.id.get_file_image()
            replace_file(self.live, image, sync)
        except OSError as error:
            raise ResultsWriteError(
                f"cannot write {self.live}: {error.strerror or error}"
            ) from error


def record_outcome(path: str | os.PathLike, attrs: dict, status: str, reason: str) -> None:
    """A results file of attributes only, for a job refused, failed or interrupted before training:
    one write, not synced (a job of a thousand seeds writes a thousand of them, and a signal must
    not wait for that); a completed file at path is kept, as ResultsWriter keeps it."""
    ResultsWriter(path, attrs, write=False).finish(status, reason, sync=False)


@dataclass
class Run:
    """One results file, read back: attributes and the /train and /eval columns as numpy arrays."""

    path: Path
    attrs: dict
    train: dict
    eval: dict
    # the problem settings that tell this run's scene apart from others of its task
    setting: str = ""
    # in a report: its group (variant and the method settings that differ), see physgrad.report
    label: str = ""
    collection: str = ""  # in a report: the label of the set of runs it was found in (LABEL=PATH)
    # the stored config parsed as plain data (parse_config)
    config: dict = field(default_factory=dict)

    @property
    def scene(self) -> str:
        """The task, with the distinguishing settings: runs are only compared within one scene."""
        return f"{self.attrs.get('task', '?')} {self.setting}".strip()

    @property
    def variant(self) -> str:
        """The variant as its file names it, in today's spelling (`bptt backprop=M clip=norm`;
        files written before it spelled the marks `bptt[M,clip=norm]`)."""
        return _OLD_MARKS.sub(
            lambda m: " ".join(
                [m[1], *(mark if "=" in mark else f"backprop={mark}" for mark in m[2].split(","))]
            ),
            str(self.attrs.get("variant", self.attrs.get("optim", "?"))),
        )

    @property
    def seconds_per_iteration(self) -> float:
        wall = self.train.get("wall_time", np.empty(0))
        return float(np.median(np.diff(np.concatenate([[0.0], wall])))) if wall.size else math.nan

    def offset(self, x_key: str) -> float:
        """Where this run's x axis starts: a run started from another's network (init_from)
        continues that run's iterations and training seconds."""
        key = {"wall_time": "init_train_seconds", "iteration": "init_iterations"}.get(x_key)
        return float(self.attrs.get(key, 0.0)) if key else 0.0

    def final(self, group: str, column: str = "loss") -> float:
        values = getattr(self, group).get(column, np.empty(0))
        return float(values[-1]) if values.size else math.nan


# the marks of a variant label as older files spelled them: name[mode,clip=...] (Run.variant)
_OLD_MARKS = re.compile(r"(\w+)\[([\w=,]+)\]")

CONFIG_KEYS_LIMIT = 10_000  # settings in a stored config; a physgrad config holds about a hundred


def parse_config(text: str) -> dict:
    """The stored config (its length bounded by the reader, physgrad.foreign) as plain data (nested
    dicts, lists, scalars), text cleaned as clean_text; ValueError (one line) if it is not YAML,
    holds an alias, is not a mapping or holds more than CONFIG_KEYS_LIMIT settings (a table would
    get a column for each). Interpolations such as ${...} stay the text they are."""
    try:
        tree = load_yaml(text) if text.strip() else {}
    except ValueError as error:
        raise ValueError(f"the config attribute is {error}") from None
    if not isinstance(tree, dict):
        raise ValueError(f"the config attribute is a {type(tree).__name__}, not a mapping")
    return _clean_tree(tree, [0])


def _clean_tree(tree: Any, settings: list[int]) -> Any:
    """tree with its text cleaned, counting its mappings' keys and lists' items in settings[0]."""
    if isinstance(tree, (dict, list)):
        settings[0] += len(tree)
        if settings[0] > CONFIG_KEYS_LIMIT:
            raise ValueError(
                f"the config attribute holds more than {CONFIG_KEYS_LIMIT} settings (a physgrad "
                "config holds about a hundred)"
            )
    if isinstance(tree, dict):
        return {clean_text(str(key)): _clean_tree(value, settings) for key, value in tree.items()}
    if isinstance(tree, list):
        return [_clean_tree(value, settings) for value in tree]
    return clean_text(tree) if isinstance(tree, str) else tree


def _config_of(path: Path, attrs: dict) -> dict:
    try:
        return parse_config(attrs.get("config", ""))
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def read_run(path: str | os.PathLike, follow: bool = False) -> Run:
    """Read one results file with every check of physgrad.foreign (follow: a link at path is
    followed, for a path the user gave); ValueError with a one-line reason if it is not a physgrad
    results file, cannot be read, fails a check or is inconsistent."""
    path = Path(path)
    with open_results(path, follow) as f:
        attrs = checked_attrs(path, f)
        columns = checked_tables(path, f, GROUPS)
        config = _config_of(path, attrs)
        data = read_columns(
            path,
            lambda: {
                group: {key: column[()] for key, column in cols.items()}
                for group, cols in columns.items()
            },
        )
    return Run(path, attrs, data["train"], data["eval"], config=config)


def read_final(path: str | os.PathLike, follow: bool = False) -> tuple[dict, dict]:
    """The attributes and the last /eval row of a results file, without reading the curves (a
    resumed sweep checks every job this way), with the checks of read_run; ValueError (one line) as
    read_run."""
    return read_end(path, follow)[:2]


def read_end(path: str | os.PathLike, follow: bool = False) -> tuple[dict, dict, float]:
    """read_final, and the iteration of the last /train row (NaN without one)."""
    path = Path(path)
    with open_results(path, follow) as f:
        attrs = checked_attrs(path, f)
        train = checked_columns(path, f, "train")
        columns = checked_columns(path, f, "eval")
        _config_of(path, attrs)
        iterations = train.get("iteration")
        last, last_train = read_columns(
            path,
            lambda: (
                {key: column[-1].item() for key, column in columns.items() if column.shape[0]},
                float(iterations[-1])
                if iterations is not None and iterations.shape[0]
                else math.nan,
            ),
        )
    return attrs, last, last_train


def cut_short(attrs: dict, last_train_iteration: float) -> str | None:
    """Why a results file that says its run ended (completed or diverged after `iterations`) does
    not hold that run whole: its training rows end before its last iteration (a file cut short or
    copied from a shorter run); None if they reach it."""
    iterations = attrs.get("iterations")
    if not isinstance(iterations, (int, np.integer)) or isinstance(iterations, bool):
        return None  # written before the record held it: nothing to hold the rows to
    if iterations > 0 and not last_train_iteration + 1 >= iterations:
        return f"its rows end at iteration {last_train_iteration:g} of {iterations}: cut short"
    return None


def read_params(path: str | os.PathLike, follow: bool = False) -> np.ndarray:
    """The flat final parameters a run saved, checked as read_run's columns; ValueError (one line)
    if the file has none or is not readable."""
    path = Path(path)
    with open_results(path, follow) as f:
        attrs = checked_attrs(path, f)
        return checked_params(path, f, attrs["status"])[()]


def natural_key(text: str) -> list:
    """Sort key that orders the numbers inside text by value: 'unroll=16' before 'unroll=128'."""
    return [
        (0, float(part), "") if re.fullmatch(r"\d+(\.\d+)?", part) else (1, 0.0, part)
        for part in re.split(r"(\d+(?:\.\d+)?)", text)
        if part
    ]


def member_order(path: Path) -> tuple[str, int, str]:
    """The sort key of a member's results file (<kind>=<n>/results.h5): seed=2 before seed=10; a
    folder name that is no number (someone else's) last."""
    kind, _, number = path.parent.name.partition("=")
    return (kind, int(number) if number.isascii() and number.isdigit() else 2**63, number)


def find_results(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Every results.h5 at or under the given files and folders, in sorted order. Under a folder the
    walk does not follow links to folders (a folder from someone else could point one at / or at
    itself) and needs no recursion however deep it goes; a results.h5 that is itself a link is
    listed, for the reader to refuse (physgrad.runs.collect)."""
    found = []
    for path in map(Path, paths):
        if path.is_file():
            found.append(path)
        elif path.is_dir():
            found.extend(sorted(walk_files(path, "results.h5")))
        else:
            raise FileNotFoundError(f"{path}: no such file or folder")
    return found
