"""Integration layer of `physgrad report` on hand-made results files: groups and thresholds,
duplicates and labelled sets, unreadable or vanishing files listed, CSV and Parquet export, the
figures' medians, styles, notes and axes, and folders from someone else walked without links."""

import csv
import math
from pathlib import Path

import matplotlib.colors
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest
import yaml

from physgrad.report import write_report
from physgrad.report_figures import median_band
from physgrad.results import ResultsWriter, read_run
from physgrad.runs import collect, label_runs
from tests.unit.test_report import (
    fake_run,
    label_settings,
    table_rows,
)


def test_report_groups_by_setting_and_times_the_threshold(tmp_path):
    fake_run(tmp_path / "a", "bptt", 0, 1, [1.0, 0.1, 0.01], [0.0, 1.0, 2.0])
    fake_run(tmp_path / "b", "stable_bptt", 0, 1, [1.0, 0.5, 0.05], [0.0, 2.0, 4.0])
    fake_run(tmp_path / "c", "bptt", 0, 2, [1.0, 0.9, 0.8], [0.0, 1.0, 2.0])
    fake_run(tmp_path / "d", "bptt", 1, 2, [1.0, 0.7, 0.6], [0.0, 1.0, 2.0], status="diverged")
    runs, unreadable, _ = collect([tmp_path])
    assert len(runs) == 4 and not unreadable
    label_settings(runs)
    assert sorted({run.scene for run in runs}) == ["multicart poles=1", "multicart poles=2"]
    rows = {(r["setting"], r["variant"], r["seed"]): r for r in table_rows(runs)}
    assert len(rows) == 4
    # threshold per scene: the best group's median final test loss (poles=1: bptt's 0.01, which
    # stable_bptt never reaches; poles=2: bptt's seeds end at 0.8 and diverged, a median of
    # infinity: no target)
    assert rows[("poles=1", "bptt", 0)]["t(thr) s"] == 2.0
    # never reached: infinite time (readout)
    assert math.isinf(rows[("poles=1", "stable_bptt", 0)]["t(thr) s"])
    assert math.isnan(rows[("poles=2", "bptt", 1)]["t(thr) s"]) and math.isnan(
        rows[("poles=2", "bptt", 0)]["t(thr) s"]
    )
    assert rows[("poles=2", "bptt", 1)]["status"] == "diverged"
    assert rows[("poles=1", "bptt", 0)]["s/iter"] == 1.0  # median of the step times 0.5, 1, 1
    fixed = {(r["setting"], r["variant"], r["seed"]): r for r in table_rows(runs, threshold=0.1)}
    assert fixed[("poles=1", "bptt", 0)]["t(thr) s"] == 1.0 and math.isinf(
        fixed[("poles=2", "bptt", 0)]["t(thr) s"]
    )
    text = write_report([tmp_path])
    assert "| multicart poles=1 | bptt | 0 | completed |  | 3 | 0.01 |" in text
    # the completed seed only
    assert "| multicart poles=2 | bptt | 2 | 1 completed, 1 diverged | 0.8 |" in text
    assert (tmp_path / "loss_vs_time.png").stat().st_size > 1000 and (
        tmp_path / "loss_vs_time.pdf"
    ).exists()


def test_unreadable_files_are_listed_not_fatal(tmp_path, report_figures_skipped):
    fake_run(tmp_path / "ok", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "results.h5").write_bytes(b"garbage")
    text = write_report([tmp_path])
    assert "1 runs under" in text and "unreadable:" in text and "bad/results.h5" in text


def test_a_results_file_that_vanishes_while_the_report_reads_is_listed_not_fatal(
    tmp_path, monkeypatch, report_figures_skipped
):
    """A sweep still being written or cleaned up: a results file listed, then gone (or made
    unreadable) before it is opened, at each of the runs in turn, is a line of the report's
    unreadable files; the other runs are reported."""
    import physgrad.runs

    for seed in range(3):
        fake_run(tmp_path / f"s{seed}", "adam", seed, 1, [1.0, 0.5], [0.0, 1.0])
    real = physgrad.runs.read_run
    for gone in range(3):
        victim = tmp_path / f"s{gone}" / "results.h5"
        kept = victim.read_bytes()

        def vanishing(path, victim=victim, **options):
            if Path(path) == victim:
                victim.unlink()
            return real(path, **options)

        monkeypatch.setattr(physgrad.runs, "read_run", vanishing)
        text = write_report([tmp_path])
        assert "2 runs under" in text and f"s{gone}/results.h5" in text.split("unreadable:")[1]
        victim.write_bytes(kept)

        # gone just after it was read: what was read is reported
        def read_then_vanish(path, victim=victim, **options):
            run = real(path, **options)
            if Path(path) == victim:
                victim.unlink()
            return run

        monkeypatch.setattr(physgrad.runs, "read_run", read_then_vanish)
        assert "3 runs under" in write_report([tmp_path])
        victim.write_bytes(kept)


def test_median_band_interpolates_in_log_loss():
    curves = [
        (np.array([0.0, 2.0]), np.array([1.0, 1e-2])),
        (np.array([0.0, 4.0]), np.array([1.0, 1e-8])),
    ]
    # log-linear between 1 and 4
    curves[1] = (
        np.array([0.0, 1.0, 4.0]),
        np.array([1.0, 1e-2, 1e-8]),
    )
    grid, median, low, high = median_band(curves)
    # every evaluation up to the shortest curve's end
    np.testing.assert_allclose(grid, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(low, [1.0, 1e-2, 1e-4])
    np.testing.assert_allclose(high, [1.0, 1e-1, 1e-2])
    # the median of two losses, as the tables take it
    np.testing.assert_allclose(median, (low + high) / 2)


def test_report_draws_the_tradeoff_and_unroll_figures(tmp_path):
    for unroll in (16, 32, 64):
        for variant, scale in (("bptt", 1.0), ("stable_bptt", 0.5)):
            folder = tmp_path / f"{variant}_{unroll}"
            config = yaml.safe_dump(
                {
                    "seed": 0,
                    "precision": 32,
                    "unroll": unroll,
                    "task": {"name": "multicart", "poles": 2, "batch_size": 8},
                }
            )
            writer = ResultsWriter(
                folder / "results.h5",
                {
                    "task": "multicart",
                    "optim": variant,
                    "variant": variant,
                    "seed": 0,
                    "config": config,
                    "unroll": unroll,
                },
            )
            for i in range(3):
                writer.append(
                    "train",
                    {
                        "iteration": i,
                        "wall_time": (i + 1) * unroll * 1e-3,
                        "loss": 1.0,
                        "grad_norm": 1.0,
                    },
                )
                writer.append(
                    "eval",
                    {"iteration": i, "wall_time": i * unroll * 1e-3, "loss": scale / (i + 1)},
                )
            writer.finish("completed")
    text = write_report([tmp_path])
    for name in ("loss_vs_time", "loss_vs_iteration", "tradeoff", "unroll"):
        assert (tmp_path / f"{name}.png").stat().st_size > 1000 and f"{name}.png" in text
        assert (tmp_path / f"{name}.pdf").read_bytes().startswith(b"%PDF")
    # six problems (one per unroll length) in the table, one unroll figure across them
    runs, _, _ = collect([tmp_path])
    label_settings(runs)
    assert sorted({run.scene for run in runs}) == [f"multicart unroll={u}" for u in (16, 32, 64)]


def test_report_without_an_unroll_axis_draws_no_unroll_figure(tmp_path):
    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    text = write_report([tmp_path])
    assert not (tmp_path / "unroll.png").exists() and "unroll.png" not in text
    assert (tmp_path / "tradeoff.png").stat().st_size > 1000


def test_a_learning_rate_sweep_is_two_groups_named_by_what_differs(
    tmp_path, report_figures_skipped
):
    for lr, losses in ((1e-3, ([1.0, 0.5], [1.0, 0.4])), (1e-2, ([1.0, 0.1], [1.0, 0.2]))):
        for seed, loss in enumerate(losses):
            # a setting that does not change the computation
            fake_run(
                tmp_path / f"lr{lr}_s{seed}",
                "adam",
                seed,
                1,
                loss,
                [0.0, 1.0],
                optim={"learning_rate": lr},
                trainer={"flush_seconds": 1.0 + seed},
            )
    fake_run(tmp_path / "hig", "hig", 0, 1, [1.0, 0.3], [0.0, 2.0], optim={"learning_rate": 1.0})
    for index, lr in enumerate(
        (0.0044303752, 0.0044312345)
    ):  # close values (an Optuna study's) stay apart
        fake_run(
            tmp_path / f"gd{index}", "gd", 0, 1, [1.0, 0.9], [0.0, 1.0], optim={"learning_rate": lr}
        )
    runs, _, dropped = collect([tmp_path])
    label_runs(runs)
    assert not dropped
    assert sorted({run.label for run in runs}) == [
        "adam learning_rate=0.001",
        "adam learning_rate=0.01",
        "gd learning_rate=0.00443038",
        "gd learning_rate=0.00443123",
        "hig",
    ]
    assert {run.scene for run in runs} == {"multicart"}
    text = write_report([tmp_path])
    assert "| multicart | adam learning_rate=0.001 | 2 | 2 completed | 0.45 [0.4, 0.5] |" in text
    assert "| multicart | adam learning_rate=0.01 | 2 | 2 completed | 0.15 [0.1, 0.2] |" in text
    assert "| multicart | hig | 1 | 1 completed | 0.3 |" in text


def test_the_same_run_found_twice_or_rerun_counts_once(tmp_path, report_figures_skipped):
    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    fake_run(tmp_path / "b", "adam", 1, 1, [1.0, 0.4], [0.0, 1.0])
    # a cadence does not make it another run
    fake_run(
        tmp_path / "again",
        "adam",
        0,
        1,
        [1.0, 0.3],
        [0.0, 1.0],
        status="interrupted",
        trainer={"eval_every": 7},
    )
    runs, _, dropped = collect([tmp_path, tmp_path / "a", tmp_path / "a" / "results.h5"])
    # the completed one of the two seed-0 runs
    assert sorted(run.path.parent.name for run in runs) == [
        "a",
        "b",
    ]
    assert [(d.path.parent.name, d.kept.parent.name) for d in dropped] == [
        ("a", "a"),
        ("again", "a"),
    ]
    assert dropped[0].why == "the same file, found twice"
    text = write_report([tmp_path, tmp_path / "b"])
    assert f"counted once: {tmp_path / 'b' / 'results.h5'}: the same file, found twice" in text
    assert (
        f"dropped {tmp_path / 'again' / 'results.h5'}: same configuration and seed as "
        f"{tmp_path / 'a'}" in text
    )
    assert "| multicart | adam | 2 | 2 completed |" in text


def test_labelled_sets_are_kept_apart(tmp_path, report_figures_skipped):
    fake_run(tmp_path / "monday" / "x", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    fake_run(tmp_path / "friday" / "x", "adam", 0, 1, [1.0, 0.2], [0.0, 1.0])
    text = write_report(
        [f"old={tmp_path / 'monday'}", f"new={tmp_path / 'friday'}"], out_dir=tmp_path / "out"
    )
    assert "| multicart | old: adam | 1 | 1 completed | 0.5 |" in text
    assert "| multicart | new: adam | 1 | 1 completed | 0.2 |" in text
    rows = list(csv.DictReader(open(tmp_path / "out" / "runs.csv")))
    assert sorted((r["set"], r["label"]) for r in rows) == [
        ("new", "new: adam"),
        ("old", "old: adam"),
    ]


def test_scene_metrics_and_csv_export(tmp_path, report_figures_skipped):
    fake_run(
        tmp_path / "a",
        "bptt",
        0,
        2,
        [1.0, 0.5, 0.25],
        [0.0, 1.0, 2.0],
        metrics={"upright": [0.0, 0.5, 1.0]},
    )
    fake_run(tmp_path / "b", "bptt", 1, 2, [1.0, 0.6], [0.0, 1.0], metrics={"upright": [0.0, 0.25]})
    text = write_report([tmp_path])
    # median of 1 and 0.25
    assert "| upright |" in text.splitlines()[2] and "| 0.625 [0.25, 1] |" in text
    rows = list(csv.DictReader(open(tmp_path / "runs.csv")))
    assert len(rows) == 2 and {
        "path",
        "label",
        "setting",
        "seed",
        "status",
        "stopped_by",
        "iterations",
        "train_seconds",
        "test_loss_at_1",
        "loss_at_common_time",
        "target",
        "time_to_target",
        "upright",
    } <= set(rows[0])
    assert sorted(float(r["upright"]) for r in rows) == [0.25, 1.0]
    curves = list(csv.DictReader(open(tmp_path / "curves.csv")))
    assert {
        "run",
        "split",
        "iteration",
        "wall_time",
        "loss",
        "grad_norm",
        "upright",
        "label",
        "variant",
        "seed",
        "scene",
    } <= set(curves[0])
    # one row per run, split and iteration: 3 + 2 training rows, 3 + 2 evaluations
    assert len(curves) == 10
    a = next(r["run"] for r in rows if r["path"].endswith("a/results.h5"))
    eval_a = [c for c in curves if c["run"] == a and c["split"] == "eval"]
    assert [(int(c["iteration"]), float(c["wall_time"]), float(c["upright"])) for c in eval_a] == [
        (0, 0.0, 0.0),
        (1, 1.0, 0.5),
        (2, 2.0, 1.0),
    ]
    assert pd.read_parquet(tmp_path / "curves.parquet").shape[0] == 10


def test_read_runs_gives_every_setting_a_column_and_curves_that_plot_without_a_merge(tmp_path):
    """An Optuna-like set of learning rates: each run's rate is a number in optim.learning_rate (not
    only in its label), the curves carry label, variant and seed, and the CSV and Parquet files hold
    the same columns."""
    import physgrad

    rates = (0.00725701, 0.0311, 0.1)
    for i, lr in enumerate(rates):
        fake_run(
            tmp_path / f"t{i}",
            "adam",
            0,
            2,
            [1.0, 0.5 - 0.1 * i],
            [0.0, 1.0],
            optim={"learning_rate": lr},
        )
    fake_run(
        tmp_path / "hig",
        "hig",
        0,
        2,
        [1.0, 0.05],
        [0.0, 2.0],
        optim={"learning_rate": 1.0, "backprop": "C"},
    )
    runs, curves = physgrad.read_runs([tmp_path])
    # one path alone, as a string or a Path, is that path, not a list of its characters
    for alone in (str(tmp_path), tmp_path):
        assert physgrad.read_runs(alone).runs.equals(runs)
    assert sorted(runs.loc[runs["variant"] == "adam", "optim.learning_rate"]) == list(rates)
    assert {
        "task.poles",
        "trainer.iterations",
        "optim.backprop",
        "seed",
        "status",
        "stopped_by",
        "unroll",
        "machine",
        "run",
    } <= set(runs.columns)
    assert runs["task.poles"].tolist() == [2] * 4 and runs["run"].tolist() == list(range(4))
    evaluations = curves[curves["split"] == "eval"]
    assert set(evaluations.groupby("label").size()) == {2} and evaluations["label"].nunique() == 4
    merged = evaluations.merge(runs[["run", "optim.learning_rate"]], on="run")
    assert merged.groupby("run")["optim.learning_rate"].nunique().eq(1).all()
    write_report([tmp_path])
    on_disk = pd.read_csv(tmp_path / "runs.csv")
    assert (
        list(on_disk.columns)
        == list(runs.columns)
        == list(pd.read_parquet(tmp_path / "runs.parquet").columns)
    )
    assert sorted(on_disk["optim.learning_rate"].dropna()) == sorted([*rates, 1.0])


def test_long_runs_are_thinned_in_csv_and_whole_in_parquet(tmp_path, report_figures_skipped):
    from physgrad.tables import CSV_TRAIN_ROWS

    count = 3 * CSV_TRAIN_ROWS + 7
    fake_run(
        tmp_path / "long",
        "adam",
        0,
        1,
        np.linspace(1, 0.1, count).tolist(),
        np.arange(count).tolist(),
    )
    write_report([tmp_path])
    train = pd.read_csv(tmp_path / "curves.csv").query("split == 'train'")
    assert CSV_TRAIN_ROWS // 2 <= len(train) <= CSV_TRAIN_ROWS + 1
    assert train["iteration"].iloc[0] == 0 and train["iteration"].iloc[-1] == count - 1
    assert len(pd.read_parquet(tmp_path / "curves.parquet").query("split == 'train'")) == count


def test_notes_of_runs_that_diverged_at_the_same_point_do_not_overprint(tmp_path, monkeypatch):
    from matplotlib.axes import Axes

    from physgrad.report_figures import plot_comparison

    for seed in (0, 1, 2):
        fake_run(
            tmp_path / f"gn{seed}",
            "gauss_newton",
            seed,
            1,
            [1.0, 2.0],
            [0.0, 0.1],
            status="diverged",
        )
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    calls, annotate = [], Axes.annotate
    monkeypatch.setattr(
        Axes,
        "annotate",
        lambda self, text, xy, **kw: (
            calls.append((text, kw["xytext"])) or annotate(self, text, xy, **kw)
        ),
    )
    plot_comparison(runs, tmp_path / "loss.png")
    numbers = [(text, offset) for text, offset in calls if text.isdigit()]
    assert sorted(text for text, _ in numbers) == ["1", "2", "3"]
    assert len({offset for _, offset in numbers}) == 3  # stacked, not overprinted
    (notes,) = [text for text, _ in calls if not text.isdigit()]
    assert notes.startswith("diverged:") and notes.count("\n") == 3


@pytest.fixture
def figures(monkeypatch):
    """Every figure a report saves, kept open: {file stem: Figure}."""
    import physgrad.plots

    saved = {}
    real = physgrad.plots.write_figure

    def keep(fig, path, *args, **kwargs):
        saved[Path(path).stem] = fig
        return real(fig, path, *args, **kwargs)

    monkeypatch.setattr(physgrad.plots, "write_figure", keep)
    monkeypatch.setattr(plt, "close", lambda fig=None: None)
    yield saved
    plt.close("all")


def line_colors(fig) -> dict:
    """legend label (without the counts) -> colour of its line or markers, over every panel of a
    figure."""
    found = {}
    for ax in fig.axes:
        for line in ax.get_lines():
            label = line.get_label()
            if not label.startswith("_"):
                found[label.split(" (")[0]] = matplotlib.colors.to_hex(line.get_color())
    return found


def test_every_group_keeps_its_style_in_every_figure_and_twelve_groups_stay_apart(
    tmp_path, figures
):
    from physgrad.plots import group_styles

    labels = [f"v{i:02d}" for i in range(12)]
    for i, label in enumerate(labels):
        for seed in range(2):
            fake_run(
                tmp_path / f"{label}_{seed}",
                label,
                seed,
                1,
                [1.0, 0.5 / (i + 1), 0.1 / (i + 1)],
                [0.0, 1.0 + i, 2.0 + i],
            )
    write_report([tmp_path], out_dir=tmp_path / "out")
    colors = {
        name: line_colors(figures[name])
        for name in ("loss_vs_time", "loss_vs_iteration", "tradeoff")
    }
    assert colors["loss_vs_time"] == colors["loss_vs_iteration"] == colors["tradeoff"]
    assert set(colors["loss_vs_time"]) == set(labels)
    styles = group_styles(labels)
    assert len({(s["color"], s["linestyle"], s["marker"]) for s in styles.values()}) == 12
    assert styles == group_styles(reversed(labels))  # the order runs are found in does not matter
    fig = figures["loss_vs_time"]
    ax = fig.axes[0]
    fig.canvas.draw()
    legend = ax.get_legend().get_window_extent()
    assert legend.x0 >= ax.get_window_extent().x1  # beside the data, not on it


@pytest.mark.parametrize("groups", [9, pytest.param(20, marks=pytest.mark.long)])
def test_many_groups_with_diverged_runs_keep_notes_legend_and_ticks_apart(
    tmp_path, figures, groups
):
    """9 and 20 groups, a third of them with a diverged seed: the divergence notes sit under the
    axes (below the tick labels and the axis label), the legend beside them, nothing drawn over
    another; every diverged run is numbered."""
    for g in range(groups):
        for seed in range(2):
            diverged = g % 3 == 0 and seed == 0
            fake_run(
                tmp_path / f"v{g}s{seed}",
                f"variant_{g}",
                seed,
                1,
                [1.0, 0.5 / (g + 1), 0.1 / (g + 1)],
                [0.0, 1.0, 2.0],
                status="diverged" if diverged else "completed",
            )
    write_report([tmp_path], out_dir=tmp_path / "out")
    for name in ("loss_vs_time", "loss_vs_iteration"):
        fig = figures[name]
        ax = fig.axes[0]
        fig.canvas.draw()  # the tick labels placed as saved
        renderer = fig.canvas.get_renderer()
        notes = [t for t in ax.texts if t.get_text().startswith("diverged:")]
        assert len(notes) == 1 and notes[0].get_text().count("\n") == len(range(0, groups, 3))
        below = notes[0].get_window_extent(renderer)
        axis_parts = [ax.xaxis.label, *(t for t in ax.get_xticklabels() if t.get_text())]
        assert all(below.y1 <= part.get_window_extent(renderer).y0 + 0.5 for part in axis_parts)
        legend = ax.get_legend().get_window_extent(renderer)
        assert legend.x0 >= ax.get_window_extent(renderer).x1 and not legend.overlaps(below)
        numbers = sorted(int(t.get_text()) for t in ax.texts if t.get_text().isdigit())
        assert numbers == list(range(1, len(range(0, groups, 3)) + 1))


def test_a_diverged_run_does_not_stretch_the_axis(tmp_path, figures):
    fake_run(tmp_path / "ok", "adam", 0, 1, [1.0, 0.1, 0.01], [0.0, 1.0, 2.0])
    fake_run(
        tmp_path / "bad", "gauss_newton", 0, 1, [1.0, 1e5, 1e33], [0.0, 1.0, 2.0], status="diverged"
    )
    write_report([tmp_path], out_dir=tmp_path / "out")
    for name in ("loss_vs_time", "loss_vs_iteration"):
        low, high = figures[name].axes[0].get_ylim()
        assert 1.0 <= high <= 10.0 and low <= 0.01
        texts = [t.get_text() for t in figures[name].axes[0].texts]
        assert any("loss 1e+33" in text for text in texts)  # said where it went instead


def test_the_drawn_median_is_the_one_the_table_reports(tmp_path, figures):
    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5, 0.02], [0.0, 1.0, 2.0])
    fake_run(tmp_path / "b", "adam", 1, 1, [1.0, 0.5, 3.3], [0.0, 1.0, 2.0])
    text = write_report([tmp_path], out_dir=tmp_path / "out")
    assert "| 1.66 [0.02, 3.3] |" in text
    (line,) = [
        drawn
        for drawn in figures["loss_vs_iteration"].axes[0].get_lines()
        if drawn.get_label().startswith("adam")
    ]
    assert line.get_ydata()[-1] == pytest.approx(1.66)


def test_the_unroll_axis_has_a_tick_at_every_length(tmp_path, figures):
    from physgrad.cost_figures import plot_unroll

    for unroll in (4, 16, 64, 256):
        fake_run(
            tmp_path / f"u{unroll}",
            "bptt",
            0,
            1,
            [1.0, 1.0 / unroll],
            [0.0, 1.0],
            attrs={"unroll": unroll},
            trainer={"iterations": unroll},
        )
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    assert plot_unroll(runs, tmp_path / "unroll")
    for ax in figures["unroll"].axes:
        if ax.get_visible():
            assert list(ax.get_xticks()) == [4, 16, 64, 256]
            ax.figure.canvas.draw()
            assert [t.get_text() for t in ax.get_xticklabels()] == ["4", "16", "64", "256"]


def test_the_run_figure_draws_the_rule_s_diagnostics_and_wide_metrics_on_a_log_axis(
    tmp_path, figures
):
    from physgrad.plots import plot_run

    writer = ResultsWriter(tmp_path / "results.h5", {"task": "toy", "optim": "hig", "seed": 0})
    for i in range(5):
        writer.append(
            "train",
            {
                "iteration": i,
                "wall_time": 0.1 * i,
                "loss": 1.0 / (i + 1),
                "grad_norm": 1.0,
                "update_norm": 0.5,
                "kept_singular_values": 10 + i,
                "svd_failures": 0,
            },
        )
        writer.append(
            "eval",
            {
                "iteration": i,
                "wall_time": 0.1 * i,
                "loss": 1.0 / (i + 1),
                "energy": 10.0 ** (-3 * i),
            },
        )
    writer.finish("completed")
    plot_run(read_run(tmp_path / "results.h5"), tmp_path / "loss.png")
    axes = {ax.get_ylabel(): ax for ax in figures["loss"].axes}
    assert {drawn.get_label() for drawn in axes["update rule diagnostic"].get_lines()} == {
        "kept_singular_values",
        "svd_failures",
    }
    assert axes["test metric"].get_yscale() == "log"


def test_a_report_replaces_a_figure_that_is_a_link_and_never_writes_through_it(tmp_path):
    """A folder from someone else with its figure names linked to a file elsewhere: the report's
    figures replace the links; the file they pointed at is untouched."""
    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    fake_run(tmp_path / "b", "hig", 0, 1, [1.0, 0.2], [0.0, 2.0])
    outside = tmp_path.parent / f"{tmp_path.name}-outside"
    outside.write_bytes(b"theirs")
    for name in ("loss_vs_time.png", "loss_vs_time.pdf", "loss_vs_iteration.png"):
        (tmp_path / name).symlink_to(outside)
    write_report([tmp_path])
    assert outside.read_bytes() == b"theirs"
    for name in ("loss_vs_time.png", "loss_vs_time.pdf", "loss_vs_iteration.png"):
        assert not (tmp_path / name).is_symlink() and (tmp_path / name).stat().st_size > 1000


def test_a_folder_from_someone_else_is_walked_without_following_links_or_recursing(tmp_path):
    """Under a folder: a results.h5 that is a link (to another run, to a file outside) is listed as
    not followed; a link to a folder (here a loop back to the top) is not entered; a run 1,500
    folders deep is found (no recursion limit)."""
    import physgrad
    from physgrad.runs import collect

    fake_run(tmp_path / "a", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    outside = tmp_path.parent / f"{tmp_path.name}-elsewhere"
    fake_run(outside, "hig", 0, 1, [1.0, 0.2], [0.0, 1.0])
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "results.h5").symlink_to(outside / "results.h5")
    (tmp_path / "loop").symlink_to(tmp_path)
    levels = [tmp_path / "deep"]
    for _ in range(1500):  # one level at a time: pathlib's mkdir(parents=True) recurses
        levels.append(levels[-1] / "d")
    try:
        for level in levels:
            level.mkdir()
        fake_run(levels[-1], "gd", 0, 1, [1.0, 0.7], [0.0, 1.0])
        runs, unreadable, _ = collect([tmp_path])
    finally:  # shutil.rmtree, which pytest cleans up with, recurses: take the tree down here
        for level in reversed(levels):
            if level.is_dir():
                for entry in level.iterdir():
                    if not entry.is_dir():
                        entry.unlink()
                level.rmdir()
    assert sorted(r.variant for r in runs) == ["adam", "gd"]
    assert [(p.parent.name, "a link: refused" in why) for p, why in unreadable] == [("b", True)]
    # the file itself, named by the user, is read
    assert physgrad.read_runs(tmp_path / "b" / "results.h5").runs["variant"].tolist() == ["hig"]


def test_read_runs_says_which_files_it_left_out_and_why(tmp_path):
    """An unreadable results file beside a good one: the good run comes back, and one warning
    names the file left out and the reason."""
    import physgrad
    from physgrad.experiment import run_experiment
    from tests.helpers import load

    run_experiment(load("task=toy", "trainer.iterations=3"), tmp_path / "good")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "results.h5").write_bytes(b"not an HDF5 file" * 8)
    with pytest.warns(UserWarning, match=r"1 results file left out.*bad/results\.h5") as caught:
        tables = physgrad.read_runs(tmp_path)
    assert len(tables.runs) == 1 and "\n" not in str(caught[0].message)
