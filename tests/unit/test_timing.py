"""Unit layer of the calibrated clock: calibrations on a simulated clock (delays, one cost per
compiled program, cost intervals), the charge of a scheduled update and of a line search's
evaluations in closed form, and a given calibration's costs reaching its jobs, and its refusals."""

import numpy as np
import pytest


@pytest.mark.parametrize("delayed_bursts", [0, 1, 3])
def test_delays_in_a_few_rounds_leave_the_calibrated_cost_where_it_is(monkeypatch, delayed_bursts):
    """On a simulated clock (steps of 1 ms and 12 ms, exact): 50 ms of other work in the first step
    of `delayed_bursts` of every ten bursts of the slow step leaves its cost at 12 ms, the 0.2
    quantile over rounds reading the undelayed ones; in nine of ten it is the delayed cost (the
    injection is seen where it is the rule, so the first case is not a blind clock). The same number
    of delays whatever the machine's load."""
    import types

    import physgrad.timing
    from physgrad.timing import BURST_SECONDS, calibrate

    def calibrated(delayed_of_ten):
        clock = {"now": 0.0, "fast_ran": True, "bursts": 0, "delays": 0}
        costs = {"fast": 0.001, "slow": 0.012}

        def fake_compiled(name, seeds):
            def step():
                if name == "slow" and clock["fast_ran"]:  # a new burst of the slow step starts here
                    clock["fast_ran"] = False
                    clock["bursts"] += 1
                    if clock["bursts"] % 10 < delayed_of_ten:
                        clock["delays"] += 1
                        clock["now"] += 0.05
                clock["fast_ran"] = clock["fast_ran"] or name == "fast"
                clock["now"] += costs[name]

            return (None,) * 6 + (step,)

        monkeypatch.setattr(physgrad.timing, "compiled_step", fake_compiled)
        monkeypatch.setattr(
            physgrad.timing, "time", types.SimpleNamespace(perf_counter=lambda: clock["now"])
        )
        result = calibrate(
            {"fast": "fast", "slow": "slow"}, seed=0, rounds=40, min_seconds=0.5, max_seconds=60
        )
        return result["costs"], clock["delays"]

    plain, none = calibrated(0)
    assert none == 0
    assert plain["fast"]["burst_steps"] == round(BURST_SECONDS / 0.001)
    assert plain["slow"]["burst_steps"] == -(-BURST_SECONDS // 0.012)
    assert plain["slow"]["rounds"] == plain["fast"]["rounds"] >= 40
    assert plain["slow"]["step_seconds"] == pytest.approx(0.012) and plain["fast"][
        "step_seconds"
    ] == pytest.approx(0.001)
    costs, delays = calibrated(delayed_bursts)
    assert delays >= costs["slow"]["rounds"] * delayed_bursts // 10 - 1
    assert costs["slow"]["step_seconds"] == pytest.approx(0.012) and costs["fast"][
        "step_seconds"
    ] == pytest.approx(0.001)
    costs, delays = calibrated(9)
    # (the probe that sizes the bursts sees the delays too, so the bursts are shorter there)
    assert costs["slow"]["step_seconds"] == pytest.approx(
        0.012 + 0.05 / costs["slow"]["burst_steps"]
    )


@pytest.mark.parametrize("slow_seconds, slow_rounds", [(18.0, 2), (5.5, 6)])
def test_a_step_of_seconds_leaves_the_other_steps_their_rounds(
    monkeypatch, slow_seconds, slow_rounds
):
    """On a simulated clock, max_seconds=60 and 30 rounds asked for: steps of 1 ms and 0.3 s beside
    two of `slow_seconds` (a burst above 60 s / 30 = 2 s). The slow ones are timed in rounds of
    their own after the others, on a budget of their own (2 rounds of 36 s, or 6 of 11 s, reach
    60 s); the others get all 30 rounds, every cost exact. Timed in the same rounds, the slow
    steps would have spent the 60 s within 2 rounds and left every step 2 samples."""
    import types

    import physgrad.timing
    from physgrad.timing import calibrate

    clock = {"now": 0.0}
    costs = {"fast": 0.001, "medium": 0.3, "slow": slow_seconds, "slow2": slow_seconds}

    def fake_compiled(name, seeds):
        def step():
            clock["now"] += costs[name]

        return (None,) * 6 + (step,)

    monkeypatch.setattr(physgrad.timing, "compiled_step", fake_compiled)
    monkeypatch.setattr(
        physgrad.timing, "time", types.SimpleNamespace(perf_counter=lambda: clock["now"])
    )
    result = calibrate({n: n for n in costs}, seed=0, rounds=30, min_seconds=0.5, max_seconds=60)
    got = result["costs"]
    assert got["slow"]["rounds"] == got["slow2"]["rounds"] == slow_rounds
    assert got["fast"]["rounds"] == got["medium"]["rounds"] == 30
    for name, cost in costs.items():
        assert got[name]["step_seconds"] == pytest.approx(cost)


def test_two_variants_of_one_compiled_program_get_one_cost_whatever_the_load(monkeypatch):
    """Three variants, two of them one program (the same optimised text: a copy of a rule under
    another name): the calibration times two programs, and the copies get the same cost, interval
    and rounds, even where other work delays the steps at random instants (a clock jittered by up
    to 50 ms in 30% of the bursts, five draws). Every cost lies in its interval."""
    import types

    import numpy as np

    import physgrad.timing
    from physgrad.timing import calibrate

    for draw in range(5):
        rng = np.random.default_rng(draw)
        clock = {"now": 0.0}
        timed = []
        costs = {"adam": 0.001, "adam_copy": 0.001, "gd": 0.002}
        text = {"adam": "HloModule one", "adam_copy": "HloModule one", "gd": "HloModule two"}

        def fake_compiled(name, seeds, clock=clock, rng=rng, timed=timed):
            def step():
                timed.append(name)
                clock["now"] += costs[name] + (0.05 * rng.random() if rng.random() < 0.3 else 0)

            compiled = types.SimpleNamespace(
                lowered_step=types.SimpleNamespace(as_text=lambda: text[name])
            )
            return (None,) * 4 + (compiled, 0.0, step)

        monkeypatch.setattr(physgrad.timing, "compiled_step", fake_compiled)
        monkeypatch.setattr(
            physgrad.timing, "time", types.SimpleNamespace(perf_counter=lambda: clock["now"])
        )
        result = calibrate(
            {name: name for name in costs}, seed=0, rounds=30, min_seconds=0.5, max_seconds=60
        )["costs"]
        assert "adam_copy" not in timed and set(timed) == {"adam", "gd"}
        assert result["adam"] == result["adam_copy"]
        assert result["adam"]["program"] != result["gd"]["program"]
        for cost in result.values():
            assert cost["low_seconds"] <= cost["step_seconds"] <= cost["high_seconds"]


def test_the_interval_of_a_cost_widens_with_a_drift_between_the_halves():
    """cost_interval: steady samples give a tight interval; the same samples 30% dearer in the
    second half (the machine got busy) give one that holds both halves' costs."""
    import numpy as np

    from physgrad.timing import CALIBRATION_QUANTILE, cost_interval

    rng = np.random.default_rng(0)
    steady = 1e-3 * (1 + 0.01 * rng.random(40))
    low, high = cost_interval(steady, CALIBRATION_QUANTILE)
    assert 1e-3 <= low <= np.quantile(steady, CALIBRATION_QUANTILE) <= high <= 1.011e-3
    drifted = np.concatenate([steady[:20], 1.3 * steady[20:]])
    low, high = cost_interval(drifted, CALIBRATION_QUANTILE)
    assert low <= np.quantile(steady[:20], CALIBRATION_QUANTILE)
    assert high >= np.quantile(1.3 * steady[20:], CALIBRATION_QUANTILE)


def annealed_schedule(at_step=None):
    """PSGD Kron's ScheduledUpdate, its step counter pinned in a state {"count": n} by default."""
    import dataclasses

    from physgrad.optim.psgd import scheduled_update

    schedule = scheduled_update({"preconditioner_update_probability": None})
    if at_step is None:
        return dataclasses.replace(schedule, at_step=lambda state, steps: {"count": steps})
    return schedule


def test_the_charge_of_a_scheduled_update_is_what_its_steps_cost_on_average():
    """ScheduledUpdate.charged_seconds(n) against a plain loop over the steps, each charged
    s - u + p_t u (p_t psgdax's annealed schedule at t = 1..n): every step charged s while p_t = 1
    (the first 500), 0.03 u from step 4,007 on; the sums asked for out of order (the cumulative
    sum grows)."""
    import numpy as np

    from physgrad.optim.psgd import annealed_probability

    schedule = annealed_schedule()
    step, update = 2e-3, 1.5e-3
    assert schedule.full_steps == 500 and schedule.floor_step == 4007
    assert annealed_probability(np.array([500, 501]))[1] < 1 == annealed_probability([500])[0]
    assert annealed_probability([4006])[0] > 0.03 == annealed_probability([4007])[0]
    assert schedule.floor == 0.03
    for n in (0, 1, 500, 20_000, 501, 4007, 4008, 2500, 1024, 1025):
        loop = sum(
            step - update + float(annealed_probability([t])[0]) * update for t in range(1, n + 1)
        )
        assert schedule.charged_seconds(n, step, update) == pytest.approx(
            loop, rel=1e-12, abs=1e-15
        )
    assert schedule.charged_seconds(500, step, update) == pytest.approx(500 * step)
    assert schedule.charged_seconds(10_000, step, update) - schedule.charged_seconds(
        9_000, step, update
    ) == pytest.approx(1000 * (step - update + 0.03 * update))
    assert schedule.charged_seconds(700, step, 0.0) == pytest.approx(700 * step)


@pytest.mark.parametrize("update_share", [0.0, 0.3, 0.9])
def test_a_scheduled_update_is_timed_where_every_step_updates_and_where_it_is_rare(
    monkeypatch, update_share
):
    """On a simulated clock, a step that costs c + p_t u (its counter advancing by one a step) and
    Adam's of 1 ms: the calibration times the scheduled step with its counter set back to the start
    before every burst (step_seconds = c + u, although 40 rounds of bursts take it thousands of
    steps on) and to the schedule's floor (advanced_seconds = c + 0.03 u), whence update_seconds =
    u; its bursts of updating steps stay within the first 500 steps. Adam's cost is Adam's."""
    import sys
    import types

    import numpy as np

    import physgrad.optim.capabilities  # noqa: F401  in sys.modules
    import physgrad.timing
    from physgrad.optim.psgd import annealed_probability
    from physgrad.timing import Stepper, calibrate

    step_seconds = 4e-5  # bursts of 0.05 s would be 1,250 steps: more than the 500 that update
    plain, update = (1 - update_share) * step_seconds, update_share * step_seconds
    clock = {"now": 0.0, "counts": []}
    costs = {"adam": lambda count: 1e-3}
    probability = annealed_probability(np.arange(1, 30_001)).tolist()  # p_{count + 1}
    costs["psgd"] = lambda count: plain + probability[count] * update

    def fake_compiled(cfg, seeds):
        name = cfg["optim"]["name"]

        def step(params, state, iteration, keys, sets):
            clock["now"] += costs[name](state["count"])
            clock["counts"].append((name, state["count"]))
            return params, {"count": state["count"] + 1}, []

        compiled = types.SimpleNamespace(params=None, opt_state={"count": 0}, step=step)
        stacked = types.SimpleNamespace(train_keys=None, train_sets=None)
        return None, None, None, stacked, compiled, 0.0, Stepper(compiled, stacked)

    monkeypatch.setattr(physgrad.timing, "compiled_step", fake_compiled)
    monkeypatch.setattr(
        physgrad.timing, "time", types.SimpleNamespace(perf_counter=lambda: clock["now"])
    )
    monkeypatch.setattr(
        sys.modules["physgrad.optim.capabilities"],  # (physgrad.optim.capabilities: a function)
        "scheduled_update",
        lambda optim: annealed_schedule() if optim["name"] == "psgd" else None,
    )
    configs = {name: {"optim": {"name": name}} for name in ("adam", "psgd")}
    result = calibrate(configs, seed=0, rounds=40, min_seconds=0.5, max_seconds=600)["costs"]
    assert result["adam"]["step_seconds"] == pytest.approx(1e-3)
    assert "update_seconds" not in result["adam"]
    psgd = result["psgd"]
    assert psgd["step_seconds"] == pytest.approx(step_seconds)
    assert psgd["advanced_seconds"] == pytest.approx(plain + 0.03 * update)
    assert psgd["update_seconds"] == pytest.approx(update, abs=1e-12)
    assert psgd["advanced_step"] == 4007 and psgd["floor_probability"] == 0.03
    assert psgd["burst_steps"] == 500 and psgd["rounds"] >= 40
    counts = np.array([count for name, count in clock["counts"] if name == "psgd"])
    assert len(counts) > 40 * 500  # the scheduled step ran on far past its first 500 steps ...
    assert set(counts[counts < 4007]) == set(range(500))  # ... never at a count in between


def test_a_calibrations_update_cost_goes_to_its_variants_jobs(tmp_path):
    """calibrated_clock with a given calibration.json: a variant whose cost has update_seconds runs
    with trainer.update_cost, the others without; an update cost for a rule without a schedule
    (Adam, or PSGD Kron with a fixed update probability) is refused in one line before any job."""
    import json
    import types

    from physgrad.comparison.calibration import calibrated_clock
    from physgrad.errors import UserError
    from tests.helpers import scheduled_calibration

    psgd_target = "physgrad.optim.psgd.psgd_kron"

    calibration = scheduled_calibration()
    given = tmp_path / "given.json"
    given.write_text(json.dumps(calibration))
    rules = {"adam": {"_target_": "optax.adam"}, "psgd_kron": {"_target_": psgd_target}}
    variants = [
        types.SimpleNamespace(name=name, config=types.SimpleNamespace(optim=optim), space={})
        for name, optim in rules.items()
    ]
    plan = types.SimpleNamespace(variants=variants)
    launcher = types.SimpleNamespace(folder=tmp_path, say=print)
    assert calibrated_clock(plan, launcher, str(given)) == calibration
    assert variants[0].job_values == {"trainer.step_cost": 2e-3, "trainer.clock": "calibrated"}
    assert variants[1].job_values == {
        "trainer.step_cost": 2e-3,
        "trainer.clock": "calibrated",
        "trainer.update_cost": 1e-3,
    }
    fixed = {"_target_": psgd_target, "preconditioner_update_probability": 0.5}
    for wrong in ({"_target_": "optax.adam"}, fixed):
        variants[1].config.optim = wrong
        with pytest.raises(UserError, match="psgd_kron's cost has an update cost") as error:
            calibrated_clock(plan, launcher, str(given))
        assert "\n" not in str(error.value)


def test_a_line_search_is_charged_the_evaluations_its_steps_made():
    """TrainerSettings.charged_seconds(n, E) for a line search of v = 0.5 ms an evaluation within a
    step cost s = 2 ms that held e = 1.5 of them: the plain-loop sum of s - v e + v e_t over steps
    of 1, 20, 3, ... evaluations; without a line search's costs, n s whatever E. Both costs or
    neither, with v e at most s, each refused in one line that names what to give."""
    import numpy as np

    from physgrad.errors import UserError
    from physgrad.trainer_settings import TrainerSettings

    base = {"eval_every": 10, "batch_size": 4, "flush_seconds": 1.0, "clock": "calibrated"}
    step, each, mean = 2e-3, 5e-4, 1.5
    settings = TrainerSettings.from_config(
        {**base, "step_cost": step, "evaluation_cost": each, "step_evaluations": mean}
    )
    made = np.random.default_rng(0).integers(1, 21, 300)
    for n in (0, 1, 7, 300):
        loop = sum(step - each * mean + each * float(e) for e in made[:n])
        assert settings.charged_seconds(n, float(made[:n].sum())) == pytest.approx(loop, rel=1e-12)
    plain = TrainerSettings.from_config({**base, "step_cost": step})
    assert plain.charged_seconds(300, 9999.0) == pytest.approx(300 * step)
    for wrong, said in (
        ({"step_cost": step, "evaluation_cost": each}, "give both"),
        ({"step_cost": step, "step_evaluations": mean}, "give both"),
        ({"evaluation_cost": each, "step_evaluations": mean, "clock": "measured"}, "give both"),
        ({"step_cost": step, "evaluation_cost": 1e-3, "step_evaluations": 3}, "more than"),
        ({"step_cost": step, "evaluation_cost": -1e-3, "step_evaluations": 1}, "evaluation_cost"),
    ):
        with pytest.raises(UserError, match=said) as error:
            TrainerSettings.from_config({**base, **wrong})
        assert "\n" not in str(error.value)


def test_a_line_search_is_timed_per_evaluation_and_counted_over_the_timed_steps(monkeypatch):
    """On a simulated clock, a line-search step that costs c + v e_t (e_t cycling 1, 3, 2, 20
    evaluations, the counts it logs) and one evaluation timed alone at v: the calibration gives
    evaluation_seconds = v and step_evaluations = the mean count over the timed steps only (the
    probe's and warm-up's steps left out); Adam, searching no line, gets neither."""
    import sys
    import types

    import numpy as np

    import physgrad.optim.capabilities  # noqa: F401  in sys.modules
    import physgrad.timing
    from physgrad.optim import LINE_SEARCH_LOG
    from physgrad.optim.capabilities import Capabilities
    from physgrad.timing import EVALUATIONS_PER_CALL, Stepper, calibrate

    plain, each, cycle = 2e-4, 5e-5, [1, 3, 2, 20]
    clock = {"now": 0.0, "made": []}

    def fake_compiled(cfg, seeds):
        name = cfg["optim"]["name"]

        def step(params, state, iteration, keys, sets):
            made = cycle[state["count"] % 4] if name == "lbfgs" else 0
            clock["now"] += (1e-3 if name == "adam" else plain) + each * made
            if name == "lbfgs":
                clock["made"].append(made)
            return params, {"count": state["count"] + 1}, np.array([[made, 0.0]])

        compiled = types.SimpleNamespace(
            params=None, opt_state={"count": 0}, step=step, log_names=[LINE_SEARCH_LOG, "loss"]
        )
        stacked = types.SimpleNamespace(train_keys=None, train_sets=None)
        settings = types.SimpleNamespace(batch_size=4)
        return settings, None, None, stacked, compiled, 0.0, Stepper(compiled, stacked)

    def fake_evaluations(scene, seeds, batch_size):
        def call():
            clock["now"] += each * EVALUATIONS_PER_CALL

        return call

    searching = Capabilities("lbfgs", (1e-2, 1e1), line_search=True)
    monkeypatch.setattr(physgrad.timing, "compiled_step", fake_compiled)
    monkeypatch.setattr(physgrad.timing, "evaluation_call", fake_evaluations)
    monkeypatch.setattr(
        physgrad.timing, "time", types.SimpleNamespace(perf_counter=lambda: clock["now"])
    )
    module = sys.modules["physgrad.optim.capabilities"]
    monkeypatch.setattr(module, "scheduled_update", lambda optim: None)
    monkeypatch.setattr(
        module,
        "capabilities",
        lambda optim: searching if optim["name"] == "lbfgs" else Capabilities("adaptive", (1, 2)),
    )
    configs = {name: {"optim": {"name": name}} for name in ("adam", "lbfgs")}
    result = calibrate(configs, seed=0, rounds=40, min_seconds=0.5, max_seconds=600)["costs"]
    assert "evaluation_seconds" not in result["adam"] and "step_evaluations" not in result["adam"]
    lbfgs = result["lbfgs"]
    assert lbfgs["evaluation_seconds"] == pytest.approx(each, rel=1e-9)
    timed = clock["made"][-lbfgs["burst_steps"] * lbfgs["rounds"] :]
    assert lbfgs["step_evaluations"] == pytest.approx(np.mean(timed), rel=1e-12)
    assert len(clock["made"]) > len(timed)  # the untimed steps were left out


def test_a_calibrations_evaluation_cost_goes_to_its_line_search_jobs(tmp_path):
    """calibrated_clock with a given calibration.json whose L-BFGS cost has a line search's
    evaluation cost: L-BFGS's jobs run with trainer.evaluation_cost and step_evaluations, Adam's
    without; the same cost on a rule that searches no line is refused in one line; a calibration
    whose v e exceeds its step cost, or whose e is not a number, is not a calibration."""
    import json
    import types

    from physgrad.comparison.calibration import calibrated_clock, read_calibration
    from physgrad.errors import UserError
    from tests.helpers import scheduled_calibration

    calibration = scheduled_calibration()
    cost = calibration["costs"]["adam"]
    calibration["costs"] = {
        "adam": cost,
        "lbfgs": {**cost, "evaluation_seconds": 5e-4, "step_evaluations": 2.5},
    }
    given = tmp_path / "given.json"
    given.write_text(json.dumps(calibration))
    rules = {"adam": {"_target_": "optax.adam"}, "lbfgs": {"_target_": "optax.lbfgs"}}
    variants = [
        types.SimpleNamespace(name=name, config=types.SimpleNamespace(optim=optim), space={})
        for name, optim in rules.items()
    ]
    plan = types.SimpleNamespace(variants=variants)
    launcher = types.SimpleNamespace(folder=tmp_path, say=print)
    assert calibrated_clock(plan, launcher, str(given)) == calibration
    assert variants[0].job_values == {"trainer.step_cost": 2e-3, "trainer.clock": "calibrated"}
    assert variants[1].job_values == {
        "trainer.step_cost": 2e-3,
        "trainer.clock": "calibrated",
        "trainer.evaluation_cost": 5e-4,
        "trainer.step_evaluations": 2.5,
    }
    variants[1].config.optim = {"_target_": "optax.adam"}
    with pytest.raises(UserError, match="lbfgs's cost has a line search's") as error:
        calibrated_clock(plan, launcher, str(given))
    assert "\n" not in str(error.value)
    for wrong in ({"step_evaluations": 5.0}, {"step_evaluations": "2"}, {"evaluation_seconds": -1}):
        calibration["costs"]["lbfgs"].update(wrong)
        given.write_text(json.dumps(calibration))
        assert read_calibration(given, ["adam", "lbfgs"], given=True) is None, wrong
        calibration["costs"]["lbfgs"].update(evaluation_seconds=5e-4, step_evaluations=2.5)


@pytest.mark.parametrize("shape", ["inverse", "linear"])
def test_a_setting_that_shapes_the_step_cost_is_charged_the_cost_at_its_value(shape):
    """knob_cost through the costs at the range's ends recovers the cost model exactly at every
    value between them: c + u / f for a period f (SOAP's eigenbasis every f steps), a + b m for a
    count m (L-BFGS's memory), with c, u, a, b drawn at random; a value between the ends costs
    between their costs; an unknown shape is refused."""
    from physgrad.optim.capabilities import knob_cost

    rng = np.random.default_rng(3)
    for _ in range(20):
        base, part = rng.uniform(1e-4, 1e-2, 2)
        low, high = sorted(rng.integers(1, 200, 2) + np.array([0, 1]))
        cost = (lambda x: base + part / x) if shape == "inverse" else (lambda x: base + part * x)
        for value in np.linspace(low, high, 7):
            charged = knob_cost(shape, value, low, cost(low), high, cost(high))
            assert charged == pytest.approx(cost(value), rel=1e-12)
            ends = sorted((cost(low), cost(high)))
            assert ends[0] * (1 - 1e-12) <= charged <= ends[1] * (1 + 1e-12)
    with pytest.raises(ValueError, match="give inverse, linear or floor"):
        knob_cost("square", 2, 1, 1e-3, 4, 2e-3)


def test_a_calibrations_costs_at_a_knobs_ends_price_each_trial_and_evaluation(tmp_path):
    """calibrated_clock for SOAP tuned over its preconditioning frequency [1, 100] and L-BFGS over
    its memory [2, 100] (compare.knobs=true): the calibration holds each one's step cost at its
    range's two ends (name@key=value), the variant keeps the own part of a step there and at its
    preset, and a job at a trial's or the tuned value is charged that own part piecewise at the
    value (the preset's measured cost at the preset) plus the preset's line-search evaluations,
    never an end's own evaluations again; Adam, whose eps does not change a step's cost, keeps one
    cost. A given calibration without the ends is refused in one line that names them; a study
    folder calibrated before a variant's ends were resumes that variant at its preset cost, with a
    note that names it, and the others at their own points."""
    import json
    import types

    from physgrad.comparison.calibration import calibrated_clock
    from physgrad.comparison.spec import Variant
    from physgrad.errors import UserError
    from physgrad.optim.capabilities import knob_cost

    def cost(seconds: float, **more) -> dict:
        return {"step_seconds": seconds, "median_seconds": seconds, "rounds": 30, **more}

    calibration = {
        "quantile": 0.2,
        "load_start": 0.1,
        "load_end": 0.1,
        "machine": {},
        "costs": {
            "adam": cost(1e-3),
            "soap": cost(2e-3),
            "soap@precondition_frequency=1": cost(9e-3),
            "soap@precondition_frequency=100": cost(1.2e-3),
            "lbfgs": cost(3e-3, evaluation_seconds=1e-3, step_evaluations=2.0),
            # own parts: 1.5 ms at memory 2, 1 ms at the preset 10, 3 ms at 100
            "lbfgs@memory_size=2": cost(2.5e-3, evaluation_seconds=1e-3, step_evaluations=1.0),
            "lbfgs@memory_size=100": cost(6e-3, evaluation_seconds=1e-3, step_evaluations=3.0),
        },
    }
    given = tmp_path / "given.json"
    given.write_text(json.dumps(calibration))
    optims = {
        "adam": ({"_target_": "optax.adam"}, {"learning_rate": (1e-5, 0.1), "eps": (1e-10, 1e-4)}),
        "soap": (
            {"_target_": "physgrad.optim.soap.soap", "precondition_frequency": 10},
            {"learning_rate": (1e-5, 0.1), "precondition_frequency": (1, 100)},
        ),
        "lbfgs": (
            {"_target_": "optax.lbfgs", "memory_size": 10},
            {"learning_rate": (0.01, 10.0), "memory_size": (2, 100)},
        ),
    }
    variants = [
        Variant(name, [], types.SimpleNamespace(optim=optim), space)
        for name, (optim, space) in optims.items()
    ]
    launcher = types.SimpleNamespace(folder=tmp_path, say=print)
    calibrated_clock(types.SimpleNamespace(variants=variants), launcher, str(given))
    adam, soap, lbfgs = variants
    assert adam.cost_knob == () and adam.priced({"eps": 1e-9, "learning_rate": 1e-3}) == {}
    points = ((1, 9e-3), (10, 2e-3), (100, 1.2e-3))
    assert soap.cost_knob == ("precondition_frequency", "inverse", points)
    for frequency, (low, high) in ((1, (0, 1)), (7, (0, 1)), (10, (1, 2)), (40, (1, 2))):
        (a, ca), (b, cb) = points[low], points[high]
        priced = soap.priced({"learning_rate": 1e-3, "precondition_frequency": frequency})
        expected = knob_cost("inverse", frequency, a, ca, b, cb)
        assert priced == {"trainer.step_cost": pytest.approx(expected, rel=1e-12)}
    assert soap.priced({"precondition_frequency": 10}) == {"trainer.step_cost": 2e-3}
    assert soap.priced({"learning_rate": 1e-3}) == {}  # untuned: the preset's calibrated cost
    # L-BFGS: the own part through (2, 1.5 ms), (10, 1 ms), (100, 3 ms), plus the preset's 2 ms
    # of evaluations (the run is charged the evaluations it makes): 3 ms at the preset, as
    # measured, and 5 ms at memory 100, not the 6 ms that hold that end's own evaluations
    for memory, own in ((2, 1.5e-3), (10, 1e-3), (55, 2e-3), (100, 3e-3)):
        assert lbfgs.priced({"memory_size": memory}) == {
            "trainer.step_cost": pytest.approx(own + 2e-3, rel=1e-12)
        }
    assert lbfgs.job_values["trainer.step_cost"] == 3e-3
    del calibration["costs"]["soap@precondition_frequency=100"]
    given.write_text(json.dumps(calibration))
    with pytest.raises(UserError, match="soap@precondition_frequency=100") as error:
        calibrated_clock(types.SimpleNamespace(variants=variants), launcher, str(given))
    assert "\n" not in str(error.value)
    # a study folder calibrated before the ends were (its own calibration.json without them)
    older = tmp_path / "older"
    older.mkdir()
    del calibration["costs"]["soap@precondition_frequency=1"]
    (older / "calibration.json").write_text(json.dumps(calibration))
    said = []
    resumed = types.SimpleNamespace(folder=older, say=said.append)
    calibrated_clock(types.SimpleNamespace(variants=variants), resumed, None)
    assert soap.cost_knob == () and soap.priced({"precondition_frequency": 1}) == {}
    assert soap.job_values["trainer.step_cost"] == 2e-3 and "preset cost" in said[0]
    # only the variant whose points are missing falls back: L-BFGS keeps its memory's costs
    assert "for soap:" in said[0] and "lbfgs" not in said[0]
    assert lbfgs.cost_knob[0] == "memory_size"
    assert lbfgs.priced({"memory_size": 100}) == {"trainer.step_cost": pytest.approx(5e-3)}


def test_a_truncation_below_the_gram_route_is_charged_the_svds_cost(tmp_path):
    """HIG tuned over tau [1e-9, 1e-3] (preset 1e-6): the calibration times it at the range's ends
    and at the Gram route's break 1e-6 (GRAM_MIN_TAU, the value physgrad.optim.spectral takes the
    route by), and a trial is charged the cost of the calibrated point at or below its tau: the
    SVD's for every tau below 1e-6, the Gram route's at and above it, never a blend. A given
    calibration without the break is refused in one line that names it."""
    import json
    import types

    from physgrad.comparison.calibration import calibrated_clock, knob_ends
    from physgrad.comparison.spec import Variant
    from physgrad.errors import UserError
    from physgrad.optim import spectral
    from physgrad.optim.capabilities import GRAM_MIN_TAU, knob_cost

    assert spectral.GRAM_MIN_TAU == GRAM_MIN_TAU == 1e-6
    wide, tall = (4, 8), (8, 4)
    assert spectral.resolve_route("auto", 0.99e-6, wide) == "svd"
    assert spectral.resolve_route("auto", 1e-6, wide) == "gram"
    assert spectral.resolve_route("auto", 1e-3, tall) == "svd"
    for value, expected in ((1e-9, 5.0), (5e-7, 5.0), (0.999e-6, 5.0), (1e-6, 1.0)):
        assert knob_cost("floor", value, 1e-9, 5.0, 1e-6, 1.0) == expected

    def cost(seconds: float) -> dict:
        return {"step_seconds": seconds, "median_seconds": seconds, "rounds": 30}

    costs = {
        "hig": cost(2e-3),
        "hig@tau=1e-09": cost(1.1e-2),
        "hig@tau=1e-06": cost(2.1e-3),
        "hig@tau=0.001": cost(1.9e-3),
    }
    given = tmp_path / "given.json"
    calibration = {"quantile": 0.2, "load_start": 0.1, "load_end": 0.1, "machine": {}}
    given.write_text(json.dumps({**calibration, "costs": costs}))
    optim = {"_target_": "physgrad.optim.spectral.spectral_rule", "kappa": 0.5, "tau": 1e-6}
    hig = Variant("hig", [], types.SimpleNamespace(optim=optim), {"tau": (1e-9, 1e-3)})
    assert set(knob_ends(hig)) == set(costs) - {"hig"}
    launcher = types.SimpleNamespace(folder=tmp_path, say=print)
    calibrated_clock(types.SimpleNamespace(variants=[hig]), launcher, str(given))
    assert hig.cost_knob == ("tau", "floor", ((1e-9, 1.1e-2), (1e-6, 2e-3), (1e-3, 1.9e-3)))
    rng = np.random.default_rng(5)
    for tau in 10 ** rng.uniform(-9, -3, 200):
        charged = hig.priced({"tau": tau})["trainer.step_cost"]
        assert charged == (1.1e-2 if tau < GRAM_MIN_TAU else 2e-3 if tau < 1e-3 else 1.9e-3)
    assert hig.priced({"tau": 1e-6}) == {"trainer.step_cost": 2e-3}
    del costs["hig@tau=1e-06"]
    given.write_text(json.dumps({**calibration, "costs": costs}))
    (tmp_path / "calibration.json").unlink()
    with pytest.raises(UserError, match="hig@tau=1e-06") as error:
        calibrated_clock(types.SimpleNamespace(variants=[hig]), launcher, str(given))
    assert "\n" not in str(error.value)
