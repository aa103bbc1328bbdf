"""The calibrated clock: each variant's step cost, measured with the variants' compiled steps
interleaved in one process, so that a busy machine slows every variant alike and its load cannot
flip an equal-time comparison.

    cost(v) = the CALIBRATION_QUANTILE quantile, over rounds in which every variant runs one burst
    of its steps,
              of v's burst time divided by its burst's length k_v,
    calibrated_time(run) = iterations(run) x cost(variant of run),

except for a rule whose step updates on a schedule (PSGD Kron's preconditioner: at every step first,
then rarer), timed both where every step updates (its cost s) and where the schedule has fallen to
its floor, which gives its update's cost u: a run of n steps is charged n (s - u) + u sum_{t<=n} p_t
(physgrad.optim.capabilities.ScheduledUpdate), what its steps cost on average; and except for a rule
that searches a line (L-BFGS, SSBFGS, SSBroyden: as many evaluations of the batch loss and its
gradient as each step's line search needs), whose evaluations are counted over the timed steps (e
per step) and one of them timed in the same rounds (v): a run is charged n (s - v e) + v E for the E
evaluations its n steps made, what its steps did. A calibration without u or v (written before they
were measured) charges n s.

A burst is k_v consecutive steps, k_v chosen so that a burst takes about BURST_SECONDS: a single
step of a sub-millisecond variant timed between other variants' steps runs with caches the others
filled, and measured 1.4 to 1.7 times what it costs in its own run (Adam, L-BFGS and K-FAC on the
toy), which would have given the fast variants fewer iterations than they get when they train.

A low quantile is the cost on the quietest rounds: a step that another process delays takes longer,
never shorter, so the low quantile is what the step itself costs (AlgoPerf and `make bench` time
interleaved for the same reason). docs/decisions.md ("Timing") gives the rule and its limits: other
step costs that depend on the data (a float64 retry of a failed factorisation) are counted at the
calibrated cost, and on a GPU the step is timed the same way (dispatch until the
results are ready).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from physgrad.comparison.jobs import Launcher
from physgrad.comparison.spec import StudyPlan, Variant
from physgrad.errors import UserError

CALIBRATION_FILE = "calibration.json"


def read_calibration(path: Path, names: list[str], given: bool = False) -> dict | None:
    """The stored calibration if it is whole: a quantile in (0, 1), load averages, the machine, and
    for every one of names a step cost of at least MIN_STEP_COST (a microsecond) and below an hour,
    its median and rounds; else None (calibrate again). A file that may come from someone else is
    read as data, at most 1 MB, never through a link (given: a path the user named, which may be
    one) and never from a FIFO, a device or a folder."""
    from physgrad.trainer_settings import MIN_STEP_COST

    def seconds(value: object) -> bool:
        return (
            isinstance(value, (int, float))
            and not isinstance(value, bool)
            and MIN_STEP_COST <= value < 3600
        )

    def finite(value: object) -> bool:
        return (
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        )

    from physgrad.files import load_json, read_own_file

    try:
        stored = load_json(read_own_file(Path(path), 1 << 20, follow=given))
        whole = (
            isinstance(stored, dict)
            and finite(stored.get("quantile"))
            and 0 < stored["quantile"] < 1
            and finite(stored.get("load_start"))
            and finite(stored.get("load_end"))
            and isinstance(stored.get("machine"), dict)
            and isinstance(stored["machine"].get("cpu_count", 1), int)
            and isinstance(stored.get("costs"), dict)
            and all(
                isinstance(stored["costs"].get(name), dict)
                and seconds(stored["costs"][name].get("step_seconds"))
                and seconds(stored["costs"][name].get("median_seconds"))
                and isinstance(stored["costs"][name].get("rounds"), int)
                and _interval_whole(stored["costs"][name], seconds)
                and _update_whole(stored["costs"][name], finite)
                and _evaluations_whole(stored["costs"][name], finite)
                for name in names
            )
        )
    except (OSError, ValueError):
        return None
    return stored if whole else None


def _interval_whole(cost: dict, seconds: object) -> bool:
    """A cost's interval (low_seconds, high_seconds), where recorded (calibrations written before
    it was are read without one), holds the cost."""
    if "low_seconds" not in cost and "high_seconds" not in cost:
        return True
    low, high = cost.get("low_seconds"), cost.get("high_seconds")
    return seconds(low) and seconds(high) and low <= cost["step_seconds"] <= high


def _evaluations_whole(cost: dict, finite: object) -> bool:
    """A line search's evaluation cost v and evaluations per step e, where recorded: both finite,
    at least 0, with v e at most the step's cost."""
    if "evaluation_seconds" not in cost and "step_evaluations" not in cost:
        return True
    each, per_step = cost.get("evaluation_seconds"), cost.get("step_evaluations")
    return (
        finite(each)
        and finite(per_step)
        and each >= 0
        and 0 <= per_step <= 1e6
        and each * per_step <= cost["step_seconds"] * (1 + 1e-9)
    )


def _update_whole(cost: dict, finite: object) -> bool:
    """A scheduled update's cost, where recorded: within [0, step_seconds], with the step it was
    timed from (a positive integer), that step's cost and its floor probability in [0, 1)."""
    if "update_seconds" not in cost:
        return True
    update, advanced, floor, step = (
        cost.get("update_seconds"),
        cost.get("advanced_seconds"),
        cost.get("floor_probability"),
        cost.get("advanced_step"),
    )
    return (
        isinstance(step, int)
        and not isinstance(step, bool)
        and step >= 1
        and finite(update)
        and 0 <= update <= cost["step_seconds"]
        and finite(advanced)
        and advanced > 0
        and finite(floor)
        and 0 <= floor < 1
    )


def cost_spread(calibration: dict, names: list[str]) -> dict[str, tuple[float, float]]:
    """Each variant's step-cost interval as factors of its cost, (low / cost, high / cost); (1, 1)
    where the calibration recorded none."""
    spread = {}
    for name in names:
        cost = calibration["costs"][name]
        step = float(cost["step_seconds"])
        spread[name] = (
            float(cost.get("low_seconds", step)) / step,
            float(cost.get("high_seconds", step)) / step,
        )
    return spread


def write_calibration(path: Path, calibration: dict) -> None:
    from physgrad.files import replace_file

    replace_file(Path(path), json.dumps(calibration, indent=1).encode())


def calibrated_clock(plan: StudyPlan, launcher: Launcher, given: str | None) -> dict:
    """Each variant's step cost (physgrad.timing.calibrate), measured once per study by one job of
    the study (phase `calibration`, launched like the others: on a cluster, where the jobs run) and
    stored in its folder (a resumed study reuses it), or taken from a given calibration.json
    (compare.calibration); every job of a variant then runs on the calibrated clock with that
    cost."""
    from omegaconf import OmegaConf, open_dict

    from physgrad.comparison.jobs import job_yaml

    folder, variants = launcher.folder, plan.variants
    path = folder / CALIBRATION_FILE
    ends = {v.name: knob_ends(v) for v in variants}
    names = [v.name for v in variants] + [name for e in ends.values() for name in e]
    if any(ends.values()) and read_calibration(path, names) is None:
        older = read_calibration(path, [v.name for v in variants])
        if older is not None:  # calibrated before a knob's costs were: resumed as it ran
            lacking = sorted(n for n, e in ends.items() if not set(e) <= set(older["costs"]))
            launcher.say(
                f"note: {path} has no costs at the points of a tuned setting that changes a "
                f"step's cost for {', '.join(lacking)}: their trials are charged their preset "
                "cost, as the study began"
            )
            ends = {n: {} if n in lacking else e for n, e in ends.items()}
            names = [v.name for v in variants] + [name for e in ends.values() for name in e]
            given = None
    if given is not None:
        calibration = read_calibration(Path(given), names, given=True)
        if calibration is None:
            raise UserError(
                f"compare.calibration={given}: not a calibration.json with a step cost for every "
                f"variant ({', '.join(names)}; name@key=value: a tuned setting that shapes the "
                "step's cost, at its range's ends); leave it out to calibrate"
            )
        write_calibration(path, calibration)
    calibration = read_calibration(path, names)
    if calibration is None:
        launcher.say(
            f"calibrating the step costs of {len(variants)} variants, interleaved in one job"
        )
        configs = {}
        for variant in variants:
            cfg = variant.config.copy()
            with open_dict(cfg):
                del cfg["hydra"]
            configs[variant.name] = OmegaConf.to_container(cfg, resolve=True)
            for name, (key, value) in ends[variant.name].items():
                configs[name] = {**configs[variant.name]}
                configs[name]["optim"] = {**configs[variant.name]["optim"], key: value}
        values = {"seed": plan.settings.tune_seed, "calibrate": configs, "figures": False}
        first = variants[0]
        launcher.run(
            "calibration",
            {"calibration": job_yaml([*plan.common, *first.overrides], plan.groups, values)},
        )
        measured = folder / "calibration" / "+compare_job=calibration" / CALIBRATION_FILE
        calibration = read_calibration(measured, names)
        if calibration is None:
            raise UserError(
                f"the calibration did not finish (see {folder / 'calibration.log'}): run the same "
                "command again to resume"
            )
        write_calibration(path, calibration)
    for variant in variants:
        charge(variant, calibration["costs"], ends[variant.name], given or path)
    return calibration


def charge(variant: Variant, costs: dict, ends: dict, where: object) -> None:
    """Set what a variant's jobs are charged from the calibration's costs: its step cost, a
    scheduled update's and a line search's evaluations' where it has them, and the costs at its
    cost-shaping knob's ends (Variant.cost_knob); UserError where a cost does not fit its rule."""
    from physgrad.optim.capabilities import capabilities, scheduled_update

    cost, kind = costs[variant.name], capabilities(variant.config.optim)
    if "evaluation_seconds" in cost and not kind.line_search:
        raise UserError(
            f"{where}: {variant.name}'s cost has a line search's evaluation cost "
            "(evaluation_seconds), and its rule searches no line: give a calibration of this "
            "study's variants, or leave compare.calibration out to calibrate"
        )
    if "update_seconds" in cost and scheduled_update(variant.config.optim) is None:
        raise UserError(
            f"{where}: {variant.name}'s cost has an update cost (update_seconds), and "
            "its rule updates on no schedule (only psgd_kron with "
            "preconditioner_update_probability=null does): give a calibration of this study's "
            "variants, or leave compare.calibration out to calibrate"
        )
    variant.job_values = {
        "trainer.step_cost": float(cost["step_seconds"]),
        "trainer.clock": "calibrated",
    }
    if "update_seconds" in cost:
        variant.job_values["trainer.update_cost"] = float(cost["update_seconds"])
    if "evaluation_seconds" in cost:
        variant.job_values["trainer.evaluation_cost"] = float(cost["evaluation_seconds"])
        variant.job_values["trainer.step_evaluations"] = float(cost["step_evaluations"])
    variant.cost_knob = ()
    if ends:
        # each point's own part of a step: its line search's evaluations are charged as the run
        # makes them (the preset's e v added back in Variant.priced), not as that point made them
        def own(c: dict) -> float:
            return c["step_seconds"] - c.get("evaluation_seconds", 0.0) * c.get(
                "step_evaluations", 0.0
            )

        key = next(iter(ends.values()))[0]
        points = {value: own(costs[name]) for name, (_, value) in ends.items()}
        preset = variant.config.optim.get(key)
        if isinstance(preset, (int, float)) and min(points) < preset < max(points):
            points[preset] = own(cost)  # measured there: the piecewise model passes through it
        variant.cost_knob = (key, kind.cost_knob[1], tuple(sorted(points.items())))


def knob_ends(variant: Variant) -> dict[str, tuple[str, float]]:
    """The calibration's further configs of a variant tuned over the setting that shapes its step
    cost (physgrad.optim.capabilities: cost_knob): `name@key=value` -> (key, value) at the two
    ends of its range and at the rule's breaks inside it (cost_points), {} for the others."""
    from physgrad.optim.capabilities import capabilities, cost_points

    kind = capabilities(variant.config.optim)
    if kind.cost_knob is None or kind.cost_knob[0] not in variant.space:
        return {}
    key = kind.cost_knob[0]
    values = cost_points(kind, *variant.space[key])
    return {f"{variant.name}@{key}={value}": (key, value) for value in values}
