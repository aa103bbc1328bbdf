"""Optuna's journal of a study's tuning (tuning.journal) through one door: a file physgrad opened
itself (physgrad.comparison.tuning.journal_storage builds the storage over it)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

from optuna.storages.journal import BaseJournalBackend
from optuna.storages.journal._storage import JournalOperation

from physgrad.files import load_json, open_foreign

# the operations Optuna's journal records; a record with another op_code made Optuna's replay fail
# with a 42-line AssertionError
OP_CODES = frozenset(int(op) for op in JournalOperation)
JOURNAL_LIMIT = 64 << 20  # bytes: a study's journal is kilobytes; a larger one is not physgrad's


class OwnJournal(BaseJournalBackend):
    """Optuna's journal format (one JSON record per line, appended) over one file descriptor held
    for the storage's life: opened without following a link, checked to be a regular file of one
    name, and never opened by its name again, so that a link or another file put at that name
    later (the folder may come from someone else) is neither read nor written through. Writers
    are kept apart by the study's own lock (.physgrad-study), not by lock files beside the
    journal. A last line without its newline (an append cut short) is not read; a journal over
    JOURNAL_LIMIT bytes or a line that is not a JSON object with a known op_code is a ValueError
    (one line)."""

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
                if not isinstance(record, dict) or record.get("op_code") not in OP_CODES:
                    raise ValueError(
                        f"{self._path}: line {number + 1} is not a record of Optuna's journal "
                        "(no known op_code): move the file away to tune again (its trials will "
                        "run again)"
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
