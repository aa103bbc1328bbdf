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
