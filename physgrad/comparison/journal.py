"""Optuna's journal of a study's tuning (tuning.journal) through one door: a file physgrad opened
itself (OwnJournal; journal_storage builds Optuna's storage over it), its records checked before
Optuna replays them, a last line cut short set aside, a journal scored by another read-out set
aside, and an error of Optuna's replay turned into one line."""

from __future__ import annotations

import json
import os
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from optuna.storages.journal import BaseJournalBackend
from optuna.storages.journal._storage import JournalOperation

from physgrad.errors import UserError
from physgrad.files import clean_text, load_json, open_foreign
from physgrad.readout import READOUT_VERSION

if TYPE_CHECKING:
    from optuna.storages import JournalStorage

# the operations Optuna's journal records; a record with another op_code made Optuna's replay fail
# with a 42-line AssertionError
OP_CODES = frozenset(int(op) for op in JournalOperation)
# the fields Optuna's replay reads from a record of each operation (besides op_code and worker_id);
# one missing made it fail with a 42-line KeyError
_FIELDS = {
    "CREATE_STUDY": ("study_name", "directions"),
    "DELETE_STUDY": ("study_id",),
    "SET_STUDY_USER_ATTR": ("study_id", "user_attr"),
    "SET_STUDY_SYSTEM_ATTR": ("study_id", "system_attr"),
    "CREATE_TRIAL": ("study_id", "datetime_start"),
    "SET_TRIAL_PARAM": ("trial_id", "param_name", "param_value_internal", "distribution"),
    "SET_TRIAL_STATE_VALUES": ("trial_id", "state"),
    "SET_TRIAL_INTERMEDIATE_VALUE": ("trial_id", "step", "intermediate_value"),
    "SET_TRIAL_USER_ATTR": ("trial_id", "user_attr"),
    "SET_TRIAL_SYSTEM_ATTR": ("trial_id", "system_attr"),
}
FIELDS = {int(op): ("worker_id", *_FIELDS.get(op.name, ())) for op in JournalOperation}


def record_problem(record: object) -> str | None:
    """Why a journal line's JSON is not a record Optuna can replay (no known op_code, or a field
    its operation needs missing), or None."""
    if not isinstance(record, dict) or record.get("op_code") not in OP_CODES:
        return "no known op_code"
    missing = [key for key in FIELDS[record["op_code"]] if key not in record]
    return f"op_code {record['op_code']} without {', '.join(missing)}" if missing else None


JOURNAL_LIMIT = 64 << 20  # bytes: a study's journal is kilobytes; a larger one is not physgrad's


class OwnJournal(BaseJournalBackend):
    """Optuna's journal format (one JSON record per line, appended) over one file descriptor held
    for the storage's life: opened without following a link, checked to be a regular file of one
    name, and never opened by its name again, so that a link or another file put at that name
    later (the folder may come from someone else) is neither read nor written through. Writers
    are kept apart by the study's own lock (.physgrad-study), not by lock files beside the
    journal. A last line without its newline (an append cut short) is not read; a journal over
    JOURNAL_LIMIT bytes or a line that is not a record Optuna can replay (record_problem) is a
    ValueError (one line)."""

    def __init__(self, path: Path) -> None:
        self._fd = open_foreign(path, write=True)
        self._path = path
        self._offsets = {0: 0}  # record number -> byte offset of its line

    def read_logs(self, log_number_from: int) -> Iterator[dict]:
        start = max(n for n in self._offsets if n <= log_number_from)
        offset = self._offsets[start]
        data = b""
        while chunk := os.pread(self._fd, 1 << 20, offset + len(data)):
            data += chunk
            if offset + len(data) > JOURNAL_LIMIT:
                raise ValueError(f"{self._path}: longer than {JOURNAL_LIMIT} bytes: not a journal")
        position = offset
        for number, line in enumerate(data.splitlines(keepends=True), start=start):
            if not line.endswith(b"\n"):
                break  # cut short: not a record (yet)
            position += len(line)
            self._offsets.setdefault(number + 1, position)
            if number >= log_number_from:
                try:
                    record = load_json(line)
                except ValueError:
                    record = None
                problem = record_problem(record)
                if problem is not None:
                    raise ValueError(
                        f"{self._path}: line {number + 1} is not a record of Optuna's journal "
                        f"({problem}): move the file away to tune again (its trials will run "
                        "again)"
                    )
                yield record

    def append_logs(self, logs: list[dict]) -> None:
        text = "".join(json.dumps(log, separators=(",", ":")) + "\n" for log in logs)
        data = text.encode()
        while data:
            data = data[os.write(self._fd, data) :]
        os.fsync(self._fd)

    # os.close bound here: at the interpreter's exit a module's globals may be gone (None) before
    # the storage is collected
    def __del__(self, _close: object = os.close) -> None:
        fd = getattr(self, "_fd", None)
        if fd is not None:
            _close(fd)
            self._fd = None


@contextmanager
def journal_replay(path: Path) -> Iterator[None]:
    """An error raised inside Optuna's replay of the journal (a record whose fields are there but
    of the wrong kind: a date that is no date, a state that is no state) as a UserError (one line)
    naming the journal; errors raised elsewhere pass unchanged."""
    try:
        yield
    except (KeyError, TypeError, ValueError, AssertionError, IndexError, AttributeError) as error:
        journal = os.sep + os.path.join("optuna", "storages", "journal") + os.sep
        frames = traceback.extract_tb(error.__traceback__)
        if not any(journal in frame.filename for frame in frames):
            raise
        if str(error).startswith(str(path)):  # OwnJournal's own refusal of a line: one already
            raise UserError(str(error)) from None
        why = clean_text(f"{type(error).__name__}: {error}".splitlines()[0], 200)
        raise UserError(
            f"{path}: a record Optuna cannot replay ({why}): move the file away to tune again "
            "(its trials will run again)"
        ) from None


def journal_storage(path: Path) -> JournalStorage:
    """Optuna's storage over the journal file at path (one JSON record per line, appended), through
    a file physgrad opened itself (OwnJournal); a journal that is a link, not a file, or a file
    with another name (a hard link) is a UserError (one line)."""
    import optuna

    try:
        backend = OwnJournal(path)
    except ValueError as error:
        raise UserError(f"{error}; remove it or give another compare.dir") from None
    with journal_replay(path):  # the storage replays the journal as it is built
        return optuna.storages.JournalStorage(backend)


def set_aside_damage(path: Path, say: Callable[[str], object]) -> None:
    """Optuna's journal is one JSON object per line, appended. A kill or a full disk during an
    append leaves the last line cut short: it is moved to <journal>.damaged-<time> with a one-line
    note, and the trials it would have told run again. Any other line that is not a JSON object is a
    UserError (one line): the journal is not Optuna's, or was changed by hand."""
    from physgrad.files import load_json, read_own_file, replace_file, timestamp

    if not os.path.lexists(path):
        return
    try:  # a journal is data from the study folder: no link followed, no FIFO waited on
        data = read_own_file(path, JOURNAL_LIMIT)
    except (OSError, ValueError) as error:
        raise UserError(f"{error}; remove it or give another compare.dir") from None
    lines = data.split(b"\n")
    kept = 0  # bytes of whole records
    for number, line in enumerate(lines):
        if not line.strip():
            kept += len(line) + 1
            continue
        try:
            problem = record_problem(load_json(line))
        except ValueError:  # no JSON (nested too deep included): cut short if it is the last
            problem = None
            last = not any(rest.strip() for rest in lines[number + 1 :])
        else:
            last = False  # a whole JSON object: written whole, so not cut short
            if problem is None:
                kept += len(line) + 1
                continue
        if not last:
            why = f" ({problem})" if problem else ""
            raise UserError(
                f"{path}: line {number + 1} is not a record of Optuna's journal{why}: move the "
                "file away to tune again (its trials will run again)"
            )
        damaged = path.with_name(f"{path.name}.damaged-{timestamp()}")
        replace_file(damaged, data[kept:])
        replace_file(path, data[:kept])
        say(
            f"note: the last line of {path} was cut short (a stop or a full disk while it was "
            f"written): moved to {damaged.name}; the trials it would have told run again"
        )
        return


def set_aside_stale(path: Path, say: Callable[[str], object]) -> bool:
    """A journal with a trial told under another read-out (its Optuna study's "readout" differs
    from physgrad.readout.READOUT_VERSION, or is not recorded: written before it was) is moved to
    <journal>.read-out-<version>-<time> with a one-line note. Its trials are then asked again at the
    same points and read from their runs by this read-out; a job that finished is not trained
    again. Returns whether it was set aside."""
    import optuna
    from optuna.trial import TrialState

    from physgrad.files import safe_name, timestamp

    if not path.is_file():
        return False
    storage = journal_storage(path)
    versions = set()
    for name in optuna.get_all_study_names(storage):
        search = optuna.load_study(study_name=name, storage=storage)
        version = search.user_attrs.get("readout")
        if version != READOUT_VERSION and search.get_trials(
            deepcopy=False, states=(TrialState.COMPLETE,)
        ):
            # the attribute is data from the folder: in a file name and on the console only as
            # safe characters (a terminal escape there was printed raw and named a file)
            versions.add("unrecorded" if version is None else safe_name(str(version)))
    if not versions:
        return False
    older = "-".join(sorted(versions))
    aside = path.with_name(f"{path.name}.read-out-{older}-{timestamp()}")
    path.rename(aside)
    say(
        f"note: {path} holds trials scored by another read-out (version {older}; this physgrad "
        f"reads with version {READOUT_VERSION}): moved to {aside.name}; its trials are read again "
        "from their runs, and a job that finished is not trained again"
    )
    return True
