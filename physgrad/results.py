"""Results files: one HDF5 file per run, written incrementally, and reading many of them into one table.

Layout (see docs/results.md):
  root attributes: task, optim, unroll (temporal scenes only), seed, status, reason, config, physgrad_version,
                   jax_version, compile_seconds, created, and a few descriptive extras;
  /train/{iteration, wall_time, loss, grad_norm, ...}: one row per iteration;
  /eval/{iteration, wall_time, loss, <scene metrics>}: held-out evaluations;
  /params: the final network as one flat vector (every run that did not diverge or fail).
The file is opened, appended to and closed at every flush, so a run killed at any moment leaves a file that
opens, holding every row flushed so far; readers never find it locked for long.
"""

from __future__ import annotations

import math
import os
import re
import signal
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

STATUSES = ("running", "completed", "diverged", "interrupted", "failed", "refused")
GROUPS = ("train", "eval")


@contextmanager
def signals_deferred():
    """Hold SIGINT and SIGTERM back while the file is being written, so that an interrupt (a second Ctrl-C
    raises KeyboardInterrupt at once) never lands between a resize and its write; they arrive right after."""
    held = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class ResultsWriter:
    """Buffers rows per group (one tuple per row, so an interrupt can never leave a row half appended) and
    appends them to resizable datasets on flush()."""

    def __init__(self, path: str | os.PathLike, attrs: dict):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._columns: dict[str, tuple[str, ...] | None] = {group: None for group in GROUPS}
        self._rows: dict[str, list[tuple]] = {group: [] for group in GROUPS}
        with signals_deferred(), h5py.File(self.path, "w") as f:
            for group in GROUPS:
                f.create_group(group)
            for key, value in {**attrs, "status": "running", "created": _now()}.items():
                if value is not None:
                    f.attrs[key] = value

    def set_columns(self, group: str, names) -> None:
        """Fix the columns of a group; append_row() then takes values in this order."""
        names = tuple(names)
        if self._columns[group] is not None and set(self._columns[group]) != set(names):
            raise ValueError(f"/{group} row has columns {sorted(names)}, expected {sorted(self._columns[group])}")
        if self._columns[group] is None:
            self._columns[group] = names

    def append(self, group: str, row: dict) -> None:
        self.set_columns(group, row)
        self._rows[group].append(tuple(row[name] for name in self._columns[group]))

    def append_row(self, group: str, values: tuple) -> None:
        """The hot path of the training loop: values in the order given to set_columns()."""
        self._rows[group].append(values)

    def shift_buffered_time(self, seconds: float) -> None:
        """Add seconds to the wall_time of every row not yet flushed (the runner moves the first step's one-off
        cost out of the training time this way)."""
        for group, rows in self._rows.items():
            if rows and "wall_time" in self._columns[group]:
                at = self._columns[group].index("wall_time")
                rows[:] = [(*row[:at], row[at] + seconds, *row[at + 1:]) for row in rows]

    def flush(self) -> None:
        """Append every buffered row to the file."""
        if not any(self._rows.values()):
            return
        with signals_deferred(), h5py.File(self.path, "a") as f:
            for group, rows in self._rows.items():
                if not rows:
                    continue
                for key, column in zip(self._columns[group], zip(*rows)):
                    column = np.asarray(column)
                    if key not in f[group]:
                        f[group].create_dataset(key, data=column, maxshape=(None,), chunks=(1024,))
                    else:
                        dataset = f[group][key]
                        start = dataset.shape[0]
                        dataset.resize((start + len(rows),))
                        dataset[start:] = column
                rows.clear()

    def set_attrs(self, **attrs) -> None:
        with signals_deferred(), h5py.File(self.path, "a") as f:
            for key, value in attrs.items():
                if value is None:
                    f.attrs.pop(key, None)
                else:
                    f.attrs[key] = value

    def save_params(self, flat: np.ndarray) -> None:
        """The network's final parameters as one flat vector (ravel_pytree order) in /params, replacing any."""
        with signals_deferred(), h5py.File(self.path, "a") as f:
            if "params" in f:
                del f["params"]
            f.create_dataset("params", data=flat)

    def finish(self, status: str, reason: str | None = None, **attrs) -> None:
        """Flush every buffered row, then record the final status (and the reason for anything but completed)."""
        if status not in STATUSES:
            raise ValueError(f"unknown status {status!r}")
        self.flush()
        self.set_attrs(status=status, reason=reason, finished=_now(), **attrs)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


@dataclass
class Run:
    """One results file, read back: attributes and the /train and /eval columns as numpy arrays."""

    path: Path
    attrs: dict
    train: dict
    eval: dict
    setting: str = ""  # the problem settings that tell this run's scene apart from others of its task
    label: str = ""  # in a report: its group (variant and the method settings that differ), see physgrad.report
    collection: str = ""  # in a report: the label of the set of runs it was found in (LABEL=PATH)

    @property
    def scene(self) -> str:
        """The task, with the distinguishing settings: runs are only compared within one scene."""
        return f"{self.attrs.get('task', '?')} {self.setting}".strip()

    @property
    def variant(self) -> str:
        return str(self.attrs.get("variant", self.attrs.get("optim", "?")))

    @property
    def seconds_per_iteration(self) -> float:
        wall = self.train.get("wall_time", np.empty(0))
        return float(np.median(np.diff(np.concatenate([[0.0], wall])))) if wall.size else math.nan

    def offset(self, x_key: str) -> float:
        """Where this run's x axis starts: a run started from another's network (init_from) continues that
        run's iterations and training seconds."""
        key = {"wall_time": "init_train_seconds", "iteration": "init_iterations"}[x_key]
        return float(self.attrs.get(key, 0.0))

    def final(self, group: str, column: str = "loss") -> float:
        values = getattr(self, group).get(column, np.empty(0))
        return float(values[-1]) if values.size else math.nan

    def time_to_reach(self, threshold: float) -> float:
        """Training seconds at the first held-out evaluation with loss <= threshold (NaN if never)."""
        loss, wall = self.eval.get("loss", np.empty(0)), self.eval.get("wall_time", np.empty(0))
        hits = np.flatnonzero(loss <= threshold)
        return float(wall[hits[0]]) if hits.size else math.nan


def read_run(path: str | os.PathLike) -> Run:
    """Read one results file; raises ValueError with a one-line reason if it is not a physgrad results file."""
    path = Path(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            if "status" not in f.attrs or "train" not in f or "eval" not in f:
                raise ValueError(f"{path}: not a physgrad results file (no status attribute or /train, /eval)")
            attrs = {key: _plain(value) for key, value in f.attrs.items()}
            train = {key: f["train"][key][()] for key in f["train"]}
            evaluation = {key: f["eval"][key][()] for key in f["eval"]}
    except OSError as error:
        raise ValueError(f"{path}: cannot be read as HDF5 ({str(error).splitlines()[0]})") from None
    return Run(path, attrs, train, evaluation)


def read_final(path: str | os.PathLike) -> tuple[dict, dict]:
    """The attributes and the last /eval row of a results file, without reading the curves (a resumed sweep
    checks every job this way); ValueError (one line) as read_run."""
    path = Path(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            if "status" not in f.attrs or "eval" not in f:
                raise ValueError(f"{path}: not a physgrad results file (no status attribute or /eval)")
            attrs = {key: _plain(value) for key, value in f.attrs.items()}
            last = {key: _plain(f["eval"][key][-1]) for key in f["eval"] if f["eval"][key].shape[0]}
    except OSError as error:
        raise ValueError(f"{path}: cannot be read as HDF5 ({str(error).splitlines()[0]})") from None
    return attrs, last


def read_params(path: str | os.PathLike) -> np.ndarray:
    """The flat final parameters a run saved; ValueError (one line) if the file has none or is not readable."""
    path = Path(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            if "params" not in f:
                status = _plain(f.attrs.get("status", "?"))
                raise ValueError(f"{path} holds no final network (status {status}): use a run that finished")
            return f["params"][()]
    except OSError as error:
        raise ValueError(f"{path}: cannot be read as HDF5 ({str(error).splitlines()[0]})") from None


def _plain(value):
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def natural_key(text: str) -> list:
    """Sort key that orders the numbers inside text by value: 'unroll=16' before 'unroll=128'."""
    return [(0, float(part), "") if re.fullmatch(r"\d+(\.\d+)?", part) else (1, 0.0, part)
            for part in re.split(r"(\d+(?:\.\d+)?)", text) if part]


def find_results(paths) -> list[Path]:
    """Every results.h5 at or under the given files and folders, in sorted order."""
    found = []
    for path in map(Path, paths):
        if path.is_file():
            found.append(path)
        elif path.is_dir():
            found.extend(sorted(path.rglob("results.h5")))
        else:
            raise FileNotFoundError(f"{path}: no such file or folder")
    return found
