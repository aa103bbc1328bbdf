"""What the user sees while a run trains: a progress bar on a terminal, log lines without one."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Protocol

from tqdm import tqdm

log = logging.getLogger("physgrad")


class Budget(Protocol):
    """What the progress shown reads of a run's settings (trainer_settings.TrainerSettings)."""

    @property
    def iterations(self) -> int | None: ...

    @property
    def time_budget(self) -> float | None: ...

    @property
    def log_seconds(self) -> float: ...


class Progress:
    """What the user sees while a run trains. On a terminal, a bar over the iterations, or over the
    training seconds when a time budget is set (its ETA is then the budget's), that says when it is
    compiling; without one (a batch job, nohup), a log line every trainer.log_seconds of wall-clock
    with iteration, loss and elapsed training time. settings: the run's TrainerSettings
    (physgrad.runner); clock: the clock the loop reads (the runner's, which tests replace)."""

    def __init__(
        self, settings: Budget, label: str, clock: Callable[[], float] = time.perf_counter
    ) -> None:
        self.settings, self.label, self.clock = settings, label, clock
        self.by_time = settings.time_budget is not None
        total = settings.time_budget if self.by_time else settings.iterations
        self.bar = tqdm(
            total=total,
            desc=f"{label} compiling",
            mininterval=0.5,
            disable=None,
            leave=False,
            unit="s" if self.by_time else "it",
            bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
            if self.by_time
            else None,
        )
        self.logging = self.bar.disable
        self.last_log = self.clock()

    def compiled(self, seconds: float) -> None:
        self.bar.set_description(self.label)
        if self.logging:
            log.info("%s compiled in %.1f s", self.label, seconds)

    def update(self, iteration: int, train_seconds: float, loss: float) -> None:
        """Called at every flush (at most every trainer.flush_seconds), not at every step."""
        if not self.bar.disable:
            self.bar.set_postfix_str(f"it {iteration}, loss {loss:.3e}", refresh=False)
            self.bar.update(
                (min(train_seconds, self.bar.total) if self.by_time else iteration) - self.bar.n
            )
        elif self.clock() - self.last_log >= self.settings.log_seconds:
            self.last_log = self.clock()
            log.info(
                "%s iteration %d, loss %.4g, %.1f s of training",
                self.label,
                iteration,
                loss,
                train_seconds,
            )

    def close(self) -> None:
        self.bar.close()
