"""compare.md's timing section: the clock a study's verdicts read, the calibrated step costs, the
step cost of each variant where the budget is in iterations, contended runs and the machines."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from physgrad.comparison.spec import Variant
from physgrad.readout import fmt

if TYPE_CHECKING:
    import pandas as pd


def timing_lines(
    variants: list[Variant], runs: pd.DataFrame, axis: str, calibration: dict | None
) -> list[str]:
    """compare.md's timing section: the clock, the calibration's step costs, contended runs, the
    machines."""
    lines = ["", "## Timing", ""]
    if axis == "calibrated_time" and calibration:
        lines += _calibration_lines(variants, runs, calibration)
    elif axis == "wall_time":
        lines += [
            "Clock: measured (training seconds as timed). A run flagged contended (step times "
            "spread or the "
            "machine oversubscribed, docs/decisions.md) was slowed by other work: a verdict that "
            "uses one is marked. The calibrated clock is the default (compare.clock=calibrated)."
        ]
    else:
        lines += ["Budget in iterations: the clock does not enter the verdicts."]
        lines += step_cost_lines(variants, runs)
    machines = sorted(set(runs["machine"])) if len(runs) else []
    if len(machines) > 1:
        lines += [
            "",
            f"**Warning**: the runs come from {len(machines)} machines ({'; '.join(machines)}): "
            "their times are not comparable.",
        ]
    elif machines:
        lines += ["", f"Machine: {machines[0]}."]
    flagged = runs[runs.contended] if len(runs) else runs
    if len(flagged):
        lines += [
            "",
            f"Contended runs: {len(flagged)} of {len(runs)} "
            f"(e.g. {flagged.iloc[0]['variant']} seed {flagged.iloc[0]['seed']}: "
            f"{flagged.iloc[0]['contention']}).",
        ]
    return lines


def step_cost_lines(variants: list[Variant], runs: pd.DataFrame) -> list[str]:
    """What an iteration costs each variant, as its evaluation runs measured it: the median over
    runs of their median step time, and their training seconds (seeds trained together in one
    job share one step)."""
    if not len(runs):
        return []
    lines = [
        "",
        "| variant | step time: median of the runs' p50 | training seconds per run: median |",
        "|---|---|---|",
    ]
    for variant in variants:
        sub = runs[runs.variant == variant.name]
        step = sub["step_seconds_p50"].astype(float)
        train = sub["train_seconds"].astype(float)
        lines.append(
            f"| {variant.name} | "
            f"{fmt(float(np.nanmedian(step))) + ' s' if step.notna().any() else '-'} | "
            f"{fmt(float(np.nanmedian(train))) + ' s' if train.notna().any() else '-'} |"
        )
    return lines + [
        "",
        "Seeds trained together in one vectorised job share each step, so a step here is that of "
        "all seeds of the job.",
    ]


def _calibration_lines(variants: list[Variant], runs: pd.DataFrame, calibration: dict) -> list[str]:
    """The calibrated clock: how the step costs were measured, each variant's cost against its
    runs' measured steps, and a warning where the calibration's machine was busy."""
    scheduled = [v.name for v in variants if "update_seconds" in calibration["costs"][v.name]]
    where = " (a scheduled update at its expected cost, below)" if scheduled else ""
    lines = [
        "Clock: calibrated. Step costs measured with every variant's compiled step "
        "interleaved in one "
        f"process (the {calibration['quantile']:g} quantile over rounds; load average "
        f"{calibration['load_start']:.2f} -> {calibration['load_end']:.2f}); a run's time is its "
        f"iterations times its variant's cost{where}, "
        "so the machine's load cannot change how far a "
        "variant gets. The measured clock: compare.clock=measured.",
        "",
        "| variant | calibrated step cost [interval] | median in the calibration | rounds | "
        "measured p50 in the runs, per seed | contended runs |",
        "|---|---|---|---|---|---|",
    ]
    for variant in variants:
        cost = calibration["costs"][variant.name]
        sub = runs[runs.variant == variant.name] if len(runs) else runs
        # a step of seeds trained together is theirs: its share per seed is what one run's costs
        step = sub["step_seconds_p50"] / sub.get("wall_time_shared_by", 1) if len(sub) else None
        p50 = float(np.nanmedian(step)) if step is not None and step.notna().any() else math.nan
        lines.append(
            f"| {variant.name} | {fmt(cost['step_seconds'])} s{_interval_text(cost)} | "
            f"{fmt(cost['median_seconds'])} s | "
            f"{cost['rounds']} | {fmt(p50)} s | "
            f"{int(sub['contended'].sum()) if len(sub) else 0} of {len(sub)} |"
        )
    if scheduled:
        lines += ["", scheduled_update_text(scheduled, calibration)]
    priced = [v for v in variants if v.cost_knob]
    if priced:
        lines += ["", knob_cost_text(priced)]
    shared = _shared_programs(variants, calibration)
    if shared:
        lines += [
            "",
            "One compiled program, timed once and given one cost: "
            + "; ".join(", ".join(group) for group in shared)
            + ".",
        ]
    lines += [
        "",
        "The interval of a cost is the widest of its bootstrap 95% interval over the rounds and "
        "the costs of each half of the rounds; a verdict of better that does not hold with the "
        "winner's cost at the top of its interval and the loser's at the bottom is "
        '"undecided by the clock".',
    ]
    from physgrad.machine import machine_label

    measured_on = machine_label(calibration["machine"])
    elsewhere = sorted(set(runs["machine"]) - {measured_on}) if len(runs) else []
    if elsewhere:
        host = str(calibration["machine"].get("hostname", "") or "?")
        lines += [
            "",
            f"**Warning**: the step costs were calibrated on {measured_on} (host {host}), but runs "
            f"ran on {'; '.join(elsewhere)}: the calibrated clock does not give those runs the "
            "time their steps took there. Calibrate where the jobs run (the calibration is a job "
            "of the study, sent with the same launcher: delete calibration.json and run again).",
        ]
    busy = busy_calibration(calibration)
    if busy:
        lines += [
            "",
            f"**Warning**: the calibration ran on a busy machine ({busy}): the step costs of the "
            "variants are not slowed alike by other work, so recalibrate on a quiet machine "
            "or give one with compare.calibration.",
        ]
    return lines


def scheduled_update_text(names: list[str], calibration: dict) -> str:
    """The sentence on the variants whose step updates on a schedule: the cost of their update and
    of a step at the schedule's floor, and how their runs are charged."""
    each = "; ".join(
        f"{name}: {fmt(cost['update_seconds'])} s of its {fmt(cost['step_seconds'])} s, "
        f"{fmt(cost['advanced_seconds'])} s a step from step {cost.get('advanced_step', '?')} on "
        f"(p = {cost['floor_probability']:g})"
        for name in names
        for cost in [calibration["costs"][name]]
    )
    return (
        "A scheduled update (a part of the step done with a probability p_t that falls along the "
        "run) was timed where every step does it (the cost above) and where p_t is at its floor, "
        f"which gives the update's cost u ({each}); a run of n steps is charged "
        "n (cost - u) + u sum_{t<=n} p_t, what its steps cost on average."
    )


def knob_cost_text(variants: list[Variant]) -> str:
    """Where a tuned setting shapes a step's cost: its costs at its range's ends, and that each
    trial and evaluation is charged at its own value (physgrad.optim.capabilities.knob_cost)."""
    shapes = {"inverse": "c + u / f", "linear": "a + b m", "floor": "each point's up to the next"}
    said = [
        f"{v.name}'s {key}: a step's own part "
        + ", ".join(f"{fmt(seconds)} s at {value:g}" for value, seconds in points)
        + f" ({shapes.get(shape, shape)} between them)"
        for v in variants
        for key, shape, points in [v.cost_knob]
    ]
    return (
        "A tuned setting that changes what a step costs was calibrated at its range's two ends, "
        "its preset and where it changes the computation, and each trial and evaluation is "
        "charged the cost at its own value (a line search's evaluations as the run made them): "
        + "; ".join(said)
        + "."
    )


def busy_calibration(calibration: dict) -> str:
    """Why the calibration's machine was busy (its load average against its cores), or ""."""
    from physgrad.machine import contention

    return contention(
        {},
        0,
        calibration["load_start"],
        calibration["load_end"],
        int(calibration["machine"].get("cpu_count", 1)),
    )


def _interval_text(cost: dict) -> str:
    if "low_seconds" not in cost:
        return " [not recorded]"
    return f" [{fmt(cost['low_seconds'])}, {fmt(cost['high_seconds'])}]"


def _shared_programs(variants: list[Variant], calibration: dict) -> list[list[str]]:
    """Groups of two or more variants whose compiled steps are one program."""
    groups: dict[str, list[str]] = {}
    for variant in variants:
        program = calibration["costs"][variant.name].get("program")
        if program:
            groups.setdefault(program, []).append(variant.name)
    return [names for names in groups.values() if len(names) > 1]
