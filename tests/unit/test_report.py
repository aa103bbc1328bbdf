"""Unit layer of `physgrad report`: a threshold from completed runs that every run must train to
reach, the loss at a common time on the budgets' clock, bad input in one line, readable axes, and a
compare's groups named, coloured and styled by variant and tuning study."""

import math

import matplotlib.pyplot as plt
import pytest
import yaml

from physgrad.plots import log_axis
from physgrad.readout import loss_at, targets
from physgrad.report import run_rows
from physgrad.report_figures import use_log_x
from physgrad.results import ResultsWriter
from physgrad.runs import collect, label_runs


def fake_run(
    folder,
    variant,
    seed,
    poles,
    eval_loss,
    eval_time,
    status="completed",
    optim=None,
    trainer=None,
    metrics=None,
    attrs=None,
    calibrated=None,
):
    config = yaml.safe_dump(
        {
            "seed": seed,
            "seeds": 1,
            "precision": 32,
            "unroll": None,
            "init_from": None,
            "task": {"name": "multicart", "poles": poles, "batch_size": 8},
            "optim": {"name": variant, **(optim or {})},
            "trainer": {"iterations": 100, "flush_seconds": 1.0, **(trainer or {})},
        }
    )
    writer = ResultsWriter(
        folder / "results.h5",
        {
            "task": "multicart",
            "optim": variant,
            "variant": variant,
            "seed": seed,
            "config": config,
            **(attrs or {}),
        },
    )
    for i, t in enumerate(eval_time):
        writer.append(
            "train",
            {
                "iteration": i,
                "wall_time": t + 0.5,
                "loss": eval_loss[i],
                "grad_norm": 1.0,
                **({"calibrated_time": calibrated[i]} if calibrated else {}),
            },
        )
        writer.append(
            "eval",
            {
                "iteration": i,
                "wall_time": t,
                "loss": eval_loss[i],
                **({"calibrated_time": calibrated[i]} if calibrated else {}),
                **{k: v[i] for k, v in (metrics or {}).items()},
            },
        )
    writer.finish(
        status, None if status == "completed" else "loss became nan at iteration 2 (loss)"
    )


def label_settings(runs):
    label_runs(runs)


def table_rows(runs, threshold=None):
    return [
        {**row, "t(thr) s": row["time_to_target"], "s/iter": row["s_per_iter"]}
        for row in run_rows(runs, threshold)
    ]


def test_threshold_comes_from_completed_runs_only(tmp_path):
    fake_run(tmp_path / "ok", "hig", 0, 1, [1.0, 0.1], [0.0, 1.0])
    fake_run(tmp_path / "bad", "gauss_newton", 0, 1, [0.9], [0.0], status="diverged")
    runs, _, _ = collect([tmp_path])
    label_settings(runs)
    assert targets(runs) == {"multicart": 0.1}


def test_the_threshold_is_one_every_run_must_train_to_reach(tmp_path):
    """A run that ends above where every run began (unstable) must not make the threshold trivial:
    the target is
    the best group's median final loss, reached by training or not at all."""
    for seed in range(3):
        fake_run(
            tmp_path / f"hig{seed}", "hig", seed, 1, [1.0, 0.2, 0.05 + 0.01 * seed], [0.0, 1.0, 2.0]
        )
        fake_run(tmp_path / f"adam{seed}", "adam", seed, 1, [1.0, 0.6, 0.3], [0.0, 1.5, 3.0])
    # ends above its start
    fake_run(tmp_path / "gn", "gauss_newton", 0, 1, [1.0, 5.0, 40.0], [0.0, 0.5, 1.0])
    runs, _, _ = collect([tmp_path])
    label_settings(runs)
    assert targets(runs) == {"multicart": pytest.approx(0.06)}  # hig's median
    rows = {(r["variant"], r["seed"]): r for r in table_rows(runs)}
    assert rows[("hig", 0)]["t(thr) s"] == rows[("hig", 1)]["t(thr) s"] == 2.0 and math.isinf(
        rows[("hig", 2)]["t(thr) s"]
    )
    assert all(math.isinf(rows[("adam", s)]["t(thr) s"]) for s in range(3))
    assert math.isinf(rows[("gauss_newton", 0)]["t(thr) s"])


def test_loss_at_common_time_uses_only_evaluations_before_it(tmp_path):
    fake_run(
        tmp_path / "fast",
        "adam",
        0,
        1,
        [1.0, 0.5, 0.1],
        [0.0, 1.0, 2.0],
        trainer={"time_budget": 2.0},
    )
    fake_run(
        tmp_path / "slow",
        "hig",
        0,
        1,
        [1.0, 0.6, 0.01],
        [0.0, 1.5, 6.0],
        trainer={"time_budget": 6.0},
    )
    fake_run(tmp_path / "bad", "gd", 0, 1, [1.0, 0.9], [0.0, 0.5], status="diverged")
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    rows = {r["variant"]: r for r in run_rows(runs)}
    # the common time is the shortest end of training of the completed runs: fast's 2.5 s (its last
    # train row)
    assert rows["adam"]["common_time"] == rows["hig"]["common_time"] == 2.5
    assert rows["adam"]["loss_at_common_time"] == 0.1 and rows["hig"]["loss_at_common_time"] == 0.6
    # diverged before that time: an infinite loss, as in a verdict
    assert rows["gd"]["loss_at_common_time"] == math.inf
    # the last evaluation at or before the time (the verdict's rule, physgrad.readout): hig's
    # evaluation at 6 s is not read at 5.99 s; a completed run ran to its budget, so its last
    # evaluation is read at any later time
    run = next(r for r in runs if r.variant == "hig")
    assert loss_at(run, 0.0, "wall_time") == 1.0 and loss_at(run, 1.5, "wall_time") == 0.6
    assert loss_at(run, 5.99, "wall_time") == 0.6 and loss_at(run, 6.0, "wall_time") == 0.01
    assert loss_at(run, 60.0, "wall_time") == 0.01 and math.isnan(loss_at(run, -2.0, "wall_time"))
    assert loss_at(run) == 0.01  # at its own budget, trainer.time_budget=6


def test_the_common_time_is_on_the_clock_the_budgets_were_on(tmp_path):
    """A compare on the calibrated clock: its report reads the loss at the common time on that
    clock, as the verdict does, not on the measured one (where a slow-stepping rule that ended
    lower reads higher: soap 1.29 against its final 0.000934); a scene with a run on the measured
    clock stays on the measured clock, and the report says which."""
    budget = {"time_budget": 2.0, "clock": "calibrated"}
    # adam: measured and calibrated alike; soap: 3x slower measured than its calibrated cost
    fake_run(
        tmp_path / "a",
        "adam",
        0,
        1,
        [1.0, 0.5, 0.1],
        [0.0, 1.0, 2.0],
        trainer=budget,
        calibrated=[0.0, 1.0, 2.0],
    )
    fake_run(
        tmp_path / "s",
        "soap",
        0,
        1,
        [1.0, 0.2, 0.01],
        [0.0, 3.0, 6.0],
        trainer=budget,
        calibrated=[0.0, 1.0, 2.0],
    )
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    rows = {r["variant"]: r for r in run_rows(runs)}
    assert rows["soap"]["common_clock"] == "calibrated clock"
    assert rows["soap"]["common_time"] == 2.0  # both ended at 2 calibrated seconds
    assert rows["soap"]["loss_at_common_time"] == 0.01 == rows["soap"]["test_loss_at_1"]
    assert rows["adam"]["loss_at_common_time"] == 0.1
    fake_run(tmp_path / "m", "gd", 0, 1, [1.0, 0.9], [0.0, 1.0], trainer={"time_budget": 1.0})
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    rows = {r["variant"]: r for r in run_rows(runs)}
    assert {r["common_clock"] for r in rows.values()} == {"measured clock"}
    assert rows["soap"]["loss_at_common_time"] == 1.0  # 1.5 measured s: only its start


@pytest.mark.parametrize("make", ["missing", "empty", "unreadable", "unwritable_out"])
def test_bad_report_input_is_one_line(tmp_path, make, capsys):
    from physgrad.cli import main

    fake_run(tmp_path / "ok", "adam", 0, 1, [1.0, 0.5], [0.0, 1.0])
    (tmp_path / "empty").mkdir()
    blocker = tmp_path / "file"
    blocker.write_text("")
    (tmp_path / "corrupt").mkdir()
    (tmp_path / "corrupt" / "results.h5").write_bytes(b"garbage")
    args = {
        "missing": [str(tmp_path / "nope")],
        "empty": [str(tmp_path / "empty")],
        "unreadable": [str(tmp_path / "corrupt")],
        "unwritable_out": [str(tmp_path / "ok"), "--out", str(blocker / "out")],
    }[make]
    assert main(["report", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("physgrad: error: ") and err.count("\n") == 1, err


def test_figure_axes_read_well():
    assert use_log_x([1.0, 60.0], "auto") and not use_log_x([30.0, 60.0], "auto")
    assert use_log_x([30.0, 60.0], "on") and not use_log_x([1.0, 60.0], "off")
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0.99992, 0.99999])
    log_axis(ax)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
    assert labels and all(len(label) <= 5 and "10^" not in label for label in labels), labels
    plt.close(fig)


def test_a_compare_s_groups_name_their_tuning_study_colour_by_variant_and_style_by_study(
    tmp_path,
):
    """3 variants x 2 tuning studies: each group's label says its variant, its tuning study (from
    the evaluation job's folder) and its tuned value; a variant has one colour in every study and a
    study one line style and marker in every variant, none of them the diverged mark."""
    from physgrad.comparison.study import tuning_study
    from physgrad.plots import design_styles
    from physgrad.report import _label_studies

    for k, prefix in enumerate(("", "st1_")):
        for index, variant in enumerate(("adam", "gd", "hig")):
            folder = tmp_path / f"+compare_job=eval_{prefix}v{index}" / f"seed={k}"
            rate = 0.01 * (k + 1) * (index + 1)
            fake_run(folder, variant, k, 1, [1.0, 0.5], [0.0, 1.0], optim={"learning_rate": rate})
    runs, _, _ = collect([tmp_path])
    label_runs(runs)
    design = _label_studies(runs, tuning_study)
    assert sorted(design) == [
        f"{v}, tuning study {k}: learning_rate={0.01 * k * (i + 1):g}"
        for i, v in enumerate(("adam", "gd", "hig"))
        for k in (1, 2)
    ]
    styles = design_styles(design)
    by = {design[label]: style for label, style in styles.items()}
    for v in ("adam", "gd", "hig"):
        assert by[(v, 1)]["color"] == by[(v, 2)]["color"]
        assert by[(v, 1)]["linestyle"] != by[(v, 2)]["linestyle"]
    assert len({by[(v, 1)]["color"] for v in ("adam", "gd", "hig")}) == 3
    assert len({by[("adam", k)]["linestyle"] for k in (1, 2)}) == 2
    assert all(design_styles({"x": ("a", k)})["x"]["marker"] != "^" for k in range(1, 13))
