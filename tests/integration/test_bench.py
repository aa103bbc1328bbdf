"""make bench on tiny problems: every number the table needs is measured, nothing is asserted about
speed."""

import math

import pytest

from physgrad.bench_measure import (
    _median_times,
    measure_floors,
    measure_seeds,
    measure_variant,
)
from physgrad.bench_tables import floor_seconds, jacobian_table, seeds_table, table


@pytest.mark.long
def test_bench_measures_steps_floors_and_overhead():
    small = ["task=poisson", "task.grid=4", "task.test_size=8", "trainer.batch_size=4"]
    hig = measure_variant([*small, "optim=hig"], repeats=2, min_seconds=0)
    adam = measure_variant([*small, "optim=adam"], repeats=2, min_seconds=0)
    assert hig["jac_shape"] == [
        4 * 16,
        1 * 16 * 16 + 16 + 16 * 32 + 32 + 32 * 16 + 16 + 16 * 16 + 16,
    ]
    assert hig["route"] == "gram" and hig["jacobian"] == "layer-factorised"
    assert (
        hig["step_s"] > 0
        and hig["per_sample_step_s"] > 0
        and hig["loss_grad_s"] > 0
        and hig["eigh_s"] > 0
    )
    assert hig["per_sample_peak_rss_gb"] >= hig["peak_rss_gb"] > 0
    assert (
        adam["loss_grad_s"] > 0 and 0 <= adam["runner_overhead"] < 1 and 0 < adam["eval_share"] < 1
    )
    floors = measure_floors(hig["jac_shape"][0], repeats=2)
    assert {"eigh_numpy_s", "eigh_scipy_evr_s", "eigh_scipy_evd_s", "eigh_jax_s"} == set(floors)
    assert all(seconds > 0 for seconds in floors.values())
    rows = [
        {"task": "poisson", "variant": "hig", "precision": 32, **hig, "floors": floors},
        {"task": "poisson", "variant": "adam", "precision": 32, **adam},
    ]
    assert f"| {adam['step_s'] / adam['loss_grad_s']:.2f} |" in table(rows)
    text = jacobian_table(rows)
    fastest = min(floors.values())
    ratio = hig["step_s"] / (hig["eigh_s"] * fastest / floors["eigh_jax_s"] + hig["loss_grad_s"])
    speed_up = hig["per_sample_step_s"] / hig["step_s"]
    assert floor_seconds(rows[0]) > hig["loss_grad_s"] and f"| {ratio:.2f} |" in text
    assert f"| {speed_up:.2f}x |" in text and "| adam |" not in text
    assert math.isfinite(ratio)


@pytest.mark.long
def test_kfac_is_measured_from_its_factors_without_a_per_sample_baseline():
    """K-FAC takes the Jacobian in layer factors: no route through J and no per-sample Jacobian to
    compare with (that baseline would refuse it), its step and floors measured as any other."""
    small = ["task=poisson", "task.grid=4", "task.test_size=8", "trainer.batch_size=4"]
    kfac = measure_variant([*small, "optim=kfac"], repeats=2, min_seconds=0)
    assert kfac["route"] == "factors" and "per_sample_step_s" not in kfac
    assert kfac["step_s"] > 0 and kfac["eigh_s"] > 0


def test_a_refused_variant_gives_its_reason():
    assert "refused" in measure_variant(["task=poisson", "optim=bptt"], repeats=1, min_seconds=0)


def test_timings_are_taken_in_turn_with_their_baseline():
    calls = []
    medians = _median_times(
        [lambda: calls.append("step"), lambda: calls.append("bare")], repeats=3, min_seconds=0
    )
    assert calls == ["step", "bare"] * 4  # one warm-up call each, then rounds of one call each
    assert [count for _, count in medians] == [3, 3]


@pytest.mark.long
def test_seeds_are_timed_against_one_seed_in_the_same_process():
    small = [
        "task=poisson",
        "task.grid=4",
        "task.test_size=8",
        "trainer.batch_size=4",
        "optim=adam",
    ]
    result = measure_seeds(small, 2, repeats=2, min_seconds=0)
    assert result["seeds"] == 2 and result["single_step_s"] > 0 and result["step_s"] > 0
    gain = 2 * result["single_step_s"] / result["step_s"]
    assert f"| {gain:.2f}x |" in seeds_table([{"task": "poisson", "variant": "adam", **result}])


def test_a_bench_cut_short_keeps_every_row_it_finished(tmp_path, monkeypatch):
    """The page is written after every row: a bench stopped in its third measurement (a device
    lent for minutes, a timeout) leaves the first two in the table."""
    from physgrad import bench

    measured = []

    def fake_subprocess(kind, payload, timeout):
        if len(measured) == 2:
            raise KeyboardInterrupt
        measured.append(payload["overrides"])
        return {"step_s": 0.001 * len(measured), "compile_s": 1.0, "peak_rss_gb": 0.1}

    monkeypatch.setattr(bench, "_subprocess", fake_subprocess)
    out = tmp_path / "bench.md"
    with pytest.raises(KeyboardInterrupt):
        bench.main(["--scenes", "poisson", "--out", str(out)])
    text = out.read_text()
    for overrides in measured:
        assert f"| poisson | {overrides[1].removeprefix('optim=')} |" in text
    assert len(measured) == 2


def test_optims_choose_the_rules_and_a_refusal_is_a_row_with_its_reason(
    tmp_path, monkeypatch, capsys
):
    """--optims measures those rules only (the scene's extra variants of them too); a rule the scene
    refuses at its reference size is listed with the reason under the tables, not dropped; an
    unknown rule is one line naming the known ones."""
    from physgrad import bench

    asked = []

    def fake_subprocess(kind, payload, timeout):
        asked.append(payload["overrides"])
        if "optim=ssbfgs" in payload["overrides"]:
            return {"refused": "24896 parameters | more than optim.max_parameters=8192"}
        return {"step_s": 0.001, "compile_s": 1.0, "peak_rss_gb": 0.1}

    monkeypatch.setattr(bench, "_subprocess", fake_subprocess)
    out = tmp_path / "bench.md"
    argv = ["--scenes", "poisson,ks,quantum", "--optims", "adam,ssbfgs", "--out", str(out)]
    assert bench.main([*argv, "--vectorised-seeds", "0"]) == 0  # no seeds table: quantum has one
    optims = {o.removeprefix("optim=") for overrides in asked for o in overrides if "optim=" in o}
    assert optims == {"adam", "ssbfgs"}
    assert "Seeds in one process" not in out.read_text()
    # ks's extra variants are Adam's: measured; poisson's extra is HIG's: not asked for
    assert ["task=ks", "optim=adam", "task.training=ONE"] in asked
    assert not any("precision=64" in overrides for overrides in asked)
    text = out.read_text()
    assert (
        "| poisson | adam | 1 ms |" in text
        and "| poisson | ssbfgs | 24896" not in text.split("Refused at the reference sizes:")[0]
    )
    assert "| poisson | ssbfgs | 24896 parameters / more than optim.max_parameters=8192 |" in text
    capsys.readouterr()
    assert bench.main(["--optims", "adam,sgd", "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("physgrad bench: error: unknown optim sgd: choose from adam, gd,")
    assert "\n" not in error
