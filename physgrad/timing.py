"""Timing training steps: the compiled step exactly as `physgrad run` builds it, and wall times of
several functions called in turn. Used by the calibrated clock (physgrad.comparison.calibration) and
`make bench` (physgrad.bench)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from physgrad.optim import UpdateRule
    from physgrad.tasks import Scene
    from physgrad.trainer_settings import TrainerSettings
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


class Stepper:
    """one_step(): one training step of a compiled training (blocking until its results are
    ready), from the parameters and optimiser state the previous call left; for a rule that
    searches a line, the steps taken and the line-search evaluations they made (each step's most
    over the seeds, as the runner charges them)."""

    def __init__(self, compiled: CompiledTraining, seeds: Seeds) -> None:
        from physgrad.optim import LINE_SEARCH_LOG

        self.compiled, self.seeds = compiled, seeds
        self.params, self.opt_state = compiled.params, compiled.opt_state
        names = list(getattr(compiled, "log_names", ()))
        self.evaluations_at = names.index(LINE_SEARCH_LOG) if LINE_SEARCH_LOG in names else None
        self.steps, self.evaluations = 0, 0.0

    def __call__(self) -> None:
        import jax
        import numpy as np

        self.params, self.opt_state, logs = self.compiled.step(
            self.params, self.opt_state, np.int32(0), self.seeds.train_keys, self.seeds.train_sets
        )
        jax.block_until_ready(self.params)
        self.steps += 1
        if self.evaluations_at is not None:
            self.evaluations += float(np.max(np.asarray(logs)[:, self.evaluations_at]))


# a line-search evaluation is timed in compiled loops of this many (a single call's dispatch would
# be most of a small scene's evaluation)
EVALUATIONS_PER_CALL = 8


def evaluation_call(scene: Scene, seeds: Seeds, batch_size: int) -> Callable[[], None]:
    """EVALUATIONS_PER_CALL evaluations of what a line search evaluates at a trial point (the value
    and gradient of the batch loss, physgrad.gradients.batch_loss_fn, over the flat parameters of
    the first seed, on one of its batches), one after another in one compiled loop; a call blocks
    until they are done."""
    import jax
    from jax.flatten_util import ravel_pytree

    from physgrad.gradients import batch_loss_fn

    params, unravel = ravel_pytree(seeds.network())
    flat = scene.over_flat_params(unravel)
    train_set = (
        None
        if seeds.train_sets is None
        else jax.tree_util.tree_map(lambda leaf: leaf[0], seeds.train_sets)
    )
    batch = flat.draw_batch(jax.random.fold_in(seeds.train_keys[0], 0), batch_size, train_set)
    value_and_grad = jax.value_and_grad(batch_loss_fn(flat, batch))

    def evaluations(start: jax.Array) -> jax.Array:
        def one(_: int, point: jax.Array) -> jax.Array:
            _, grad = value_and_grad(point)
            return point - 1e-12 * grad  # each at a new point, as a line search's are

        return jax.lax.fori_loop(0, EVALUATIONS_PER_CALL, one, start)

    compiled = jax.jit(evaluations).lower(params).compile()
    return lambda: jax.block_until_ready(compiled(params))


def compiled_step(
    cfg: DictConfig, seeds: list[int]
) -> tuple[TrainerSettings, Scene, UpdateRule, Seeds, CompiledTraining, float, Stepper]:
    """The scene, rule, seeds and compiled training exactly as `physgrad run` builds them, the
    compile time and one_step() (one training step, blocking: a Stepper)."""
    from physgrad.experiment import prepare
    from physgrad.job_spec import checked
    from physgrad.runner import compile_training

    spec = checked(cfg)
    settings = spec.trainer
    scene, rule, stacked = prepare(spec, seeds)
    start = time.perf_counter()
    compiled = compile_training(scene, rule, stacked, settings.batch_size)
    compile_s = time.perf_counter() - start
    return settings, scene, rule, stacked, compiled, compile_s, Stepper(compiled, stacked)


# the calibrated clock (physgrad.comparison.calibration): its rule and measurement
CALIBRATION_QUANTILE = 0.2
BURST_SECONDS = 0.05  # the length of one variant's turn in a round
ROUNDS = 30  # at least this many rounds ...
MIN_SECONDS = 3.0  # ... and this many seconds of steps in all ...
MAX_SECONDS = 60.0  # ... but no more than this (slow steps: fewer rounds)


def program_fingerprint(lowered_step: object, name: str) -> str:
    """A digest of a training step's program as lowered (jax.stages.Lowered.as_text, before XLA
    compiles it: a compiled step read from JAX's compilation cache prints otherwise than one
    compiled anew): two variants with one digest run the same program and get one step cost; a
    step without its text is its own program (its name)."""
    import hashlib

    try:
        text = lowered_step.as_text()
    except Exception:  # noqa: BLE001 - a callable that is not an AOT-compiled jax program
        text = None
    if not isinstance(text, str) or not text:
        return f"variant {name}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def cost_interval(samples: Sequence[float], quantile: float, seed: int = 0) -> tuple[float, float]:
    """How uncertain a step cost (the `quantile` of per-round samples) is: the widest of the
    percentile bootstrap 95% interval over rounds (2,000 resamples) and the costs of the first and
    second half of the rounds alone (a drift in the machine's load during the calibration)."""
    import numpy as np

    samples = np.asarray(samples, float)
    if samples.size < 4:
        return float(samples.min()), float(samples.max())
    rng = np.random.default_rng(seed)
    resampled = np.quantile(
        samples[rng.integers(0, samples.size, (2000, samples.size))], quantile, axis=1
    )
    low, high = np.quantile(resampled, [0.025, 0.975])
    half = samples.size // 2
    halves = [
        float(np.quantile(samples[:half], quantile)),
        float(np.quantile(samples[half:], quantile)),
    ]
    return float(min(low, *halves)), float(max(high, *halves))


def calibrate(
    configs: dict,
    seed: int,
    rounds: int = ROUNDS,
    min_seconds: float = MIN_SECONDS,
    max_seconds: float = MAX_SECONDS,
) -> dict:
    """{name: step cost in seconds, with its interval} for every composed config (a variant each;
    refused ones raise UserError), from their compiled training steps (as `physgrad run` builds
    them, one seed) timed in turn, one burst each per round, after one untimed step each; plus the
    machine and the samples' spread. Variants whose compiled steps are one program (the same
    program_fingerprint: a copy of a rule under another name) are timed once and get one cost, so
    the calibration cannot split them. Each step advances its own state, so a rule whose state
    changes its cost (damping, line searches) is timed along its trajectory.

    A rule whose step updates on a schedule (physgrad.optim.capabilities.ScheduledUpdate: PSGD
    Kron's preconditioner, at every step first, then rarer) is timed twice in the same rounds: its
    step counter set back before every burst to the start (step_seconds: s, a step that updates)
    and to where the schedule reaches its floor p (advanced_seconds: a); its update's cost is

        update_seconds u = (s - a) / (1 - p), kept within [0, s],

    which the runner charges as expected (trainer.update_cost: step t costs s - u + p_t u).

    A rule that searches a line (optax's zoom line search: one value and gradient of the batch
    loss per evaluation, as many as the step needs) has its evaluations counted over the timed
    steps (step_evaluations: e per step) and one evaluation timed in the same rounds
    (evaluation_seconds: v, evaluation_call), kept within [0, s / e]; the runner charges step t
    s - v e + v e_t for the e_t evaluations it made (trainer.evaluation_cost, step_evaluations)."""
    from physgrad.machine import load_average, machine_attributes

    programs, timed, schedules = _timed_programs(configs, seed)

    def burst(key: tuple[str, str], length: int) -> Callable[[], None]:
        call, counter = timed[key]
        schedule = schedules.get(key[0])

        def run() -> None:
            if counter is not None:
                call.opt_state = schedule.at_step(call.opt_state, counter)
            for _ in range(length):
                call()

        return run

    load_start = load_average()
    probe = interleaved_times(
        [burst(key, 1) for key in timed], 3, 0.0, warmup=True, max_seconds=max_seconds / 4
    )
    lengths = {
        key: max(1, math.ceil(BURST_SECONDS / max(sorted(t)[len(t) // 2], 1e-9)))
        for key, t in zip(timed, probe)
    }
    if schedules:  # an updating step's burst stays within the steps that all update
        lengths |= {
            (program, "step"): min(lengths[program, "step"], schedule.full_steps)
            for program, schedule in schedules.items()
        }
    for (_, kind), (call, _) in timed.items():
        if kind == "step":  # line-search evaluations are counted over the timed steps only
            call.steps, call.evaluations = 0, 0.0
    bursts = [burst(key, lengths[key]) for key in timed]
    seconds = [sorted(t)[len(t) // 2] * lengths[key] for key, t in zip(timed, probe)]
    times = rounds_by_cost(bursts, seconds, rounds, min_seconds, max_seconds)
    measured = _measured_costs(
        {key: [t / lengths[key] for t in samples] for key, samples in zip(timed, times)},
        {key: lengths[key] for key in timed},
        timed,
        schedules,
    )
    return {
        "quantile": CALIBRATION_QUANTILE,
        "costs": {name: dict(measured[programs[name]]) for name in configs},
        "load_start": load_start,
        "load_end": load_average(),
        "machine": machine_attributes(),
    }


def rounds_by_cost(
    bursts: list[Callable[[], None]],
    seconds: list[float],
    rounds: int,
    min_seconds: float,
    max_seconds: float,
) -> list[list[float]]:
    """interleaved_times of the bursts, those whose probed length (seconds) is above
    max_seconds / rounds in rounds of their own after the others, on a budget of their own:
    timed beside the others, a few such bursts would spend max_seconds in one round and leave every
    burst a single sample, no interval on any cost."""
    slow = max_seconds / max(rounds, 1)
    times: list[list[float]] = [[] for _ in bursts]
    for group in (
        [i for i, s in enumerate(seconds) if s <= slow],
        [i for i, s in enumerate(seconds) if s > slow],
    ):
        if group:
            found = interleaved_times(
                [bursts[i] for i in group], rounds, min_seconds, False, max_seconds
            )
            for i, samples in zip(group, found):
                times[i] = samples
    return times


def _timed_programs(configs: dict, seed: int) -> tuple[dict, dict, dict]:
    """What calibrate times: {name: program fingerprint}, {(program, kind): (call, the step counter
    set before a burst, or None)} with kind "step", "advanced" (a scheduled update's floor) or
    "evaluation" (EVALUATIONS_PER_CALL line-search evaluations), and {program: ScheduledUpdate}."""
    from physgrad.optim.capabilities import capabilities, scheduled_update

    programs: dict[str, str] = {}
    timed: dict[tuple[str, str], tuple[Callable[[], None], int | None]] = {}
    schedules: dict[str, object] = {}
    for name, cfg in configs.items():
        settings, scene, _, stacked, compiled, _, one_step = compiled_step(cfg, [seed])
        program = programs[name] = program_fingerprint(
            getattr(compiled, "lowered_step", None), name
        )
        if (program, "step") in timed:
            continue
        optim = cfg["optim"] if isinstance(cfg, Mapping) else {}
        schedule = scheduled_update(optim) if optim else None
        timed[program, "step"] = (one_step, None if schedule is None else 0)
        if schedule is not None:
            schedules[program] = schedule
            timed[program, "advanced"] = (Stepper(compiled, stacked), schedule.floor_step)
        if capabilities(optim).line_search and one_step.evaluations_at is not None:
            call = evaluation_call(scene, stacked, settings.batch_size)
            timed[program, "evaluation"] = (call, None)
    return programs, timed, schedules


def _measured_costs(samples: dict, lengths: dict, timed: dict, schedules: dict) -> dict:
    """{program: its cost} from the per-step samples of every timed (program, kind) (calibrate)."""
    import numpy as np

    measured = {}
    for (program, kind), per_step in samples.items():
        if kind != "step":
            continue
        per_step = np.asarray(per_step)
        low, high = cost_interval(per_step, CALIBRATION_QUANTILE)
        step_seconds = float(np.quantile(per_step, CALIBRATION_QUANTILE))
        measured[program] = {
            "step_seconds": step_seconds,
            "low_seconds": low,
            "high_seconds": high,
            "median_seconds": float(np.median(per_step)),
            "rounds": int(per_step.size),
            "burst_steps": lengths[program, kind],
            "program": program,
        }
        if program in schedules:
            advanced = float(np.quantile(samples[program, "advanced"], CALIBRATION_QUANTILE))
            measured[program] |= update_cost(step_seconds, advanced, schedules[program])
        if (program, "evaluation") in samples:
            stepper = timed[program, "step"][0]
            per_evaluation = np.asarray(samples[program, "evaluation"]) / EVALUATIONS_PER_CALL
            measured[program] |= evaluation_cost(
                step_seconds,
                float(np.quantile(per_evaluation, CALIBRATION_QUANTILE)),
                stepper.evaluations / max(stepper.steps, 1),
            )
    return measured


def evaluation_cost(step_seconds: float, evaluation_seconds: float, per_step: float) -> dict:
    """A line search's cost v of one evaluation, kept within [0, s / e] (a step of e evaluations
    costs at least those), and the e evaluations per step of its calibration (calibrate)."""
    ceiling = step_seconds / per_step if per_step > 0 else evaluation_seconds
    return {
        "evaluation_seconds": float(min(max(evaluation_seconds, 0.0), ceiling)),
        "step_evaluations": float(per_step),
    }


def update_cost(step_seconds: float, advanced_seconds: float, schedule: object) -> dict:
    """A scheduled update's cost u = (s - a) / (1 - p) within [0, s] (calibrate's docstring), with
    the measurements it comes from."""
    floor = schedule.floor
    update = (step_seconds - advanced_seconds) / (1 - floor) if floor < 1 else 0.0
    return {
        "update_seconds": float(min(max(update, 0.0), step_seconds)),
        "advanced_seconds": float(advanced_seconds),
        "advanced_step": int(schedule.floor_step),
        "floor_probability": float(floor),
    }


def write_calibration_of(configs: Mapping, seed: int, folder: Path) -> Path:
    """calibrate() of {name: config} (each a whole run config as plain data, resolved: the door's
    physgrad.job_spec.Calibration) into folder/calibration.json, written by rename; returns its
    path."""
    import json

    from omegaconf import OmegaConf

    from physgrad.files import replace_file

    plain = {str(name): OmegaConf.create(config) for name, config in configs.items()}
    path = Path(folder) / "calibration.json"
    replace_file(path, json.dumps(calibrate(plain, seed), indent=1).encode())
    return path
