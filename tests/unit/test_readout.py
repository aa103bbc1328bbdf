"""Unit layer (pure functions, no scene compiled) of the tests of:
One read-out for every reader: a study's compare.md / runs.csv and the report/ of the same files
give the same number for the same run at the same budget, a diverged run and a non-monotone curve
among them."""

import math

import numpy as np
import yaml

from physgrad.readout import Curve, loss_at, run_curve, time_to_target
from physgrad.results import ResultsWriter, read_run


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
