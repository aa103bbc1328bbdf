"""A results file read as foreign data: it may come from anyone. A reader opens regular files only,
follows no link, external storage or virtual dataset, checks every attribute's type and every
column's shape, dtype and size before using it, and cuts long text and replaces control characters
(terminal escapes); it never resolves or instantiates anything. A file failing a check is refused
with one line (ValueError) naming the check. physgrad.results reads through these checks."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from physgrad.files import CONFIG_LIMIT, clean_text, open_foreign, with_live_status

STATUSES = ("running", "completed", "diverged", "interrupted", "failed", "refused")
COLUMN_LIMIT = 1 << 26  # elements of one /train or /eval column (512 MiB of float64) ...
FILE_COLUMNS_LIMIT = 1 << 28  # ... and of all of a file's columns together
# ... and their bytes at most this many times the file's size (+1 MiB): physgrad writes its columns
# uncompressed, and a few MB of compressed zeros would otherwise unpack into gigabytes
EXPANSION_LIMIT = 8
REQUIRED_TEXT = ("status", "task", "optim")
# what each attribute physgrad computes with must be; any other attribute may be any scalar
KINDS = {
    **dict.fromkeys(
        "seed unroll iterations batch_size n_params wall_time_shared_by init_iterations cpu_count "
        "contended".split(),
        "an integer",
    ),
    **dict.fromkeys(
        "compile_seconds train_seconds first_step_overhead_seconds init_train_seconds step_cost "
        "update_cost evaluation_cost step_evaluations "
        "load_start load_end step_seconds_p10 step_seconds_p50 step_seconds_p90 "
        "step_seconds_p99".split(),
        "a number",
    ),
    **dict.fromkeys(
        "task optim variant status reason stopped_by config precision physgrad_version "
        "jax_version jaxlib_version git_commit cpu_model device thread_settings hostname created "
        "finished owner heartbeat jacobian clock contention init_from init_variant".split(),
        "text",
    ),
}
FITS = {  # whether a value is of a kind (None: an attribute physgrad does not read)
    "text": lambda value: isinstance(value, str),
    "an integer": lambda value: isinstance(value, int) and not isinstance(value, bool),
    "a number": lambda value: isinstance(value, (int, float)) and not isinstance(value, bool),
    None: lambda value: isinstance(value, (str, int, float, bool)),
}


@contextmanager
def open_results(path: Path, follow: bool = False) -> Iterator[h5py.File]:
    """The HDF5 file at path, opened from a descriptor of a regular file through
    physgrad.files.open_foreign (no link followed unless follow: a path the user gave; a FIFO,
    device or socket refused without blocking on it); ValueError (one line) if it cannot be
    opened."""
    try:
        fd = open_foreign(path, follow=follow)
    except OSError as error:
        raise ValueError(f"{path}: cannot be opened ({error.strerror or error})") from None
    with os.fdopen(fd, "rb") as stream:
        try:
            f = h5py.File(stream, "r")
        except (OSError, RuntimeError, ValueError) as error:
            raise ValueError(
                f"{path}: cannot be read as HDF5 ({clean_text(str(error).splitlines()[0], 200)})"
            ) from None
        with f:
            yield f


def checked_attrs(path: Path, f: h5py.File) -> dict:
    """The root attributes, each checked: text (cleaned, cut), integers and numbers where physgrad
    computes with them, other scalars kept, arrays of unknown attributes dropped. ValueError naming
    the first that fails."""
    attrs = {}
    for key in f.attrs:
        name = clean_text(key, 200)
        value = _attribute(path, f, key, name)
        expected = KINDS.get(key)
        # a text seed is allowed for a refused job only (the invalid value it was refused for)
        if not FITS[expected](value) and not (key == "seed" and isinstance(value, str)):
            if expected is None:
                continue  # an unknown attribute physgrad does not read: dropped
            raise ValueError(
                f"{path}: attribute {name!r} is {_describe(value)}, expected {expected}"
            )
        attrs[name] = value
    _check_required(path, attrs)
    return with_live_status(attrs)


def _attribute(path: Path, f: h5py.File, key: str, name: str) -> Any:
    """One root attribute read as a Python scalar (text decoded, cleaned and cut; the config kept
    whole up to CONFIG_LIMIT, its lines kept), or an array as stored."""
    try:
        value = f.attrs[key]
    except (OSError, RuntimeError, TypeError, ValueError) as error:
        raise ValueError(
            f"{path}: attribute {name!r} cannot be read ({clean_text(str(error), 200)})"
        ) from None
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode(errors="replace")
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, str):
        if key == "config":
            if len(value) > CONFIG_LIMIT:
                raise ValueError(
                    f"{path}: attribute 'config' is longer than {CONFIG_LIMIT} characters"
                )
            value = clean_text(value, None, lines=True)
        else:
            value = clean_text(value)
    return value


def _check_required(path: Path, attrs: dict) -> None:
    """The attributes every results file has: status (one of STATUSES), task, optim and seed (an
    integer unless the job was refused)."""
    missing = [key for key in (*REQUIRED_TEXT, "seed") if key not in attrs]
    if missing:
        raise ValueError(f"{path}: not a physgrad results file (no {', '.join(missing)} attribute)")
    if attrs["status"] not in STATUSES:
        raise ValueError(f"{path}: status {attrs['status']!r} is none of {', '.join(STATUSES)}")
    if isinstance(attrs["seed"], str) and attrs["status"] != "refused":
        raise ValueError(
            f"{path}: attribute 'seed' is {_describe(attrs['seed'])}, expected an integer"
        )


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    kind = "text" if isinstance(value, str) else type(value).__name__
    return f"{kind} {clean_text(repr(value), 40)}"


def _hard(path: Path, parent: h5py.Group, key: str, kind: type, where: str) -> Any:
    """parent[key] if it is a hard link to an object of kind (stored in this file: no soft or
    external link followed, where `in` or indexing would follow one); ValueError (one line) naming
    where otherwise."""
    link = parent.get(key, getlink=True)
    if link is None:
        raise ValueError(f"{path}: not a physgrad results file (no {where})")
    if not isinstance(link, h5py.HardLink) or not isinstance(parent[key], kind):
        raise ValueError(
            f"{path}: {where} is a {type(link).__name__}, not a {kind.__name__.lower()}: links "
            "are not followed"
        )
    return parent[key]


def checked_columns(path: Path, f: h5py.File, group: str) -> dict[str, h5py.Dataset]:
    """The datasets of /group after the checks (not read yet): each a _checked_column, of equal
    length, holding iteration and loss (and in /eval wall_time) when there are any."""
    g, columns = _hard(path, f, group, h5py.Group, f"/{group}"), {}
    for key in g:
        name = clean_text(key, 200)
        columns[name] = _checked_column(path, g, key, f"/{group}/{name}")
    lengths = {key: column.shape[0] for key, column in columns.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(
            f"{path}: /{group} columns have unequal lengths {lengths}: the file is damaged"
        )
    needed = {"iteration", "loss"} | ({"wall_time"} if group == "eval" else set())  # readers index
    if columns and needed - set(columns):
        raise ValueError(f"{path}: /{group} lacks {', '.join(sorted(needed - set(columns)))}")
    return columns


def _checked_column(
    path: Path, g: h5py.Group, key: str, where: str, kinds: str = "fiub"
) -> h5py.Dataset:
    """g[key]: a hard link to a 1-D dataset of a numeric dtype kind in kinds, stored in this file
    (no external or virtual storage), of at most COLUMN_LIMIT values."""
    column = _hard(path, g, key, h5py.Dataset, where)
    if column.external or column.is_virtual:
        raise ValueError(
            f"{path}: {where} keeps its data in other files (external or virtual storage): refused"
        )
    if column.ndim != 1 or column.dtype.kind not in kinds:
        raise ValueError(
            f"{path}: {where} is {column.ndim}-D of {column.dtype}, expected a 1-D column of "
            f"dtype kind {kinds}"
        )
    if column.size > COLUMN_LIMIT:
        raise ValueError(f"{path}: {where} has {column.size} values, more than {COLUMN_LIMIT}")
    return column


def checked_tables(path: Path, f: h5py.File, groups: tuple[str, ...]) -> dict[str, dict]:
    """checked_columns of every group, with at most FILE_COLUMNS_LIMIT values in all."""
    columns = {group: checked_columns(path, f, group) for group in groups}
    every = [c for group in columns.values() for c in group.values()]
    if sum(c.size for c in every) > FILE_COLUMNS_LIMIT:
        raise ValueError(
            f"{path}: more than {FILE_COLUMNS_LIMIT} values in /train and /eval together"
        )
    # the bytes of the open file (not of whatever its name points to by now)
    unpacked, stored = sum(c.size * c.dtype.itemsize for c in every), f.id.get_filesize()
    if unpacked > EXPANSION_LIMIT * stored + (1 << 20):
        raise ValueError(
            f"{path}: its columns unpack to {unpacked >> 20} MiB from a file of "
            f"{max(stored >> 20, 1)} MiB or less (more than {EXPANSION_LIMIT} times): refused, as "
            "physgrad writes them uncompressed"
        )
    return columns


def checked_params(path: Path, f: h5py.File, status: str) -> h5py.Dataset:
    """/params after the checks (not read yet): a _checked_column of floats; ValueError (one line)
    if the file has none."""
    if f.get("params", getlink=True) is None:
        raise ValueError(
            f"{path} holds no final network (status {status}): use a run that finished"
        )
    return _checked_column(path, f, "params", "/params", kinds="f")


def read_columns(path: Path, read: Callable[[], Any]) -> Any:
    """read() of checked columns, ValueError (one line) if HDF5 cannot read one."""
    try:
        return read()
    except (OSError, RuntimeError, ValueError) as error:
        raise ValueError(
            f"{path}: a column cannot be read ({clean_text(str(error).splitlines()[0], 200)})"
        ) from None
