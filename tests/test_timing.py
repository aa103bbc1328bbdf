"""The calibrated clock, the contention flag and the machine a result was measured on: slow steps are injected
by replacing the runner's clock, at random instants, and the calibrated time must not move."""

import numpy as np
import pytest

import physgrad.runner
from physgrad import UserError
from physgrad.experiment import run_experiment
from physgrad.machine import contention, machine_label, step_statistics
from physgrad.results import read_run
from tests.test_configs import load
from tests.test_runner import SimulatedClock

COST = 0.01


class LoadedClock(SimulatedClock):
    """SimulatedClock whose steps are slowed `factor` times at the given step numbers (another process taking
    the cores for a while)."""

    def __init__(self, monkeypatch, slow_steps, factor=20.0):
        super().__init__(monkeypatch, step=COST)
        self.slow, self.factor = set(slow_steps), factor
        real = physgrad.runner.compile_training  # the simulated one
        monkeypatch.setattr(physgrad.runner, "compile_training", self.slowed(real))

    def slowed(self, compile_training):
        import dataclasses

        def compile_with_slow_steps(*args, **kwargs):
            compiled = compile_training(*args, **kwargs)

            def step(*step_args):
                if self.calls in self.slow:
                    self.now += COST * (self.factor - 1)
                return compiled.step(*step_args)

            return dataclasses.replace(compiled, step=step)

        return compile_with_slow_steps


@pytest.fixture
def quiet_load(monkeypatch):
    monkeypatch.setattr(physgrad.runner, "load_average", lambda: 0.2)


def run_toy(tmp_path, *overrides):
    outcome, path = run_experiment(load("task=toy", "trainer.eval_every=100000", "trainer.flush_seconds=1",
                                        *overrides), tmp_path)
    return outcome, read_run(path)


@pytest.mark.parametrize("instants", range(6))
def test_slow_steps_flag_the_run_and_leave_the_calibrated_time_unchanged(tmp_path, monkeypatch, quiet_load,
                                                                         instants):
    """15% of the steps 20 times slower, at random instants: on the calibrated clock the run stops at the same
    iteration with the same calibrated times as a run without them, its measured time grows, and it is flagged."""
    budget = ["trainer.time_budget=4", "trainer.step_cost=0.01", "trainer.clock=calibrated"]
    SimulatedClock(monkeypatch, step=COST)
    quiet_outcome, quiet = run_toy(tmp_path / "quiet", *budget)
    monkeypatch.undo()
    monkeypatch.setattr(physgrad.runner, "load_average", lambda: 0.2)
    rng = np.random.default_rng(instants)
    slow = rng.choice(np.arange(1, 400), size=60, replace=False)
    LoadedClock(monkeypatch, slow)
    loaded_outcome, loaded = run_toy(tmp_path / "loaded", *budget)

    assert quiet_outcome.iterations == loaded_outcome.iterations == 400  # 4 s / 0.01 s per step
    assert quiet.attrs["stopped_by"] == loaded.attrs["stopped_by"] == "time_budget"
    np.testing.assert_array_equal(quiet.train["calibrated_time"], loaded.train["calibrated_time"])
    np.testing.assert_allclose(loaded.train["calibrated_time"], COST * np.arange(1, 401), rtol=1e-12)
    np.testing.assert_array_equal(quiet.eval["iteration"], loaded.eval["iteration"])  # evaluations by the budget's clock
    np.testing.assert_array_equal(quiet.eval["calibrated_time"], loaded.eval["calibrated_time"])
    assert loaded.train["wall_time"][-1] > quiet.train["wall_time"][-1] + 50 * COST * 19 * 0.9
    assert quiet.attrs["contended"] == 0 and "contention" not in quiet.attrs
    assert loaded.attrs["contended"] == 1 and "p90/p50" in loaded.attrs["contention"]
    assert loaded.attrs["step_seconds_p90"] > 1.5 * loaded.attrs["step_seconds_p50"]
    assert loaded.attrs["step_seconds_p50"] == pytest.approx(COST, rel=1e-3)
    assert loaded.attrs["clock"] == "calibrated" and loaded.attrs["step_cost"] == COST


def test_on_the_measured_clock_slow_steps_cost_iterations(tmp_path, monkeypatch, quiet_load):
    """The measured clock is the default: the same slow steps end the run earlier, and the run is flagged."""
    LoadedClock(monkeypatch, range(1, 400, 5))
    outcome, run = run_toy(tmp_path, "trainer.time_budget=4")
    assert outcome.iterations < 400 and run.attrs["contended"] == 1
    assert "calibrated_time" not in run.train and "clock" not in run.attrs


def test_a_few_slow_steps_or_a_short_run_are_not_contention():
    assert contention(step_statistics([COST] * 95 + [20 * COST] * 5), 100, 0.5, 0.5, 2) == ""  # p90 unaffected
    assert contention(step_statistics([COST, 20 * COST] * 5), 10, 0.5, 0.5, 2) == ""  # too few steps to judge
    assert "p90/p50" in contention(step_statistics([COST] * 80 + [20 * COST] * 20), 100, 0.5, 0.5, 2)
    # sub-millisecond steps jitter by fractions of a millisecond on a quiet machine: not contention
    assert contention(step_statistics([3e-4] * 80 + [6e-4] * 20), 100, 0.5, 0.5, 2) == ""
    # a step whose cost depends on the data (a line search) is judged by the load alone
    spread = step_statistics([COST] * 80 + [20 * COST] * 20)
    assert contention(spread, 100, 0.5, 0.5, 2, static_cost=False) == ""
    assert "load average" in contention(spread, 100, 3.5, 0.5, 2, static_cost=False)


@pytest.mark.parametrize("load_start, load_end, flagged", [(0.3, 1.9, False), (3.2, 1.0, True), (0.1, 3.0, True),
                                                          (float("nan"), float("nan"), False)])
def test_an_oversubscribed_machine_is_contention(load_start, load_end, flagged):
    """The load average less the run's own process reaching the cores (2): two CPU-bound processes beside it."""
    why = contention(step_statistics([COST] * 100), 100, load_start, load_end, 2)
    assert bool(why) == flagged and (not flagged or "load average" in why)


def test_the_load_average_is_read_at_the_start_and_the_end(tmp_path, monkeypatch):
    readings = iter([3.5, 0.4])
    monkeypatch.setattr(physgrad.runner, "load_average", lambda: next(readings))
    SimulatedClock(monkeypatch, step=COST)
    _, run = run_toy(tmp_path, "trainer.iterations=30")
    assert (run.attrs["load_start"], run.attrs["load_end"]) == (3.5, 0.4)
    assert run.attrs["contended"] == 1 and "load average 3.50" in run.attrs["contention"]


def test_every_file_records_the_machine_and_the_software(tmp_path):
    _, run = run_toy(tmp_path, "trainer.iterations=25")
    for key in ("cpu_model", "cpu_count", "device", "thread_settings", "jax_version", "jaxlib_version",
                "physgrad_version", "git_commit", "load_start", "load_end", "step_seconds_p50", "step_seconds_p90",
                "step_seconds_p99", "contended"):
        assert key in run.attrs, key
    assert run.attrs["cpu_count"] >= 1 and run.attrs["device"] == "cpu"
    assert run.attrs["step_seconds_p10"] <= run.attrs["step_seconds_p50"] <= run.attrs["step_seconds_p90"] \
        <= run.attrs["step_seconds_p99"]
    assert machine_label(run.attrs).endswith(f"({run.attrs['cpu_count']} cores)")
    assert machine_label({}) == "unknown machine"


def test_the_calibrated_clock_needs_a_step_cost(tmp_path):
    outcome, _ = run_experiment(load("task=toy", "trainer.clock=calibrated"), tmp_path)
    assert outcome.status == "refused" and "trainer.step_cost" in outcome.reason
    outcome, _ = run_experiment(load("task=toy", "trainer.clock=wall"), tmp_path / "b")
    assert outcome.status == "refused" and "trainer.clock" in outcome.reason


def test_the_calibration_ranks_steps_by_their_cost_and_ignores_delays(monkeypatch):
    """Two configurations interleaved in one process: a Jacobian rule's step costs more than Adam's on the same
    scene; 50 ms of other work injected into the first step of one of its bursts in ten (counted by bursts, not
    by steps or seconds, so that neither a busy machine's shorter bursts nor a quiet machine's shorter
    calibration changes how many there are) leaves its calibrated cost where a calibration without them puts
    it."""
    import time

    import physgrad.bench
    from physgrad.calibration import calibrate

    configs = {name: load("task=toy", f"optim={name}", "trainer.batch_size=64") for name in ("adam", "gauss_newton")}
    plain = calibrate(configs, seed=0, rounds=40, min_seconds=0.5, max_seconds=20)
    real = physgrad.bench._compiled
    calls = {"last_step": None, "bursts": 0, "delays": 0}

    def with_delays(cfg, seeds):
        *rest, one_step = real(cfg, seeds)
        if cfg.optim.name != "gauss_newton":
            return (*rest, one_step)

        def slowed():
            # a gap of over 20 ms since its last step: Adam's burst ran in between, a new burst starts here
            if calls["last_step"] is None or time.perf_counter() - calls["last_step"] > 0.02:
                calls["bursts"] += 1
                if calls["bursts"] % 10 == 5:
                    calls["delays"] += 1
                    time.sleep(0.05)
            one_step()
            calls["last_step"] = time.perf_counter()

        return (*rest, slowed)

    monkeypatch.setattr(physgrad.bench, "_compiled", with_delays)
    delayed = calibrate(configs, seed=0, rounds=40, min_seconds=0.5, max_seconds=20)
    assert calls["delays"] >= 2  # the delays happened
    for result in (plain, delayed):
        costs = {name: c["step_seconds"] for name, c in result["costs"].items()}
        assert costs["gauss_newton"] > costs["adam"] > 0
        assert result["costs"]["gauss_newton"]["rounds"] == result["costs"]["adam"]["rounds"] >= 40
        # bursts of about 50 ms: many steps of the fast variant per turn
        assert result["costs"]["adam"]["burst_steps"] > result["costs"]["gauss_newton"]["burst_steps"] >= 1
    # as a ratio to Adam's, timed in the same rounds: other work on the machine between the two calibrations
    # slows both variants alike (absolute costs moved 3x with a sweep running beside the test)
    ratio = {name: r["costs"]["gauss_newton"]["step_seconds"] / r["costs"]["adam"]["step_seconds"]
             for name, r in (("plain", plain), ("delayed", delayed))}
    assert ratio["delayed"] < 1.5 * ratio["plain"]
    assert delayed["machine"]["cpu_count"] >= 1
