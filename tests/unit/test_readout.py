"""Unit layer of the one read-out: the loss at a budget is the last evaluation at or before it, a
continued run is read on its own training, the time to a target is a time on every axis, and older
files' variant names read in today's spelling."""

import math
from pathlib import Path

import numpy as np
import yaml

from physgrad.readout import Curve, loss_at, run_curve, run_record, time_to_target
from physgrad.results import ResultsWriter, Run, read_run


def write_run(path, variant, seed, x, loss, status="completed", trainer=None, step=1.0, attrs=None):
    """A results file with held-out evaluations `loss` at iterations x (training seconds step *
    x), with the root attributes `attrs` besides."""
    config = yaml.safe_dump(
        {
            "seed": seed,
            "seeds": 1,
            "precision": 32,
            "unroll": None,
            "init_from": None,
            "task": {"name": "toy"},
            "optim": {"name": variant},
            "trainer": {"iterations": 100, "time_budget": None, **(trainer or {})},
        }
    )
    stopped = {"stopped_by": "time_budget" if (trainer or {}).get("time_budget") else "iterations"}
    writer = ResultsWriter(
        path,
        {
            "task": "toy",
            "optim": variant,
            "variant": variant,
            "seed": seed,
            "config": config,
            **(stopped if status == "completed" else {}),
            **(attrs or {}),
        },
    )
    last = int(x[-1]) + (1 if status == "completed" else 0)
    for i in range(last):
        writer.append("train", {"iteration": i, "wall_time": step * (i + 1), "loss": 1.0})
    for xi, li in zip(x, loss):
        writer.append("eval", {"iteration": int(xi), "wall_time": step * xi, "loss": li})
    writer.finish(status, None if status == "completed" else f"{status} at iteration {last}")
    return path


def test_loss_at_reads_the_last_evaluation_at_or_before_the_budget(tmp_path):
    path = write_run(
        tmp_path / "results.h5",
        "adam",
        0,
        np.array([0, 10, 20, 30]),
        np.array([1.0, 0.2, 0.5, 0.4]),
    )
    run = read_run(path)
    assert loss_at(run) == 0.4  # its own budget (100 iterations): the last evaluation
    assert [loss_at(run, x, "iteration") for x in (0, 9, 10, 25, 1000)] == [1.0, 1.0, 0.2, 0.5, 0.4]
    assert math.isnan(loss_at(run, -1, "iteration"))
    assert time_to_target(run, 0.2, axis="iteration") == 10.0
    assert time_to_target(run, 0.1, axis="iteration") == math.inf
    assert math.isnan(time_to_target(run, math.nan))
    # completed: it ran to its budget, so its curve goes on past its end
    curve = run_curve(run, "iteration")
    assert isinstance(curve, Curve) and curve.end == math.inf and curve.at(10**6) == 0.4


def test_a_continued_run_is_read_on_its_own_training_and_placed_after_its_start(tmp_path):
    """A run started from another's network (init_from: 1,000 iterations and 500 s of training
    before it) with a budget of 100 iterations is read at its own 100th iteration, a quarter of
    its budget at its own 25th, and its time to a target on its own clock: not at the network it
    started from, where the shared axis puts its first evaluation. The report's common time is on
    the shared axis: a run from scratch ending at 530 s meets the continued one 30 s into its own
    training."""
    from physgrad.report import run_rows

    x, loss = np.array([0, 25, 50, 75, 99]), np.array([1.0, 0.5, 0.3, 0.2, 0.15])
    start = {"init_from": "start/results.h5", "init_iterations": 1000, "init_train_seconds": 500.0}
    continued = read_run(write_run(tmp_path / "a" / "results.h5", "gd", 0, x, loss, attrs=start))
    assert continued.offset("iteration") == 1000 and continued.offset("wall_time") == 500.0
    assert loss_at(continued) == 0.15
    assert [loss_at(continued, f * 100, "iteration") for f in (0.25, 0.5, 1)] == [0.5, 0.3, 0.15]
    assert time_to_target(continued, 0.3, axis="iteration") == 50.0
    assert time_to_target(continued, 0.3) == 50.0  # seconds of its own training (1 s a step)
    scratch = read_run(
        write_run(
            tmp_path / "b" / "results.h5",
            "gd",
            1,
            np.array([0, 529]),
            np.array([1.0, 0.9]),
            trainer={"iterations": 530},
        )
    )
    rows = {row["seed"]: row for row in run_rows([continued, scratch])}
    assert rows[0]["common_time"] == rows[1]["common_time"] == 530.0
    assert rows[0]["loss_at_common_time"] == 0.5  # its own 30 s: the evaluation at 25 s
    assert rows[1]["loss_at_common_time"] == 0.9


def test_the_time_to_a_target_is_a_time_on_every_axis():
    """On an iteration budget the evaluation that first reaches the target is found by its
    iteration, within the budget, and timed in training seconds; on a time budget it is its
    seconds; never reached: inf; no target: NaN."""
    run = Run(
        Path("r"),
        {"status": "completed", "seed": 0},
        {"iteration": np.arange(40.0), "wall_time": 0.5 * np.arange(1, 41.0)},
        {
            "iteration": np.array([0.0, 10, 20, 30]),
            "wall_time": np.array([0.0, 5.5, 10.5, 15.5]),
            "loss": np.array([1.0, 0.5, 0.2, 0.1]),
        },
    )
    assert time_to_target(run, 0.2, 40, "iteration") == 10.5
    assert time_to_target(run, 0.1, 25, "iteration") == math.inf  # reached after the budget
    assert time_to_target(run, 0.5, 20.0, "wall_time") == 5.5
    assert math.isnan(time_to_target(run, math.nan, 40, "iteration"))
    record = run_record(run, 0.2, "iteration", 40)
    assert record["time_to_target"] == 10.5 and record["test_loss_at_0.5"] == 0.2
    assert record["iterations"] == 40 and not record["diverged_by_budget"]


def test_an_older_file_s_variant_reads_in_today_s_spelling(tmp_path):
    """Files written before the variant's marks were spelled as compare names variants
    (`bptt[C,clip=norm]`, `stable_bptt[clip=norm]`, `bptt[M]`) read as `bptt backprop=C
    clip=norm`, ...; a name with a bracket of its own is left as it is."""
    x, loss = np.array([0, 10]), np.array([1.0, 0.5])
    for old, today in (
        ("bptt[C,clip=norm]", "bptt backprop=C clip=norm"),
        ("stable_bptt[clip=norm]", "stable_bptt clip=norm"),
        ("adam (from bptt[M])", "adam (from bptt backprop=M)"),
        ("bptt backprop=M", "bptt backprop=M"),
        ("my[rule", "my[rule"),
    ):
        assert read_run(write_run(tmp_path / f"{len(old)}.h5", old, 0, x, loss)).variant == today
