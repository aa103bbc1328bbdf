"""The calibrated clock: each variant's step cost, measured with the variants' compiled steps
interleaved in one process, so that a busy machine slows every variant alike and its load cannot
flip an equal-time comparison.

    cost(v) = the CALIBRATION_QUANTILE quantile, over rounds in which every variant runs one burst
    of its steps,
              of v's burst time divided by its burst's length k_v,
    calibrated_time(run) = iterations(run) x cost(variant of run).

A burst is k_v consecutive steps, k_v chosen so that a burst takes about BURST_SECONDS: a single
step of a sub-millisecond variant timed between other variants' steps runs with caches the others
filled, and measured 1.4 to 1.7 times what it costs in its own run (Adam, L-BFGS and K-FAC on the
toy), which would have given the fast variants fewer iterations than they get when they train.

A low quantile is the cost on the quietest rounds: a step that another process delays takes longer,
never shorter, so the low quantile is what the step itself costs (AlgoPerf and `make bench` time
interleaved for the same reason). docs/decisions.md ("Timing") gives the rule and its limits: step
costs that depend on the data (L-BFGS's line search, a float64 retry of a failed factorisation) are
counted at the calibrated cost, and on a GPU the step is timed the same way (dispatch until the
results are ready).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from physgrad.comparison.spec import Variant
from physgrad.errors import UserError

CALIBRATION_QUANTILE = 0.2
CALIBRATION_FILE = "calibration.json"
BURST_SECONDS = 0.05  # the length of one variant's turn in a round
ROUNDS = 30  # at least this many rounds ...
MIN_SECONDS = 3.0  # ... and this many seconds of steps in all ...
MAX_SECONDS = 60.0  # ... but no more than this (slow steps: fewer rounds)


def calibrate(
    configs: dict,
    seed: int,
    rounds: int = ROUNDS,
    min_seconds: float = MIN_SECONDS,
    max_seconds: float = MAX_SECONDS,
) -> dict:
    """{name: step cost in seconds} for every composed config (a variant each; refused ones raise
    UserError), from their compiled training steps (as `physgrad run` builds them, one seed) timed
    in turn, one step each per round, after one untimed step each; plus the machine and the samples'
    spread. Each step advances its own state, so a rule whose state changes its cost (damping, line
    searches) is timed along its trajectory."""
    from physgrad.machine import load_average, machine_attributes
    from physgrad.timing import compiled_step, interleaved_times

    steps = {}
    for name, cfg in configs.items():
        steps[name] = compiled_step(cfg, [seed])[-1]
    load_start = load_average()
    probe = interleaved_times(
        list(steps.values()), 3, 0.0, warmup=True, max_seconds=max_seconds / 4
    )
    lengths = [max(1, math.ceil(BURST_SECONDS / max(float(np.median(t)), 1e-9))) for t in probe]

    def burst(step: Callable[[], None], length: int) -> Callable[[], None]:
        def run() -> None:
            for _ in range(length):
                step()

        return run

    bursts = [burst(step, length) for step, length in zip(steps.values(), lengths)]
    times = interleaved_times(bursts, rounds, min_seconds, warmup=False, max_seconds=max_seconds)
    costs = {}
    for name, samples, length in zip(steps, times, lengths):
        samples = np.asarray(samples) / length
        costs[name] = {
            "step_seconds": float(np.quantile(samples, CALIBRATION_QUANTILE)),
            "median_seconds": float(np.median(samples)),
            "rounds": int(samples.size),
            "burst_steps": length,
        }
    return {
        "quantile": CALIBRATION_QUANTILE,
        "costs": costs,
        "load_start": load_start,
        "load_end": load_average(),
        "machine": machine_attributes(),
    }


def read_calibration(path: Path, names: list[str]) -> dict | None:
    """The stored calibration if it is whole: a quantile in (0, 1), load averages, the machine, and
    for every one of names a step cost of at least MIN_STEP_COST (a microsecond) and below an hour,
    its median and rounds; else None (calibrate again). A file that may come from someone else is
    read as data, at most 1 MB."""
    from physgrad.runner import MIN_STEP_COST

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

    try:
        with open(path, "rb") as file:
            stored = json.loads(file.read(1 << 20).decode())
        whole = (
            isinstance(stored, dict)
            and finite(stored.get("quantile"))
            and 0 < stored["quantile"] < 1
            and finite(stored.get("load_start"))
            and finite(stored.get("load_end"))
            and isinstance(stored.get("machine"), dict)
            and isinstance(stored.get("costs"), dict)
            and all(
                isinstance(stored["costs"].get(name), dict)
                and seconds(stored["costs"][name].get("step_seconds"))
                and seconds(stored["costs"][name].get("median_seconds"))
                and isinstance(stored["costs"][name].get("rounds"), int)
                for name in names
            )
        )
    except (OSError, ValueError):
        return None
    return stored if whole else None


def write_calibration(path: Path, calibration: dict) -> None:
    from physgrad.files import replace_file

    replace_file(Path(path), json.dumps(calibration, indent=1).encode())


def calibrated_clock(
    folder: Path,
    variants: list[Variant],
    seed: int,
    given: str | None,
    say: Callable[[str], object],
) -> dict:
    """Each variant's step cost (calibrate), measured once per study and stored in its folder (a
    resumed study reuses it), or taken from a given calibration.json (compare.calibration); every
    job of a variant then runs on the calibrated clock with that cost."""
    from omegaconf import open_dict

    path = folder / CALIBRATION_FILE
    names = [v.name for v in variants]
    if given is not None:
        calibration = read_calibration(Path(given), names)
        if calibration is None:
            raise UserError(
                f"compare.calibration={given}: not a calibration.json with a step cost for every "
                f"variant ({', '.join(names)}); leave it out to calibrate"
            )
        write_calibration(path, calibration)
    calibration = read_calibration(path, names)
    if calibration is None:
        say(f"calibrating the step costs of {len(variants)} variants, interleaved in one process")
        configs = {}
        for variant in variants:
            cfg = variant.config.copy()
            with open_dict(cfg):
                del cfg["hydra"]
            configs[variant.name] = cfg
        calibration = calibrate(configs, seed)
        write_calibration(path, calibration)
    for variant in variants:
        cost = float(calibration["costs"][variant.name]["step_seconds"])
        variant.job_values = {"trainer.step_cost": cost, "trainer.clock": "calibrated"}
    return calibration
