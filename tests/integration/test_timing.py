"""Integration layer of the calibrated clock, contention and the machine: slow steps injected
through the runner's clock leave the calibrated time unchanged and flag the run, scheduled updates
and line searches are charged their costs, real calibrations rank the steps, and every file
records the machine and the software."""

import jax
import numpy as np
import pytest

import physgrad.runner
from physgrad.experiment import run_experiment
from physgrad.machine import contention, machine_label, step_statistics
from physgrad.results import read_run
from tests.helpers import SimulatedClock, load

COST = 0.01


class LoadedClock(SimulatedClock):
    """SimulatedClock whose steps are slowed `factor` times at the given step numbers (another
    process taking the cores for a while)."""

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
    outcome, path = run_experiment(
        load("task=toy", "trainer.eval_every=100000", "trainer.flush_seconds=1", *overrides),
        tmp_path,
    )
    return outcome, read_run(path)


# one draw of the instants in make test, five more in make test-long
@pytest.mark.parametrize(
    "instants", [0, *(pytest.param(k, marks=pytest.mark.long) for k in range(1, 6))]
)
def test_slow_steps_flag_the_run_and_leave_the_calibrated_time_unchanged(
    tmp_path, monkeypatch, quiet_load, instants
):
    """15% of the steps 20 times slower, at random instants: on the calibrated clock the run stops
    at the same iteration with the same calibrated times as a run without them, its measured time
    grows, and it is flagged."""
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
    np.testing.assert_allclose(
        loaded.train["calibrated_time"], COST * np.arange(1, 401), rtol=1e-12
    )
    # evaluations by the budget's clock
    np.testing.assert_array_equal(quiet.eval["iteration"], loaded.eval["iteration"])
    np.testing.assert_array_equal(quiet.eval["calibrated_time"], loaded.eval["calibrated_time"])
    assert loaded.train["wall_time"][-1] > quiet.train["wall_time"][-1] + 50 * COST * 19 * 0.9
    assert quiet.attrs["contended"] == 0 and "contention" not in quiet.attrs
    assert loaded.attrs["contended"] == 1 and "p90/p50" in loaded.attrs["contention"]
    assert loaded.attrs["step_seconds_p90"] > 1.5 * loaded.attrs["step_seconds_p50"]
    assert loaded.attrs["step_seconds_p50"] == pytest.approx(COST, rel=1e-3)
    assert loaded.attrs["clock"] == "calibrated" and loaded.attrs["step_cost"] == COST


def test_on_the_measured_clock_slow_steps_cost_iterations(tmp_path, monkeypatch, quiet_load):
    """The measured clock is the default: the same slow steps end the run earlier, and the run is
    flagged."""
    LoadedClock(monkeypatch, range(1, 400, 5))
    outcome, run = run_toy(tmp_path, "trainer.time_budget=4")
    assert outcome.iterations < 400 and run.attrs["contended"] == 1
    assert "calibrated_time" not in run.train and "clock" not in run.attrs


def test_a_few_slow_steps_or_a_short_run_are_not_contention():
    # p90 unaffected
    assert contention(step_statistics([COST] * 95 + [20 * COST] * 5), 100, 0.5, 0.5, 2) == ""
    # too few steps to judge
    assert contention(step_statistics([COST, 20 * COST] * 5), 10, 0.5, 0.5, 2) == ""
    assert "p90/p50" in contention(
        step_statistics([COST] * 80 + [20 * COST] * 20), 100, 0.5, 0.5, 2
    )
    # sub-millisecond steps jitter by fractions of a millisecond on a quiet machine: not contention
    assert contention(step_statistics([3e-4] * 80 + [6e-4] * 20), 100, 0.5, 0.5, 2) == ""
    # a step whose cost depends on the data (a line search) is judged by the load alone
    spread = step_statistics([COST] * 80 + [20 * COST] * 20)
    assert contention(spread, 100, 0.5, 0.5, 2, static_cost=False) == ""
    assert "load average" in contention(spread, 100, 3.5, 0.5, 2, static_cost=False)


@pytest.mark.parametrize(
    "load_start, load_end, flagged",
    [(0.3, 1.9, False), (3.2, 1.0, True), (0.1, 3.0, True), (float("nan"), float("nan"), False)],
)
def test_an_oversubscribed_machine_is_contention(load_start, load_end, flagged):
    """The load average less the run's own process reaching the cores (2): two CPU-bound processes
    beside it."""
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
    for key in (
        "cpu_model",
        "cpu_count",
        "device",
        "thread_settings",
        "jax_version",
        "jaxlib_version",
        "physgrad_version",
        "git_commit",
        "load_start",
        "load_end",
        "step_seconds_p50",
        "step_seconds_p90",
        "step_seconds_p99",
        "contended",
    ):
        assert key in run.attrs, key
    assert run.attrs["cpu_count"] >= 1 and run.attrs["device"] == "cpu"
    assert (
        run.attrs["step_seconds_p10"]
        <= run.attrs["step_seconds_p50"]
        <= run.attrs["step_seconds_p90"]
        <= run.attrs["step_seconds_p99"]
    )
    assert machine_label(run.attrs).endswith(f"({run.attrs['cpu_count']} cores)")
    assert machine_label({}) == "unknown machine"


def test_the_calibrated_clock_needs_a_step_cost(tmp_path):
    outcome, _ = run_experiment(load("task=toy", "trainer.clock=calibrated"), tmp_path)
    assert outcome.status == "refused" and "trainer.step_cost" in outcome.reason
    outcome, _ = run_experiment(load("task=toy", "trainer.clock=wall"), tmp_path / "b")
    assert outcome.status == "refused" and "trainer.clock" in outcome.reason


def test_a_scheduled_update_is_charged_its_expected_cost_and_only_for_a_rule_with_one(tmp_path):
    """PSGD Kron on the toy with step_cost s = 2 ms of which update_cost u = 1.5 ms: the
    calibrated time after n steps is the plain-loop sum of s - u + p_t u (p_t psgdax's schedule),
    s a step for the first 500, and the run stops at the first n where that reaches the 1.2 s
    budget (n s would stop it at 600). An update cost for Adam, one above the step cost, or one
    without a step cost is refused in one line that names it. at_step reaches the counter in the
    state of the compiled training the calibration times (one per seed): set to floor_step, one step
    later it reads floor_step + 1."""
    import psgdax

    from physgrad.optim.psgd import annealed_probability, scheduled_update
    from physgrad.timing import compiled_step

    step, update, budget = 2e-3, 1.5e-3, 1.2
    charged = np.cumsum(step - update + annealed_probability(np.arange(1, 2000)) * update)
    expected = int(np.argmax(charged >= budget - 1e-12)) + 1
    outcome, run = run_toy(
        tmp_path / "psgd",
        "optim=psgd_kron",
        f"trainer.time_budget={budget}",
        f"trainer.step_cost={step}",
        f"trainer.update_cost={update}",
        "trainer.clock=calibrated",
    )
    assert outcome.status == "completed" and run.attrs["stopped_by"] == "time_budget"
    assert outcome.iterations == expected > 600
    np.testing.assert_allclose(run.train["calibrated_time"], charged[:expected], rtol=1e-12)
    assert run.attrs["update_cost"] == update and run.attrs["step_cost"] == step
    for refused, key in (
        (["optim=adam", "trainer.step_cost=0.002", "trainer.update_cost=0.001"], "optim=adam"),
        (["optim=psgd_kron", "trainer.step_cost=0.002", "trainer.update_cost=0.003"], "0.003"),
        (["optim=psgd_kron", "trainer.update_cost=0.001"], "trainer.update_cost"),
    ):
        outcome, _ = run_experiment(load("task=toy", *refused), tmp_path / key)
        assert outcome.status == "refused" and "trainer.update_cost" in outcome.reason, refused
        assert key in outcome.reason and "\n" not in outcome.reason
    schedule = scheduled_update({"preconditioner_update_probability": None})
    *_, one_step = compiled_step(load("task=toy", "optim=psgd_kron"), [0])
    one_step.opt_state = schedule.at_step(one_step.opt_state, schedule.floor_step)
    one_step()

    def kron(part) -> bool:
        return isinstance(part, psgdax.psgd.KronState)

    def counters(state):
        parts = jax.tree.leaves(state, is_leaf=kron)
        return [np.asarray(p.count).tolist() for p in parts if kron(p)]

    assert counters(one_step.opt_state) == [[schedule.floor_step + 1]]


def test_a_line_search_is_charged_the_evaluations_it_made_and_only_a_line_search(tmp_path):
    """L-BFGS on the toy (fresh minibatches: its line searches take from 1 to 20 evaluations a
    step) with s = 1 ms a step holding e = 1.5 evaluations of v = 0.2 ms: the calibrated time after
    n steps is the plain-loop sum of s - v e + v e_t over the evaluations e_t the steps logged, and
    the run stops at the first n where it reaches the 0.3 s budget; an evaluation cost for Adam is
    refused in one line that names it."""
    step, each, mean, budget = 1e-3, 2e-4, 1.5, 0.3
    outcome, run = run_toy(
        tmp_path / "lbfgs",
        "optim=lbfgs",
        f"trainer.time_budget={budget}",
        f"trainer.step_cost={step}",
        f"trainer.evaluation_cost={each}",
        f"trainer.step_evaluations={mean}",
        "trainer.clock=calibrated",
    )
    assert outcome.status == "completed" and run.attrs["stopped_by"] == "time_budget"
    made = np.asarray(run.train["linesearch_evaluations"])
    assert made.min() >= 1 and made.max() > 2
    charged = np.cumsum([step - each * mean + each * e for e in made])
    np.testing.assert_allclose(run.train["calibrated_time"], charged, rtol=1e-12)
    assert charged[-1] >= budget - 1e-12 > charged[-2]
    assert run.attrs["evaluation_cost"] == each and run.attrs["step_evaluations"] == mean
    outcome, _ = run_experiment(
        load(
            "task=toy",
            "optim=adam",
            f"trainer.step_cost={step}",
            f"trainer.evaluation_cost={each}",
            f"trainer.step_evaluations={mean}",
        ),
        tmp_path / "adam",
    )
    assert outcome.status == "refused" and "trainer.evaluation_cost" in outcome.reason
    assert "optim=adam" in outcome.reason and "\n" not in outcome.reason


@pytest.mark.long
def test_a_real_line_search_is_calibrated_per_evaluation():
    """L-BFGS and Adam on the toy interleaved in one process: L-BFGS's cost has one evaluation's
    seconds (more than 0, and v e within its step cost) and the evaluations its timed steps made
    (at least one a step: the zoom line search evaluates its first trial); Adam's has neither."""
    from physgrad.timing import calibrate

    configs = {name: load("task=toy", f"optim={name}") for name in ("adam", "lbfgs")}
    costs = calibrate(configs, seed=0, rounds=20, min_seconds=0.5, max_seconds=600)["costs"]
    lbfgs = costs["lbfgs"]
    assert lbfgs["evaluation_seconds"] > 0 and lbfgs["step_evaluations"] >= 1
    assert lbfgs["evaluation_seconds"] * lbfgs["step_evaluations"] <= lbfgs["step_seconds"]
    assert "evaluation_seconds" not in costs["adam"]


# a real calibration of two rules (40 rounds of bursts): make test-long, as the real line search's
# above; make test keeps the calibrations on a simulated clock (tests/unit/test_timing.py) and a
# real compiled step timed through the calibration's compiled_step in
# test_a_scheduled_update_is_charged_its_expected_cost_and_only_for_a_rule_with_one
@pytest.mark.long
def test_the_calibration_ranks_real_steps_by_their_cost():
    """Two configurations interleaved in one process: a Jacobian rule's step costs more than Adam's
    on the same scene (about 9 to 26 times on the 2-core machine, quiet or beside a 2-core job),
    both timed in every round."""
    from physgrad.timing import calibrate

    configs = {
        name: load("task=toy", f"optim={name}", "trainer.batch_size=64")
        for name in ("adam", "gauss_newton")
    }
    # max_seconds well above what 40 rounds of bursts take (about 10 s with a study beside it; 31
    # rounds were done at 60 s with a study and the whole suite beside it), so that a loaded machine
    # slows the calibration without cutting its rounds: the count is what is asserted
    result = calibrate(configs, seed=0, rounds=40, min_seconds=0.5, max_seconds=600)
    costs = {name: c["step_seconds"] for name, c in result["costs"].items()}
    assert costs["gauss_newton"] > costs["adam"] > 0
    assert result["costs"]["gauss_newton"]["rounds"] == result["costs"]["adam"]["rounds"] >= 40
    assert result["machine"]["cpu_count"] >= 1
