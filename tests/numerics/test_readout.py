"""Numerics layer of the one read-out: compare.md / runs.csv and the report of the same study give
the same number per run at an iteration or time budget (diverged, blown-up, interrupted and
non-monotone runs among them), and the budget is what the configuration asked for."""

import csv
import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from physgrad.comparison import StudySettings, Variant, analyse, study_settings
from physgrad.comparison.study import write_curves_report
from physgrad.readout import budget_of, run_curve
from physgrad.results import read_run
from tests.unit.test_readout import (
    write_run,
)

SEEDS = range(6)


def study(tmp_path, time_budget=None):
    """Two variants on six paired seeds, as a study's evaluation folder: hig seed 2 diverges (a NaN
    evaluation, stopped as diverged), adam seed 3 goes down and up again (non-monotone), adam seed 4
    blows up without NaN (a loss 10^5 times its first), hig seed 5 was interrupted before the
    budget."""
    x = np.array([0, 25, 50, 75, 99])
    # a time budget of 1.5 s: the last evaluation (1.98 s) is past it
    step = 0.02 if time_budget else 1.0
    trainer = {"time_budget": time_budget} if time_budget else {}
    for seed in SEEDS:
        adam = np.array([1.0, 0.5, 0.3, 0.2, 0.15]) * (1 + 0.1 * seed)
        hig = np.array([1.0, 0.3, 0.1, 0.05, 0.04]) * (1 + 0.1 * seed)
        status = {"adam": "completed", "hig": "completed"}
        if seed == 3:
            adam = np.array([1.0, 0.1, 0.6, 0.3, 0.45])
        if seed == 4:
            adam = np.array([1.0, 0.5, 2e5, 3e5, 0.1])
        hig_x = x
        if seed == 2:
            hig, hig_x, status["hig"] = np.array([1.0, 0.3, np.nan]), x[:3], "diverged"
        if seed == 5:
            hig, hig_x, status["hig"] = hig[:3], x[:3], "interrupted"
        write_run(
            tmp_path / "eval" / f"+compare_job=eval_v0_s{seed}" / "results.h5",
            "adam",
            seed,
            x,
            adam,
            status["adam"],
            trainer,
            step,
        )
        write_run(
            tmp_path / "eval" / f"+compare_job=eval_v1_s{seed}" / "results.h5",
            "hig",
            seed,
            hig_x,
            hig,
            status["hig"],
            trainer,
            step,
        )


def analysed(tmp_path, axis, budget):
    """compare's phase 3 on the evaluation files, then `physgrad report` on the same files, as a
    study writes them: (compare's runs.csv, report/runs.csv), each by path."""
    # named as a study with a second axis names them: not as their files do ("adam", "hig")
    variants = [
        Variant(name, [f"optim={name}"], OmegaConf.create({"task": {"name": "toy"}, "optim": {}}))
        for name in ("adam tau=1e-06", "hig tau=1e-06")
    ]
    curves, statuses = {}, {}
    for index, variant in enumerate(variants):
        curves[variant.name], statuses[variant.name] = {}, {}
        for seed in SEEDS:
            run = read_run(tmp_path / "eval" / f"+compare_job=eval_v{index}_s{seed}" / "results.h5")
            curves[variant.name][seed], statuses[variant.name][seed] = run_curve(run, axis), run
    settings: StudySettings = study_settings({"seeds": len(SEEDS), "studies": 1})
    best = [{v.name: {} for v in variants}]
    analyse(tmp_path, variants, best, [curves], [statuses], settings, axis, budget, [])
    said = []
    write_curves_report(tmp_path, said.append, False, 1, [v.name for v in variants])
    assert not said  # the report was written
    with (
        open(tmp_path / "runs.csv") as compare_csv,
        open(tmp_path / "report" / "runs.csv") as report_csv,
    ):
        return (
            {row["path"]: row for row in csv.DictReader(compare_csv)},
            {row["path"]: row for row in csv.DictReader(report_csv)},
        )


def number(text: str) -> float:
    return math.nan if text in ("", "nan") else float(text)


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


# make test-long: the time budget (the same read-out on the wall_time axis); make test keeps the
# iteration budget here, and the last evaluation at or before a budget in
# tests/unit/test_readout.py::test_loss_at_reads_the_last_evaluation_at_or_before_the_budget
@pytest.mark.parametrize("time_budget", [None, pytest.param(1.5, marks=pytest.mark.long)])
def test_compare_and_report_give_one_number_per_run_at_the_budget(tmp_path, time_budget):
    study(tmp_path, time_budget)
    axis, budget = ("wall_time", time_budget) if time_budget else ("iteration", 100.0)
    compare, report = analysed(tmp_path, axis, budget)
    assert sorted(compare) == sorted(report) and len(compare) == 12
    # one record per run: every column the two tables share is the same text in both, the variant
    # as the study names it included
    shared = set(next(iter(compare.values()))) & set(next(iter(report.values())))
    assert {
        "variant",
        "seed",
        "status",
        "axis",
        "budget",
        "test_loss_at_0.25",
        "test_loss_at_0.5",
        "test_loss_at_1",
        "diverged_by_budget",
        "target",
        "time_to_target",
        "iterations",
        "train_seconds",
        "machine",
    } <= shared
    for path, row in compare.items():
        assert {c: row[c] for c in shared} == {c: report[path][c] for c in shared}, path
    by_name = {  # by the rule's name
        (row["variant"].split()[0], int(row["seed"])): number(row["test_loss_at_1"])
        for row in compare.values()
    }
    assert by_name[("hig", 2)] == math.inf  # diverged (a NaN evaluation)
    assert by_name[("adam", 4)] == math.inf  # blew up without NaN, whatever its last loss
    assert math.isnan(by_name[("hig", 5)])  # interrupted before the budget: no loss at it
    if (
        time_budget
    ):  # the evaluation after the budget is not read: adam seed 3's last one at or before 1.5 s
        assert by_name[("adam", 3)] == 0.3
    else:  # the last evaluation, not the lowest
        assert by_name[("adam", 3)] == 0.45
    # one target (the lowest median at the budget) and one time to it, in both tables
    targets = {number(row["target"]) for row in report.values()}
    assert len(targets) == 1
    target = targets.pop()
    text = (tmp_path / "compare.md").read_text()
    assert f"Target: {target:.3g}," in text
    # 6 seeds, one comparison: one seed against leaves p = 4 / 2^6 above 0.05
    assert "needs every seed on one side" in text and "compare.seeds=7 would allow one" in text


def test_the_budget_is_what_the_configuration_asked_for():
    assert budget_of({"trainer": {"iterations": 300, "time_budget": None}}) == ("iteration", 300.0)
    assert budget_of({"trainer": {"iterations": 300, "time_budget": 60}}) == ("wall_time", 60.0)
    assert budget_of({"trainer": {"time_budget": 60, "clock": "calibrated"}}) == (
        "calibrated_time",
        60.0,
    )
    assert budget_of({"trainer": {}}, default_iterations=1000) == ("iteration", 1000.0)
    assert math.isnan(budget_of({})[1])
