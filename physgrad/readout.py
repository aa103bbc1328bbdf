"""The read-out: what a run's results say at a budget. Every reader (compare.md, `physgrad report`,
read_runs, the claims, the trackers) reads through these functions, so two tables of one study
cannot disagree about one run.

- A run's held-out curve on an axis (iteration, wall_time or calibrated_time) is its /eval column
  against that axis, counted from the run's own start, as its budget is (trainer.iterations and
  trainer.time_budget are the run's own training, a run started from another's network (init_from)
  included), and ends where its training ended; a completed run ran to its budget, so its curve goes
  on past its last evaluation. The shared axis, on which a continued run starts where its start run
  ended (Run.offset), is for placing curves side by side: the report's figures and its common time.
- The loss at budget x is the last evaluation at or before x: the step that crosses a time budget
  counts against its variant, and an evaluation after it is not read at the budget. It is infinite
  when the run diverged by x: stopped as diverged, a non-finite held-out loss, or a loss above
  DIVERGENCE_FACTOR times its first (a blow-up without NaN). It is NaN (no loss) when the run ended
  before x without diverging (interrupted, failed, crashed) or has no evaluation by x.
- The time to a target is the training time (seconds; calibrated seconds on the calibrated clock) of
  the first evaluation at or below it by the budget; infinite if never, or if the run diverged
  first.
- A run at a budget is one row (run_record), the same in compare's runs.csv, the report's and
  read_runs'.
- The target is the median loss at the budget of the group with the lowest median (diverged runs
  counting as infinite, missing ones left out): the best group's typical result (highest_median: the
  worst group's, which the claims' timed comparisons use).
- A run's budget is what its configuration asked for: trainer.time_budget seconds (on the calibrated
  clock where trainer.clock is calibrated), else trainer.iterations.
- Numbers are printed with three significant figures, '-' for a missing one.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from physgrad.results import Run, parse_config

# a loss above this many times its first value counts as diverged (trainer.divergence_factor)
DIVERGENCE_FACTOR = 1e4
# The version of these rules: raised whenever what Curve.at gives for a stored run changes. A tuning
# journal records the version its trials were scored with (physgrad.comparison.tuning), so that a
# study tuned under another read-out is read again rather than kept. 1: a continued run read on the
# shared axis; 2: every run read on its own training.
READOUT_VERSION = 2
AXES = ("iteration", "wall_time", "calibrated_time")
# the fractions of the budget every table reads a run at (and the verdicts decide at)
FRACTIONS = (0.25, 0.5, 1.0)


@dataclass(frozen=True)
class Curve:
    """One run's held-out loss against iterations or training seconds.

    x, loss: its evaluations; end: where its training ended (iterations done, or training seconds;
    inf for a run that ran to its budget); diverged: stopped as diverged (at `end`)."""

    x: np.ndarray
    loss: np.ndarray
    end: float
    diverged: bool = False
    divergence_factor: float | None = DIVERGENCE_FACTOR

    def at(self, x: float) -> float:
        """The loss at budget x: the last evaluation at or before x; inf if the run diverged by x
        (stopped as diverged, a non-finite loss, or a loss past divergence_factor times its first);
        NaN if it ended before x without diverging, or has no evaluation by x."""
        x_tol = x * (1 + 1e-9)
        if self.diverged and self.end <= x_tol:
            return math.inf
        before = np.flatnonzero(np.asarray(self.x) <= x_tol)
        if not before.size:
            return math.nan
        losses = np.asarray(self.loss, float)[: before[-1] + 1]
        if not np.isfinite(losses).all():
            # a NaN or inf held-out loss is a divergence, whatever the run's status said
            return math.inf
        if (
            self.divergence_factor is not None
            and losses[0] > 0
            and (losses > self.divergence_factor * losses[0]).any()
        ):
            return math.inf
        if self.end < x * (1 - 1e-9):
            return math.nan  # ended early (interrupted, failed): no loss at x
        return float(losses[-1])

    def reaches(self, target: float, x: float) -> float:
        """The first evaluation's x at which the loss is at or below target, by budget x; inf if
        never (or the run diverged first)."""
        xs, losses = np.asarray(self.x, float), np.asarray(self.loss, float)
        for i in np.flatnonzero(xs <= x * (1 + 1e-9)):
            if not math.isfinite(losses[i]):
                return math.inf
            if losses[i] <= target:
                return float(xs[i])
        return math.inf


def run_curve(run: Run, axis: str, column: str = "loss") -> Curve:
    """The run's held-out `column` on the axis (iteration, wall_time or calibrated_time), counted
    from the run's own start (a run started from another's network too: its budget counts its own
    training), ending where its training ended (inf: a completed run)."""
    x = np.asarray(run.eval.get(axis, np.empty(0)), float)
    end = run.final("train", axis) + (1 if axis == "iteration" else 0)
    status = run.attrs.get("status")
    if status == "completed":
        end = math.inf  # ran to its budget: its last evaluation at or before any x counts
    elif not math.isfinite(end):
        end = 0.0
    return Curve(
        x,
        np.asarray(run.eval.get(column, np.full(x.shape, np.nan)), float),
        end,
        status == "diverged",
    )


def config_value(config: Mapping, dotted: str, default: Any = None) -> Any:
    """A value of a nested configuration (a dict or an OmegaConf DictConfig) by its dotted key."""
    node = config
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def budget_of(config: Mapping, default_iterations: int | None = None) -> tuple[str, float]:
    """(axis, budget) a configuration trains to: trainer.time_budget seconds (calibrated_time where
    trainer.clock is calibrated, else wall_time), else trainer.iterations (default_iterations where
    it is unset; NaN if that is None too)."""
    seconds = config_value(config, "trainer.time_budget")
    if seconds is not None:
        calibrated = config_value(config, "trainer.clock") == "calibrated"
        return ("calibrated_time" if calibrated else "wall_time"), float(seconds)
    iterations = config_value(config, "trainer.iterations", default_iterations)
    return "iteration", float(iterations) if iterations is not None else math.nan


def run_budget(run: Run) -> tuple[str, float]:
    """(axis, budget) of a run read back: its stored configuration's budget, else the iterations it
    trained."""
    axis, budget = budget_of(run.config or {})
    if axis == "iteration" and not math.isfinite(budget):
        budget = run.final("train", "iteration") + 1
    return axis, budget


def loss_at(
    run: Run, budget: float | None = None, axis: str | None = None, column: str = "loss"
) -> float:
    """The run's held-out loss at the budget on the axis (Curve.at); by default at the run's own
    budget."""
    if budget is None or axis is None:
        own_axis, own_budget = run_budget(run)
        axis, budget = axis or own_axis, own_budget if budget is None else budget
    return run_curve(run, axis, column).at(budget)


def time_to_target(
    run: Run, target: float, budget: float | None = None, axis: str | None = None
) -> float:
    """The run's training seconds (calibrated seconds where the budget is on the calibrated clock)
    at its first held-out evaluation at or below target by the budget on the axis (Curve.reaches;
    by default the run's own budget); inf if never or diverged first, NaN if there is no target.
    On an iteration budget the evaluation is found by its iteration and timed in seconds, so that
    every table's time to target is a time."""
    if not math.isfinite(target):
        return math.nan
    if axis is None or budget is None:
        own_axis, own_budget = run_budget(run)
        if budget is None:
            budget = own_budget if axis in (None, own_axis) else math.inf
        axis = axis or own_axis
    reached = run_curve(run, axis).reaches(target, budget)
    if axis != "iteration" or not math.isfinite(reached):
        return reached
    iterations = np.asarray(run.eval.get("iteration", np.empty(0)), float)
    seconds = np.asarray(run.eval.get("wall_time", np.full(iterations.shape, np.nan)), float)
    return float(seconds[np.flatnonzero(iterations == reached)[0]])


def number_attr(run: Run, key: str) -> float:
    """A numeric attribute of the run's file (NaN where it is missing or not a number)."""
    value = run.attrs.get(key)
    return (
        float(value)
        if isinstance(value, (int, float)) and not isinstance(value, bool)
        else math.nan
    )


def _shared_by(run: Run) -> int:
    """How many members trained together in the run's job (1 for a run alone, or a file that does
    not say)."""
    shared = number_attr(run, "wall_time_shared_by")
    return int(shared) if math.isfinite(shared) and shared >= 1 else 1


def run_record(
    run: Run, target: float, axis: str | None = None, budget: float | None = None
) -> dict:
    """One run at a budget as a row, the same in every runs table (compare's runs.csv, the
    report's runs.csv and read_runs, the claims): the run (path, its variant as its file names it:
    compare's tables put the study's name of the variant there, its report's too,
    seed), how it ended (status, stopped_by, reason), the budget (axis, budget: by default the
    run's own), its held-out loss at 1/4, 1/2 and all of the budget (test_loss_at_0.25, _0.5, _1:
    inf if it had diverged by then, NaN if it ended before without a loss), diverged_by_budget, the
    target and its time_to_target (seconds, time_to_target), what it cost (iterations,
    train_seconds, calibrated_seconds, compile_seconds, first_step_overhead_seconds,
    step_seconds_p50/p90; wall_time_shared_by: how many seeds or trials trained together in its
    job, whose train_seconds they share), whether its timing was contended and where it ran
    (machine)."""
    from physgrad.machine import machine_label

    own_axis, own_budget = run_budget(run)
    axis = axis or own_axis
    budget = (own_budget if axis == own_axis else math.inf) if budget is None else budget
    row = {
        "path": str(run.path),
        "variant": run.variant,
        "seed": run.attrs.get("seed"),
        "status": run.attrs.get("status"),
        "stopped_by": run.attrs.get("stopped_by", "") or "",
        "axis": axis,
        "budget": budget,
        **{f"test_loss_at_{f:g}": loss_at(run, budget * f, axis) for f in FRACTIONS},
    }
    last = run.final("train", "iteration")
    row.update(
        diverged_by_budget=math.isinf(row["test_loss_at_1"]),
        target=target,
        time_to_target=time_to_target(run, target, budget, axis),
        iterations=int(last) + 1 if math.isfinite(last) else 0,
        train_seconds=run.final("train", "wall_time"),
        wall_time_shared_by=_shared_by(run),
        calibrated_seconds=run.final("train", "calibrated_time"),
        compile_seconds=number_attr(run, "compile_seconds"),
        first_step_overhead_seconds=number_attr(run, "first_step_overhead_seconds"),
        step_seconds_p50=number_attr(run, "step_seconds_p50"),
        step_seconds_p90=number_attr(run, "step_seconds_p90"),
        contended=bool(run.attrs.get("contended", 0)),
        contention=str(run.attrs.get("contention", "") or ""),
        machine=machine_label(run.attrs),
        reason=str(run.attrs.get("reason", "") or ""),
    )
    return row


def _finite_medians(losses: dict[str, list[float]]) -> dict[str, float]:
    """Each group's median loss, NaN losses left out and infinite ones (diverged) counted; groups
    whose median is not finite are left out."""
    medians = {
        name: float(np.median(kept))
        for name, values in losses.items()
        if (kept := [v for v in values if not math.isnan(v)])
    }
    return {name: m for name, m in medians.items() if math.isfinite(m)}


def lowest_median(losses: dict[str, list[float]]) -> tuple[str, float]:
    """(group, its median) of the group whose median loss is lowest; NaN losses are left out,
    infinite ones (diverged) count; ("", NaN) if no group has a finite median. The target every
    group works towards: the best group's typical result, which the other groups may or may not
    reach."""
    finite = _finite_medians(losses)
    if not finite:
        return "", math.nan
    best = min(finite, key=finite.get)
    return best, finite[best]


def highest_median(losses: dict[str, list[float]]) -> tuple[str, float]:
    """(group, its median) of the group whose finite median loss is highest; ("", NaN) if none is
    finite. A target every group with a finite median reaches in at least about half its runs (the
    worse group's typical result), so that time to target compares times, not mostly pairs where
    neither run got there."""
    finite = _finite_medians(losses)
    if not finite:
        return "", math.nan
    worst = max(finite, key=finite.get)
    return worst, finite[worst]


def target_loss(curves: dict[str, dict[int, Curve]], budget: float) -> tuple[str, float]:
    """The target of time-to-target: lowest_median of every group's losses at the budget; (group,
    target)."""
    return lowest_median(
        {name: [c.at(budget) for c in by_seed.values()] for name, by_seed in curves.items()}
    )


def targets(runs: Iterable[Run]) -> dict[str, float]:
    """Per scene of a report (run.scene), the target of time to target: lowest_median over its
    groups (run.label, else the variant) of each run's loss at its own budget. Every run has to
    train to get there, and a group that never does says so. (The worst final loss would be reached
    at the first evaluation whenever one run ends above where all began.)"""
    losses = defaultdict(lambda: defaultdict(list))
    for run in runs:
        losses[run.scene][run.label or run.variant].append(loss_at(run))
    return {scene: lowest_median(groups)[1] for scene, groups in losses.items()}


def flat_config(tree: Mapping, prefix: str = "") -> dict:
    """A nested configuration as one row: dotted keys (optim.learning_rate), lists as tuples."""
    flat = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(flat_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value if not isinstance(value, list) else tuple(value)
    return flat


def config_row(run: Run) -> dict:
    """The run's resolved configuration as one row of dotted keys (empty if it holds none):
    read_run's parsed
    copy, or for a Run built in memory its config attribute parsed the same way
    (results.parse_config)."""
    tree = run.config
    if not tree and isinstance(run.attrs.get("config"), str):
        try:
            tree = parse_config(run.attrs["config"])
        except ValueError:
            tree = {}
    return flat_config(tree)


def fmt(value: object) -> str:
    """A number as printed in every table: three significant figures, '-' for a missing one (None,
    NaN), inf and -inf as such; any other value as its text."""
    if isinstance(value, np.floating):
        value = float(value)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.3g}" if isinstance(value, float) else str(value)
