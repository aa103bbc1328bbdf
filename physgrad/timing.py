"""Timing training steps: the compiled step exactly as `physgrad run` builds it, and wall times of
several functions called in turn. Used by the calibrated clock (physgrad.comparison.calibration) and
`make bench` (physgrad.bench)."""

from __future__ import annotations

import time
from collections.abc import Callable
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
