"""Unit layer of the training loop: the results writer's flushes, whole rows and fixed columns, a
stalled step abandoned in one line, a first signal asking to stop and a second ending the step,
and a time budget below one step refused."""

import numpy as np
import pytest

from physgrad.results import ResultsWriter, read_run


def test_writer_appends_in_flushes_and_checks_columns(tmp_path):
    writer = ResultsWriter(tmp_path / "results.h5", {"task": "poisson", "optim": "adam", "seed": 0})
    for i in range(5):
        writer.append(
            "train", {"iteration": i, "wall_time": 0.1 * i, "loss": 1.0 / (i + 1), "grad_norm": 1.0}
        )
        if i == 2:
            writer.flush()
            assert read_run(tmp_path / "results.h5").train["iteration"].tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="columns"):
        writer.append("train", {"iteration": 5, "loss": 0.0})
    writer.finish("interrupted", "SIGINT after 5 iterations")
    run = read_run(tmp_path / "results.h5")
    assert run.train["iteration"].tolist() == list(range(5))
    assert (run.attrs["status"], run.attrs["reason"]) == (
        "interrupted",
        "SIGINT after 5 iterations",
    )


def test_rows_are_whole_and_columns_fixed(tmp_path):
    writer = ResultsWriter(tmp_path / "results.h5", {"task": "poisson", "optim": "adam", "seed": 0})
    writer.set_columns("train", ("iteration", "loss"))
    writer.append_row("train", (0, 1.0))
    writer.append("train", {"loss": 0.5, "iteration": 1})  # by name, in any order
    with pytest.raises(ValueError, match="columns"):
        writer.set_columns("train", ("iteration", "grad_norm"))
    writer.finish("interrupted", "SIGINT after 2 iterations")
    run = read_run(tmp_path / "results.h5")
    assert run.train["iteration"].tolist() == [0, 1] and run.train["loss"].tolist() == [1.0, 0.5]


def test_a_step_that_stops_computing_without_returning_ends_in_one_line_one_that_computes_not():
    """XLA's CPU pool can wedge: every thread idle, the step never ready. A step whose process uses
    no CPU for the stall window is abandoned with StepStalled, whose message names the way round;
    a step that keeps the CPU busy for longer than the window returns its result."""
    import threading
    import time

    from physgrad.interrupts import ABANDONED, StepStalled, StopRequest

    request, release = StopRequest(), threading.Event()
    start = time.perf_counter()
    with pytest.raises(StepStalled) as stalled:
        request.call(lambda: release.wait(30), stall_seconds=0.5, stall_cpu_seconds=0.05)
    assert 0.5 <= time.perf_counter() - start < 5
    assert "\n" not in str(stalled.value)
    assert "XLA_FLAGS=--xla_cpu_enable_concurrency_optimized_scheduler=false" in str(stalled.value)
    release.set()
    ABANDONED[-1].join(5)

    def busy(seconds):  # computing, in Python: the process's CPU time grows
        end, total = time.perf_counter() + seconds, 0
        while time.perf_counter() < end:
            total += 1
        return total

    assert request.call(busy, 1.5, stall_seconds=0.5, stall_cpu_seconds=0.05) > 0


# make test-long: three more draws of the instants (1.7 s each, computing); make test keeps [0]
@pytest.mark.parametrize(
    "trial", [0, *(pytest.param(k, marks=pytest.mark.long) for k in range(1, 4))]
)
def test_a_process_stopped_and_resumed_is_not_a_stalled_step(monkeypatch, trial):
    """SIGSTOP (or Ctrl-Z, or a suspended machine) stops every thread: on resuming, the wall clock
    has jumped while the CPU clock has not. The jump is injected at random instants of a step that
    computes (a clock whose monotonic time leaps by 30 s, five times, the stall window 1 s): the
    step returns. The same leaps read as a stall when a pause is not recognised (the control), and
    a step that truly computes nothing still stalls between leaps."""
    import random
    import threading
    import time
    import types

    from physgrad import interrupts
    from physgrad.interrupts import ABANDONED, StepStalled, StopRequest

    leaps = []
    clock = types.SimpleNamespace(
        monotonic=lambda: time.monotonic() + 30.0 * len(leaps), process_time=time.process_time
    )
    monkeypatch.setattr(interrupts, "time", clock)
    rng = random.Random(trial)

    def busy_with_pauses(seconds, pauses):
        instants = sorted(rng.uniform(0.05, seconds) for _ in range(pauses))
        start, total = time.perf_counter(), 0
        while time.perf_counter() - start < seconds:
            total += 1
            if instants and time.perf_counter() - start > instants[0]:
                instants.pop(0)
                leaps.append(1)
        return len(leaps)

    request = StopRequest()
    window = {"stall_seconds": 1.0, "stall_cpu_seconds": 1e3}  # no CPU share ever counts
    assert request.call(busy_with_pauses, 0.6, 5, **window) == 5
    monkeypatch.setattr(interrupts, "PAUSED_SECONDS", float("inf"))
    with pytest.raises(StepStalled):  # control: unrecognised, the first leap reads as a stall
        request.call(busy_with_pauses, 0.6, 5, **window)
    monkeypatch.setattr(interrupts, "PAUSED_SECONDS", 2.0)
    release = threading.Event()
    threading.Timer(0.2, leaps.append, (1,)).start()
    start = time.perf_counter()
    with pytest.raises(StepStalled):  # a wedged step resumed still stalls, a window later
        request.call(lambda: release.wait(30), stall_seconds=0.5, stall_cpu_seconds=0.05)
    assert 0.7 <= time.perf_counter() - start < 5
    release.set()
    ABANDONED[-1].join(5)


def test_first_signal_asks_to_stop_second_ends_a_step_still_computing():
    import signal
    import threading
    import time

    from physgrad.interrupts import StopRequest

    request = StopRequest()
    assert request.call(lambda x: x + 1, np.float32(1)) == 2  # no signal: the step's result
    request(signal.SIGINT, None)
    assert request.signal_name == "SIGINT" and not request.at_once
    release = threading.Event()
    threading.Timer(0.2, request, (signal.SIGTERM, None)).start()  # the handler never raises
    start = time.perf_counter()
    with pytest.raises(KeyboardInterrupt, match="SIGINT"):
        request.call(lambda: release.wait(30))  # a step that would take 30 s
    assert time.perf_counter() - start < 5
    release.set()


@pytest.mark.parametrize("budget", [1e-300, 1e-9, 0.0, -1.0])
def test_a_time_budget_below_one_step_of_any_rule_is_refused_at_the_door(budget):
    """A budget shorter than the calibrated clock's floor (a microsecond) trains no step of any
    rule: a mistake in the config, refused in one line naming the key (1e-300 ran without a
    word)."""
    from physgrad.errors import UserError
    from physgrad.trainer_settings import MIN_STEP_COST, TrainerSettings

    trainer = {"iterations": None, "eval_every": 10, "batch_size": 8, "flush_seconds": 1.0}
    with pytest.raises(UserError, match=r"trainer.time_budget=.* use a number >= 1e-06"):
        TrainerSettings.from_config({**trainer, "time_budget": budget})
    assert TrainerSettings.from_config({**trainer, "time_budget": MIN_STEP_COST}).time_budget > 0
