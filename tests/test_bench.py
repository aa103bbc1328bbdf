"""make bench on tiny problems: every number the table needs is measured, nothing is asserted about speed."""

import math

from physgrad.bench import _median_times, measure_floors, measure_seeds, measure_variant, seeds_table, table


def test_bench_measures_steps_floors_and_overhead():
    small = ["task=poisson", "task.grid=4", "task.test_size=8", "trainer.batch_size=4"]
    hig = measure_variant([*small, "optim=hig"], repeats=2, min_seconds=0)
    adam = measure_variant([*small, "optim=adam"], repeats=2, min_seconds=0)
    assert hig["jac_shape"] == [4 * 16, 1 * 16 * 16 + 16 + 16 * 32 + 32 + 32 * 16 + 16 + 16 * 16 + 16]
    assert hig["route"] == "gram" and hig["step_s"] > 0 and hig["jacobian_s"] > 0 and hig["peak_rss_gb"] > 0
    assert adam["loss_grad_s"] > 0 and 0 <= adam["runner_overhead"] < 1 and 0 < adam["eval_share"] < 1
    floors = measure_floors(tuple(hig["jac_shape"]), 32, repeats=2)
    assert floors["svd_numpy_s"] > 0 and floors["svd_jax_s"] > 0
    rows = [{"task": "poisson", "variant": "hig", "precision": 32, **hig, "floors": floors},
            {"task": "poisson", "variant": "adam", "precision": 32, **adam}]
    text = table(rows)
    ratio = hig["step_s"] / (hig["jacobian_s"] + min(floors.values()))
    assert f"| {ratio:.2f} |" in text and f"| {adam['step_s'] / adam['loss_grad_s']:.2f} |" in text
    assert math.isfinite(ratio)


def test_a_refused_variant_is_left_out():
    assert "refused" in measure_variant(["task=poisson", "optim=bptt"], repeats=1, min_seconds=0)


def test_timings_are_taken_in_turn_with_their_baseline():
    calls = []
    medians = _median_times([lambda: calls.append("step"), lambda: calls.append("bare")], repeats=3, min_seconds=0)
    assert calls == ["step", "bare"] * 4  # one warm-up call each, then rounds of one call each
    assert [count for _, count in medians] == [3, 3]


def test_seeds_are_timed_against_one_seed_in_the_same_process():
    small = ["task=poisson", "task.grid=4", "task.test_size=8", "trainer.batch_size=4", "optim=adam"]
    result = measure_seeds(small, 2, repeats=2, min_seconds=0)
    assert result["seeds"] == 2 and result["single_step_s"] > 0 and result["step_s"] > 0
    gain = 2 * result["single_step_s"] / result["step_s"]
    assert f"| {gain:.2f}x |" in seeds_table([{"task": "poisson", "variant": "adam", **result}])
