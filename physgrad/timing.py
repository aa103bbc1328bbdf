"""Timing training steps: the compiled step exactly as `physgrad run` builds it, and wall times of
several functions called in turn. Used by the calibrated clock (physgrad.comparison.calibration) and
`make bench` (physgrad.bench)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from physgrad.optim import UpdateRule
    from physgrad.runner import TrainerSettings
    from physgrad.tasks import Scene
    from physgrad.training import CompiledTraining, Seeds


def interleaved_times(
    fns: list[Callable[[], object]],
    repeats: int,
    min_seconds: float,
    warmup: bool = True,
    max_seconds: float = 120.0,
) -> list[list[float]]:
    """The wall times of each fn() (which must block until its results are ready), called in turn,
    one call each per round, so that a step and its baseline see the same machine (on 2 shared cores
    the speed drifts by tens of percent between measurements taken a few seconds apart). At least
    `repeats` rounds and min_seconds, but stopping once max_seconds are spent (slow steps: fewer,
    long repeats), after one untimed warm-up call each."""
    if warmup:
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    spent = 0.0
    while not times[0] or (
        (len(times[0]) < repeats or spent < min_seconds)
        and spent < max_seconds
        and len(times[0]) < 100_000
    ):
        for fn, fn_times in zip(fns, times):
            start = time.perf_counter()
            fn()
            fn_times.append(time.perf_counter() - start)
            spent += fn_times[-1]
    return times


def compiled_step(
    cfg: DictConfig, seeds: list[int]
) -> tuple[TrainerSettings, Scene, UpdateRule, Seeds, CompiledTraining, float, Callable[[], None]]:
    """The scene, rule, seeds and compiled training exactly as `physgrad run` builds them, the
    compile time and one_step() (one training step, blocking)."""
    import jax
    import numpy as np

    from physgrad.experiment import prepare
    from physgrad.refusals import check_config
    from physgrad.runner import compile_training

    settings = check_config(cfg)
    scene, rule, stacked = prepare(cfg, seeds, settings)
    start = time.perf_counter()
    compiled = compile_training(scene, rule, stacked, settings.batch_size)
    compile_s = time.perf_counter() - start

    state = [compiled.params, compiled.opt_state]

    def one_step() -> None:
        state[0], state[1], _ = compiled.step(
            state[0], state[1], np.int32(0), stacked.train_keys, stacked.train_sets
        )
        jax.block_until_ready(state[0])

    return settings, scene, rule, stacked, compiled, compile_s, one_step


# the calibrated clock (physgrad.comparison.calibration): its rule and measurement
CALIBRATION_QUANTILE = 0.2
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
    import numpy as np

    from physgrad.machine import load_average, machine_attributes

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


def write_calibration_of(configs: Mapping, seed: int, folder: Path) -> Path:
    """calibrate() of {name: config} (each a whole resolved run config) into
    folder/calibration.json, written by rename; returns its path."""
    import json

    from omegaconf import OmegaConf

    from physgrad.files import replace_file

    plain = {
        str(name): OmegaConf.create(OmegaConf.to_container(config, resolve=True))
        for name, config in configs.items()
    }
    path = Path(folder) / "calibration.json"
    replace_file(path, json.dumps(calibrate(plain, seed), indent=1).encode())
    return path
