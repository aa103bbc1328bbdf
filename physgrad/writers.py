"""The results files of the seeds trained together, as the training loop writes them: each seed's
file with how it ended so far (SeedRun), the files written alike (Writers), and a finish that
marks a file failed in place when it cannot be written."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from physgrad.errors import ResultsWriteError
from physgrad.results import ResultsWriter


@dataclass
class SeedRun:
    """What the loop tracks for one seed: its results file, how it ended so far, its last
    evaluation, and the factorisation failures counted before the current step (to name them in a
    divergence reason)."""

    writer: ResultsWriter
    status: str = "completed"
    reason: str | None = None
    iterations: int | None = None  # set when the seed stops before the others (diverged)
    latest_eval: dict = field(default_factory=dict)
    svd_failures: float = 0.0
    # the training loss of the first step: the scale of the blow-up bound
    first_loss: float | None = None

    @property
    def running(self) -> bool:
        return self.status == "completed"


def finish_or_mark(
    writer: ResultsWriter, status: str, reason: str | None, **attrs: Any
) -> str | None:
    """writer.finish(), and if the file cannot be written (disk full) status failed set on the file
    as it is; returns the write error as one line, or None."""
    try:
        writer.finish(status, reason, **attrs)
        return None
    except ResultsWriteError as error:
        writer.mark_failed_in_place(
            f"{error}; the run ended {status}" + (f" ({reason})" if reason else "")
        )
        return str(error)


class Writers:
    """The results files of the seeds trained together (one ResultsWriter per seed), written
    alike."""

    def __init__(self, writers: Iterable[ResultsWriter]) -> None:
        self.writers = list(writers)

    def __len__(self) -> int:
        return len(self.writers)

    def set_attrs(self, **attrs: Any) -> None:
        for writer in self.writers:
            writer.set_attrs(**attrs)

    def set_columns(self, group: str, names: Iterable[str]) -> None:
        for writer in self.writers:
            writer.set_columns(group, names)

    def shift_buffered_time(self, seconds: float) -> None:
        for writer in self.writers:
            writer.shift_buffered_time(seconds)

    def flush(self) -> None:
        for writer in self.writers:
            writer.flush()
