"""Unit layer (pure functions, no scene compiled) of the tests of:
The calibrated clock, the contention flag and the machine a result was measured on: slow steps
are injected by replacing the runner's clock, at random instants, and the calibrated time must not
move."""

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
