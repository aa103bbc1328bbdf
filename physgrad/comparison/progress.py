"""A phase's progress on the console while its multirun runs, read from the log Hydra and the
runner write: a bar on a terminal, a line now and then in a log, the time left by each job's own
variant's pace."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field

# Hydra's line for each job it launches: "[HYDRA] \t#3 : +compare_job=..."; a job's training
# progress as the runner logs it without a terminal (physgrad.progress): "toy/hig seed 1000000
# (+1) iteration 6214, loss 0.007778, 28.5 s of training"
_EVENT = re.compile(
    r"\[HYDRA\]\s+#(?P<job>\d+) : "
    r"|\[HYDRA\] job \S+: (?P<stopped>never started|interrupted)"
    r"|\] - (?P<label>\S+ seed \d+(?: \(\+\d+\))?) "
    r"iteration (?P<iteration>\d+), loss (?P<loss>\S+),"
)


@dataclass
class Progress:
    """A phase's progress on the console, read from its log as the multirun writes it. On a terminal
    (stream, default stderr), a bar over the phase's jobs with the running job's loss so far and
    the time left, redrawn at every look; without one (a log, nohup, a batch job), a line when
    more of its jobs have started, at most one every `every` seconds, with the same news, so that
    logs stay readable. Either way one line at the end with the jobs it ran (Hydra launches the
    jobs of a local sweep one after another, so job k started means k - 1 done). names: the jobs
    in launch order, where known, so that the time left counts each job at its own variant's pace
    (a Gauss-Newton job may take ten of Adam's)."""

    phase: str
    total: int
    say: Callable[[str], object]
    names: tuple[str, ...] = ()
    every: float = 30.0
    started: int = 0
    said: int = 0
    begun: float = field(default_factory=time.monotonic)
    last: float = field(default_factory=time.monotonic)
    launched_at: float = 0.0  # when the latest job was seen to start
    training: str = ""  # the running job's last progress: its label, loss and iteration
    training_said: str = ""
    stream: object = None  # where the bar is drawn (None: stderr); no bar unless it is a terminal
    bar: object = field(default=None, init=False)  # the terminal's bar (tqdm), if there is one
    took: dict = field(default_factory=dict, init=False)  # a job's kind -> seconds of each done
    # jobs a stopped sweep names as interrupted or never started (its launcher still logs a
    # launch line for each, so the launches alone would count them as run)
    stopped: dict = field(default_factory=dict, init=False)

    def __post_init__(self) -> None:
        import sys

        from tqdm import tqdm

        bar = tqdm(
            total=self.total,
            desc=self.phase,
            unit="job",
            file=self.stream if self.stream is not None else sys.stderr,
            disable=None,  # a bar only on a terminal
            leave=False,
            dynamic_ncols=True,
            bar_format="{desc}: {n}/{total} jobs done |{bar}| {elapsed}{postfix}",
        )
        self.bar = None if bar.disable else bar

    def read(self, text: str, final: bool = False) -> None:
        """Take the log's new text; say where the phase is if it moved on."""
        now = time.monotonic()
        for event in _EVENT.finditer(text):
            if event["job"] is not None and int(event["job"]) + 1 > self.started:
                if self.started:
                    kind = self._kind(self.started - 1)
                    self.took.setdefault(kind, []).append(now - self.launched_at)
                self.started, self.launched_at, self.training = int(event["job"]) + 1, now, ""
            elif event["stopped"] is not None:
                self.stopped[event["stopped"]] = self.stopped.get(event["stopped"], 0) + 1
            elif event["label"] is not None:
                self.training = (
                    f"{event['label']}: loss {event['loss']} at iteration {event['iteration']}"
                )
        moved = self.started > self.said
        minutes = (now - self.begun) / 60
        if self.bar is not None:
            ran = min(self.started - (0 if final else 1), self.total) - sum(self.stopped.values())
            self.bar.n = max(0, ran)
            news = [
                f"job {self.started}: {self.training}" if self.training else "",
                "" if final else self._left(now),
            ]
            self.bar.set_postfix_str("; ".join(n.removeprefix("; ") for n in news if n), False)
            self.bar.refresh()
            if final:
                self.bar.close()
        if final and self.started:
            ran = min(self.started, self.total) - sum(self.stopped.values())
            self.say(
                f"{self.phase}: {ran} of {self.total} jobs run in {minutes:.1f} min"
                + (
                    ", then stopped ("
                    + ", ".join(f"{n} {why}" for why, n in sorted(self.stopped.items()))
                    + ")"
                    if self.stopped
                    else ""
                )
            )
        elif (
            self.bar is None
            and (moved or self.training != self.training_said)
            and now - self.last >= self.every
        ):
            self.say(
                f"{self.phase}: job {min(self.started, self.total)} of {self.total} started, "
                f"{minutes:.1f} min in"
                + (f"; {self.training}" if self.training else "")
                + self._left(now)
            )
            self.said, self.last, self.training_said = self.started, now, self.training

    def _kind(self, index: int) -> int | None:
        """Job index's variant (None where its name does not say, or is not known)."""
        from physgrad.comparison.job_names import variant_index

        try:
            return variant_index(self.names[index])
        except (IndexError, AttributeError):  # no name, or one without a variant (calibration)
            return None

    def _left(self, now: float) -> str:
        """The time left at the pace of the jobs done (none before one is done, or once all are):
        each job not done at the mean time of the done jobs of its variant, less what the running
        one has had; once the running one has had more than that, the time left after it, how
        long it has run and, where its variant has a done job, how long those took. Jobs of a
        variant none of whose jobs is done have no pace to count them at: the time is then "at
        least" and says how many such jobs are left (another variant's pace can be ten times
        off: a Gauss-Newton job beside Adam's)."""
        done = self.started - 1
        if done < 1 or done >= self.total:
            return ""

        def pace(index: int) -> float | None:
            times = self.took.get(self._kind(index))
            return sum(times) / len(times) if times else None

        later = [pace(index) for index in range(self.started, self.total)]
        after = sum(p for p in later if p is not None)
        untimed = sum(p is None for p in later)
        running, expected = now - self.launched_at, pace(done)
        bound = "at least" if untimed or expected is None else "about"
        besides = (
            ""
            if not untimed
            else ", and 1 job of a variant not timed yet"
            if untimed == 1
            else f", and {untimed} jobs of variants not timed yet"
        )
        if expected is not None and running <= expected:
            return f"; {bound} {_span(expected - running + after)} left{besides}"
        ran, why = f"{_span(running)} so far", "the first of its variant"
        if expected is not None:
            why = f"about {_span(expected)} expected"
        if untimed and not after:  # "at least 0 s left" would say nothing
            return f"; the running job {ran} ({why}){besides}"
        return f"; {bound} {_span(after)} left after the running job ({ran}, {why}){besides}"


def _span(seconds: float) -> str:
    """A duration as the console says it: seconds up to a minute and a half, then minutes."""
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"
