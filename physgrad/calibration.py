"""The calibrated clock: each variant's step cost, measured with the variants' compiled steps interleaved in one
process, so that a busy machine slows every variant alike and its load cannot flip an equal-time comparison.

    cost(v) = the CALIBRATION_QUANTILE quantile of v's step times over rounds in which every variant steps once,
    calibrated_time(run) = iterations(run) x cost(variant of run).

A low quantile is the cost on the quietest rounds: a step that another process delays takes longer, never
shorter, so the low quantile is what the step itself costs (AlgoPerf and `make bench` time interleaved for the
same reason). docs/decisions.md ("Timing") gives the rule and its limits: step costs that depend on the data
(L-BFGS's line search, a float64 retry of a failed factorisation) are counted at the calibrated cost, and on a
GPU the step is timed the same way (dispatch until the results are ready).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

CALIBRATION_QUANTILE = 0.2
CALIBRATION_FILE = "calibration.json"
ROUNDS = 30  # at least this many rounds ...
MIN_SECONDS = 3.0  # ... and this many seconds of steps in all ...
MAX_SECONDS = 60.0  # ... but no more than this (slow steps: fewer rounds)


def calibrate(configs: dict, seed: int, rounds: int = ROUNDS, min_seconds: float = MIN_SECONDS,
              max_seconds: float = MAX_SECONDS) -> dict:
    """{name: step cost in seconds} for every composed config (a variant each; refused ones raise UserError),
    from their compiled training steps (as `physgrad run` builds them, one seed) timed in turn, one step each per
    round, after one untimed step each; plus the machine and the samples' spread. Each step advances its own
    state, so a rule whose state changes its cost (damping, line searches) is timed along its trajectory."""
    from physgrad.bench import _compiled, interleaved_times
    from physgrad.machine import load_average, machine_attributes

    steps = {}
    for name, cfg in configs.items():
        steps[name] = _compiled(cfg, [seed])[-1]
    load_start = load_average()
    times = interleaved_times(list(steps.values()), rounds, min_seconds, warmup=True, max_seconds=max_seconds)
    costs = {}
    for name, samples in zip(steps, times):
        samples = np.asarray(samples)
        costs[name] = {"step_seconds": float(np.quantile(samples, CALIBRATION_QUANTILE)),
                       "median_seconds": float(np.median(samples)), "rounds": int(samples.size)}
    return {"quantile": CALIBRATION_QUANTILE, "costs": costs, "load_start": load_start,
            "load_end": load_average(), "machine": machine_attributes()}


def read_calibration(path: Path, names: list[str]) -> dict | None:
    """The stored calibration if it holds a finite, positive cost for every one of names (else None: calibrate
    again)."""
    try:
        stored = json.loads(Path(path).read_text())
        costs = {name: float(stored["costs"][name]["step_seconds"]) for name in names}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not all(math.isfinite(c) and c > 0 for c in costs.values()):
        return None
    return stored


def write_calibration(path: Path, calibration: dict) -> None:
    from physgrad.results import replace_file

    replace_file(Path(path), json.dumps(calibration, indent=1).encode())
