"""Optuna's journal of a study's tuning (tuning.journal) through one door: a file physgrad opened
itself (physgrad.comparison.tuning.journal_storage builds the storage over it)."""

from __future__ import annotations

import errno
import json
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from optuna.storages.journal import BaseJournalBackend

from physgrad.files import file_kind


class OwnJournal(BaseJournalBackend):
    """Optuna's journal format (one JSON record per line, appended) over one file descriptor held
    for the storage's life: opened without following a link, checked to be a regular file of one
    name, and never opened by its name again, so that a link or another file put at that name
    later (the folder may come from someone else) is neither read nor written through. Writers
    are kept apart by the study's own lock (.physgrad-study), not by lock files beside the
    journal. A last line without its newline (an append cut short) is not read."""

    def __init__(self, path: Path) -> None:
        flags = os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK
        try:
            fd = os.open(path, flags, 0o644)
        except OSError as error:
            if error.errno == errno.ELOOP:
                raise ValueError(
                    f"{path}: a link: refused (a folder may come from someone else)"
                ) from None
            if error.errno == errno.EISDIR:
                raise ValueError(f"{path}: a folder, not a file: refused") from None
            raise
        found = os.fstat(fd)
        if not stat.S_ISREG(found.st_mode) or found.st_nlink > 1:
            os.close(fd)
            why = (
                f"{file_kind(found.st_mode)}, not a file: refused"
                if not stat.S_ISREG(found.st_mode)
                else "has another name (a hard link), which writing would change too"
            )
            raise ValueError(f"{path}: {why}")
        os.set_blocking(fd, True)
        self._fd = fd
        self._offsets = {0: 0}  # record number -> byte offset of its line

    def read_logs(self, log_number_from: int) -> Iterator[dict]:
        start = max(n for n in self._offsets if n <= log_number_from)
        offset = self._offsets[start]
        data = b""
        while chunk := os.pread(self._fd, 1 << 20, offset + len(data)):
            data += chunk
        position = offset
        for number, line in enumerate(data.splitlines(keepends=True), start=start):
            if not line.endswith(b"\n"):
                break  # cut short: not a record (yet)
            position += len(line)
            self._offsets.setdefault(number + 1, position)
            if number >= log_number_from:
                yield json.loads(line)

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
