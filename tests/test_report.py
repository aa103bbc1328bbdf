"""physgrad report on hand-made results files: grouping by setting, thresholds, time to reach, the band."""

import math

import numpy as np
import yaml

from physgrad.plots import median_band
from physgrad.report import collect, label_settings, table_rows, write_report
from physgrad.results import ResultsWriter


def fake_run(folder, variant, seed, poles, eval_loss, eval_time, status="completed"):
    config = yaml.safe_dump({"seed": seed, "precision": 32, "unroll": None,
                             "task": {"name": "multicart", "poles": poles, "batch_size": 8}})
    writer = ResultsWriter(folder / "results.h5", {"task": "multicart", "optim": variant, "variant": variant,
                                                   "seed": seed, "config": config})
    for i, t in enumerate(eval_time):
        writer.append("train", {"iteration": i, "wall_time": t + 0.5, "loss": eval_loss[i], "grad_norm": 1.0})
        writer.append("eval", {"iteration": i, "wall_time": t, "loss": eval_loss[i]})
    writer.finish(status, None if status == "completed" else "loss became nan at iteration 2")


def test_report_groups_by_setting_and_times_the_threshold(tmp_path):
    fake_run(tmp_path / "a", "bptt", 0, 1, [1.0, 0.1, 0.01], [0.0, 1.0, 2.0])
    fake_run(tmp_path / "b", "stable_bptt", 0, 1, [1.0, 0.5, 0.05], [0.0, 2.0, 4.0])
    fake_run(tmp_path / "c", "bptt", 0, 2, [1.0, 0.9, 0.8], [0.0, 1.0, 2.0])
    fake_run(tmp_path / "d", "bptt", 1, 2, [1.0, 0.7, 0.6], [0.0, 1.0, 2.0], status="diverged")
    runs, unreadable = collect([tmp_path])
    assert len(runs) == 4 and not unreadable
    label_settings(runs)
    assert sorted({run.scene for run in runs}) == ["multicart poles=1", "multicart poles=2"]
    rows = {(r["setting"], r["variant"], r["seed"]): r for r in table_rows(runs)}
    # threshold per scene: the worst final test loss (0.05 for poles=1, 0.8 for poles=2)
    assert rows[("poles=1", "bptt", 0)]["t(thr) s"] == 2.0
    assert rows[("poles=1", "stable_bptt", 0)]["t(thr) s"] == 4.0
    assert rows[("poles=2", "bptt", 1)]["t(thr) s"] == 1.0
    assert rows[("poles=2", "bptt", 1)]["status"] == "diverged"
    assert rows[("poles=1", "bptt", 0)]["s/iter"] == 1.0  # median of the step times 0.5, 1, 1
    fixed = {(r["setting"], r["variant"], r["seed"]): r for r in table_rows(runs, threshold=0.1)}
    assert fixed[("poles=1", "bptt", 0)]["t(thr) s"] == 1.0 and math.isnan(fixed[("poles=2", "bptt", 0)]["t(thr) s"])
    text = write_report([tmp_path])
    assert "| multicart | poles=1 | bptt | 0 | completed |" in text
    assert (tmp_path / "loss_vs_time.png").stat().st_size > 1000


def test_unreadable_files_are_listed_not_fatal(tmp_path):
    fake_run(tmp_path / "ok", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "results.h5").write_bytes(b"garbage")
    text = write_report([tmp_path])
    assert "1 runs under" in text and "unreadable:" in text and "bad/results.h5" in text


def test_median_band_interpolates_in_log_loss():
    curves = [(np.array([0.0, 2.0]), np.array([1.0, 1e-2])), (np.array([0.0, 4.0]), np.array([1.0, 1e-8]))]
    grid, median, low, high = median_band(curves, points=3)
    np.testing.assert_allclose(grid, [0.0, 1.0, 2.0])  # up to the shortest curve's end
    np.testing.assert_allclose(low, [1.0, 1e-2, 1e-4])
    np.testing.assert_allclose(high, [1.0, 1e-1, 1e-2])
    np.testing.assert_allclose(median, np.sqrt(low * high))


def test_report_draws_the_tradeoff_and_unroll_figures(tmp_path):
    for unroll in (16, 32, 64):
        for variant, scale in (("bptt", 1.0), ("stable_bptt", 0.5)):
            folder = tmp_path / f"{variant}_{unroll}"
            config = yaml.safe_dump({"seed": 0, "precision": 32, "unroll": unroll,
                                     "task": {"name": "multicart", "poles": 2, "batch_size": 8}})
            writer = ResultsWriter(folder / "results.h5", {"task": "multicart", "optim": variant, "variant": variant,
                                                           "seed": 0, "config": config, "unroll": unroll})
            for i in range(3):
                writer.append("train", {"iteration": i, "wall_time": (i + 1) * unroll * 1e-3, "loss": 1.0,
                                        "grad_norm": 1.0})
                writer.append("eval", {"iteration": i, "wall_time": i * unroll * 1e-3, "loss": scale / (i + 1)})
            writer.finish("completed")
    text = write_report([tmp_path])
    for name in ("loss_vs_time.png", "loss_vs_iteration.png", "tradeoff.png", "unroll.png"):
        assert (tmp_path / name).stat().st_size > 1000 and name in text
    # six problems (one per unroll length) in the table, one unroll figure across them
    runs, _ = collect([tmp_path])
    label_settings(runs)
    assert sorted({run.scene for run in runs}) == [f"multicart unroll={u}" for u in (16, 32, 64)]


def test_report_without_an_unroll_axis_draws_no_unroll_figure(tmp_path):
    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    text = write_report([tmp_path])
    assert not (tmp_path / "unroll.png").exists() and "unroll.png" not in text
    assert (tmp_path / "tradeoff.png").stat().st_size > 1000


def test_threshold_comes_from_completed_runs_only(tmp_path):
    fake_run(tmp_path / "ok", "hig", 0, 1, [1.0, 0.1], [0.0, 1.0])
    fake_run(tmp_path / "bad", "gauss_newton", 0, 1, [0.9], [0.0], status="diverged")
    runs, _ = collect([tmp_path])
    label_settings(runs)
    from physgrad.report import thresholds

    assert thresholds(runs) == {"multicart": 0.1}
