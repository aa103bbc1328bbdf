"""Results files: one HDF5 file per run, written incrementally, and reading many of them into one table.

Layout (see docs/results.md):
  root attributes: task, optim, unroll (temporal scenes only), seed, status, reason, config, physgrad_version,
                   jax_version, compile_seconds, created, and a few descriptive extras;
  /train/{iteration, wall_time, loss, grad_norm, ...}: one row per iteration;
  /eval/{iteration, wall_time, loss, <scene metrics>}: held-out evaluations;
  /params: the final network as one flat vector (every run that did not diverge or fail).
At every flush the whole file is written beside results.h5 and renamed onto it, so a run killed at any moment
leaves a complete file holding every row flushed so far, and readers never share a file with the writer.
"""

from __future__ import annotations

import fcntl
import math
import os
import re
import socket
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

STATUSES = ("running", "completed", "diverged", "interrupted", "failed", "refused")
GROUPS = ("train", "eval")


ASIDE_SUFFIX = ".overwriting.h5"  # a re-run's file while a completed results.h5 it would replace stays valid


class ResultsWriteError(OSError):
    """results.h5 could not be written (disk full, quota, permissions): one line that names the file."""


class FolderOwned(RuntimeError):
    """Another live process owns the job (or sweep) folder."""


def owner_tag() -> str:
    return f"pid {os.getpid()} on {socket.gethostname()}"


@contextmanager
def own_folder(folder: str | os.PathLike, what: str = "job"):
    """Hold the folder for this process while the block runs: an exclusive flock on folder/.physgrad-<what>,
    which the operating system releases when the process ends however it ends, so a dead owner never blocks a
    new one. FolderOwned (one line naming the owner's pid, host and start time) if a live process holds it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock_path = folder / f".physgrad-{what}"
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        owner = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise FolderOwned(f"{folder} is being written by {owner} (another {what}): wait for it to end, stop it, "
                          "or write somewhere else") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{owner_tag()} since {_now()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with a new owner)


def holds_completed(path: Path) -> bool:
    try:
        return read_final(path)[0].get("status") == "completed"
    except (ValueError, OSError):
        return False


class ResultsWriter:
    """Keeps every row of a run in memory (one tuple per row, so an interrupt can never leave a row half
    appended) and writes the whole file at each flush() into a temporary file beside it, which then replaces
    results.h5 by an atomic rename. So the file on disk is always a complete, consistent earlier state: a kill
    at any instant loses at most the rows since the last flush, a write cut short by a signal or a full disk
    leaves the previous version, and a reader (any reader, with or without HDF5 file locking) keeps the version
    it opened and never blocks the writer. A completed results.h5 is not replaced before its successor has
    completed: until then the run writes results.overwriting.h5 beside it."""

    def __init__(self, path: str | os.PathLike, attrs: dict):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.live = self.path.with_name(self.path.stem + ASIDE_SUFFIX) if holds_completed(self.path) else self.path
        self.attrs = {key: value for key, value in {**attrs, "status": "running", "created": _now(),
                                                      "owner": owner_tag()}.items() if value is not None}
        self._columns: dict[str, tuple[str, ...] | None] = {group: None for group in GROUPS}
        self._rows: dict[str, list[tuple]] = {group: [] for group in GROUPS}  # not yet flushed
        self._data: dict[str, dict[str, list[np.ndarray]]] = {group: {} for group in GROUPS}  # flushed chunks
        self._params: np.ndarray | None = None
        for stale in self.live.parent.glob(f".{self.live.name}.*.tmp"):  # left by a writer killed mid-write
            stale.unlink(missing_ok=True)
        self._write()

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

    def flush(self, sync: bool = False) -> None:
        """Write the file with every row so far and the attributes set since (sync: to the disk itself, not
        only to the operating system, which a killed process cannot lose anyway)."""
        for group, rows in self._rows.items():
            if rows:
                columns = self._data[group]
                for key, column in zip(self._columns[group], zip(*rows)):
                    columns.setdefault(key, []).append(np.asarray(column))
                rows.clear()
        self._write(sync)

    def set_attrs(self, **attrs) -> None:
        """Set (None: remove) root attributes; they reach the file with the next flush()."""
        for key, value in attrs.items():
            if value is None:
                self.attrs.pop(key, None)
            else:
                self.attrs[key] = value

    def save_params(self, flat: np.ndarray) -> None:
        """The network's final parameters as one flat vector (ravel_pytree order) in /params, with the next
        flush()."""
        self._params = np.asarray(flat)

    def finish(self, status: str, reason: str | None = None, **attrs) -> None:
        """Record the final status (and the reason for anything but completed) and write the file, synced to
        disk. A completed run written aside replaces the completed results.h5 only now."""
        if status not in STATUSES:
            raise ValueError(f"unknown status {status!r}")
        self.set_attrs(status=status, reason=reason, finished=_now(), **attrs)
        self.flush(sync=True)
        if self.live != self.path and status == "completed":
            os.replace(self.live, self.path)
            self.live = self.path

    def mark_failed_in_place(self, reason: str) -> bool:
        """Last resort when a full write fails (disk full): set status failed and the reason on the file as it
        is, a few bytes of attributes. True if that worked."""
        try:
            with h5py.File(self.live, "a", locking=False) as f:
                f.attrs["status"], f.attrs["reason"], f.attrs["finished"] = "failed", reason, _now()
            return True
        except (OSError, ValueError):
            return False

    def _write(self, sync: bool = False) -> None:
        """The file is built in memory (HDF5's core driver) and its bytes written by Python: a failing write()
        (disk full, quota, size limit) is then an OSError here, where HDF5 writing to disk itself crashed the
        process when a write failed as it closed the file."""
        self.attrs["heartbeat"] = _now()
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
            raise ResultsWriteError(f"cannot write {self.live}: {error.strerror or error}") from error


def replace_file(path: Path, content: bytes, sync: bool = False) -> None:
    """Write content beside path (.NAME.<pid>.tmp) and rename it onto path: a reader, or a process killed at
    any instant, sees the old file or the new one, never a part (sync: onto the disk itself before the rename,
    which a power cut could otherwise undo). The temporary file is removed on any error."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as out:
            out.write(content)
            if sync:
                out.flush()
                os.fsync(out.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


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
        key = {"wall_time": "init_train_seconds", "iteration": "init_iterations"}.get(x_key)
        return float(self.attrs.get(key, 0.0)) if key else 0.0

    def final(self, group: str, column: str = "loss") -> float:
        values = getattr(self, group).get(column, np.empty(0))
        return float(values[-1]) if values.size else math.nan

    def time_to_reach(self, threshold: float) -> float:
        """Training seconds at the first held-out evaluation with loss <= threshold (NaN if never)."""
        loss, wall = self.eval.get("loss", np.empty(0)), self.eval.get("wall_time", np.empty(0))
        hits = np.flatnonzero(loss <= threshold)
        return float(wall[hits[0]]) if hits.size else math.nan


def owner_alive(owner: str) -> bool | None:
    """Whether the process named by an `owner` attribute (pid N on HOST) still runs: None when that cannot be
    told from here (another host, or a file without an owner)."""
    match = re.fullmatch(r"pid (\d+) on (.+)", owner or "")
    if match is None or match[2] != socket.gethostname():
        return None
    try:
        os.kill(int(match[1]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def with_live_status(attrs: dict) -> dict:
    """A file that says `running` whose writer is gone reads as `crashed` (killed, or its machine lost), with a
    reason; the file itself is left as it is."""
    if attrs.get("status") == "running" and owner_alive(attrs.get("owner", "")) is False:
        attrs["status"] = "crashed"
        attrs["reason"] = (f"its writer ({attrs['owner']}) ended without finishing; rows up to its last write "
                           f"({attrs.get('heartbeat', '?')}) are kept")
    return attrs


def _check_columns(path: Path, group: str, columns: dict) -> None:
    lengths = {key: len(values) for key, values in columns.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"{path}: /{group} columns have unequal lengths {lengths}: the file is damaged")


def read_run(path: str | os.PathLike) -> Run:
    """Read one results file; raises ValueError with a one-line reason if it is not a physgrad results file,
    cannot be read or is inconsistent."""
    path = Path(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            if "status" not in f.attrs or "train" not in f or "eval" not in f:
                raise ValueError(f"{path}: not a physgrad results file (no status attribute or /train, /eval)")
            attrs = with_live_status({key: _plain(value) for key, value in f.attrs.items()})
            train = {key: f["train"][key][()] for key in f["train"]}
            evaluation = {key: f["eval"][key][()] for key in f["eval"]}
    except (OSError, KeyError, RuntimeError) as error:
        raise ValueError(f"{path}: cannot be read as HDF5 ({str(error).splitlines()[0]})") from None
    _check_columns(path, "train", train)
    _check_columns(path, "eval", evaluation)
    return Run(path, attrs, train, evaluation)


def read_final(path: str | os.PathLike) -> tuple[dict, dict]:
    """The attributes and the last /eval row of a results file, without reading the curves (a resumed sweep
    checks every job this way); ValueError (one line) as read_run."""
    path = Path(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            if "status" not in f.attrs or "eval" not in f:
                raise ValueError(f"{path}: not a physgrad results file (no status attribute or /eval)")
            attrs = with_live_status({key: _plain(value) for key, value in f.attrs.items()})
            lengths = {f["eval"][key].shape[0] for key in f["eval"]}
            if len(lengths) > 1:
                raise ValueError(f"{path}: /eval columns have unequal lengths: the file is damaged")
            last = {key: _plain(f["eval"][key][-1]) for key in f["eval"] if f["eval"][key].shape[0]}
    except (OSError, KeyError, RuntimeError) as error:
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
    except (OSError, KeyError, RuntimeError) as error:
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
