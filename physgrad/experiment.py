"""From a composed config to a finished run: validate, refuse what does not apply, build, train, write."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from omegaconf import DictConfig, OmegaConf

import physgrad
from physgrad import UserError
from physgrad.nets import count_params
from physgrad.optim import BACKPROP_MODES, CLIPPING, OPTIMS, build_rule
from physgrad.optim.spectral import ROUTES
from physgrad.results import ResultsWriter
from physgrad.runner import Outcome, Seeds, TrainerSettings, stack, train
from physgrad.tasks import Scene, build_scene, traits
from physgrad.validate import choice, flag, number


def check_config(cfg: DictConfig) -> TrainerSettings:
    """Every key the run reads, validated; combinations the scene cannot use are refused with the reason."""
    choice(cfg, "precision", (32, 64))
    flag(cfg, "overwrite")
    if cfg.get("init_from") is not None and not isinstance(cfg.init_from, str):
        raise UserError(f"init_from={cfg.init_from!r} is not allowed: use the path of a results.h5, or null")
    number(cfg, "seed", 0, integer=True)
    number(cfg, "seeds", 1, integer=True)
    optim = choice(cfg, "optim.name", OPTIMS)
    number(cfg, "optim.lr", 0, open_low=True)
    if optim in ("hig", "gauss_newton"):
        number(cfg, "optim.tau", 0, 1)
        number(cfg, "optim.kappa")
        choice(cfg, "optim.route", ROUTES)
        flag(cfg, "optim.retry_float64")
    if optim in ("adam", "bptt", "stable_bptt"):
        number(cfg, "optim.b1", 0, 1)
        number(cfg, "optim.b2", 0, 1)
        number(cfg, "optim.eps", 0, open_low=True)
    if optim in ("bptt", "stable_bptt"):
        choice(cfg, "optim.clip", CLIPPING)
        choice(cfg, "optim.backprop", BACKPROP_MODES)

    scene_traits = traits(cfg.task)
    task = cfg.task.name
    if cfg.get("unroll") is not None and not scene_traits.time_axis:
        raise UserError(f"task={task} has no time axis: remove unroll={cfg.unroll} "
                        "(unroll applies to temporal scenes only)")
    if optim in ("bptt", "stable_bptt") and scene_traits.controller != "closed":
        why = ("has no time axis" if not scene_traits.time_axis
               else "has an open-loop controller: set task.controller=feedback, or")
        raise UserError(f"optim={optim} needs a closed-loop controller in time, and task={task} {why}"
                        f"{':' if not scene_traits.time_axis else ''} use adam, gd, gauss_newton or hig")
    if scene_traits.time_axis and cfg.get("unroll") is not None:
        number(cfg, "unroll", 1, integer=True)

    return TrainerSettings(
        iterations=number(cfg, "trainer.iterations", 1, integer=True),
        time_budget=number(cfg, "trainer.time_budget", 0, optional=True, open_low=True),
        eval_every=number(cfg, "trainer.eval_every", 1, integer=True),
        batch_size=number(cfg, "trainer.batch_size", 1, integer=True),
        flush_seconds=number(cfg, "trainer.flush_seconds", 0, open_low=True),
    )


def set_precision(bits: int) -> None:
    """Set every time: Hydra's launchers reuse processes, so a previous job's x64 flag would leak."""
    jax.config.update("jax_enable_x64", bits == 64)


PRESET_BACKPROP = {"bptt": "R", "stable_bptt": "C"}


def variant_label(optim_cfg) -> str:
    """The optim name, plus the backprop mode and clipping where they differ from the preset's (so that a
    report keeps `bptt` with mode M apart from plain `bptt`): e.g. bptt[M], stable_bptt[clip=norm]."""
    name = optim_cfg.name
    if name not in PRESET_BACKPROP:
        return name
    marks = [] if optim_cfg.backprop == PRESET_BACKPROP[name] else [str(optim_cfg.backprop)]
    marks += [] if optim_cfg.clip == "none" else [f"clip={optim_cfg.clip}"]
    return f"{name}[{','.join(marks)}]" if marks else name


def run_attributes(cfg: DictConfig, unroll: int | None = None) -> dict:
    """Root attributes of results.h5; unroll is the effective number of time steps (temporal scenes only)."""
    attrs = {
        "task": cfg.task.name,
        "optim": cfg.optim.name,
        "variant": variant_label(cfg.optim),
        "seed": cfg.seed if isinstance(cfg.seed, int) else str(cfg.seed),
        "precision": str(cfg.precision),
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "physgrad_version": physgrad.__version__,
        "jax_version": jax.__version__,
    }
    if unroll is not None:
        attrs["unroll"] = unroll
    return attrs


def _has_time_axis(cfg) -> bool:
    try:
        return traits(cfg.task).time_axis
    except UserError:
        return False


def comparable_config(cfg: DictConfig) -> str:
    """The resolved config as stored in results.h5, without the keys that do not change what a run computes."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    plain.pop("overwrite", None)
    return OmegaConf.to_yaml(plain)


def finished_before(path: Path, cfg: DictConfig) -> Outcome | None:
    """The outcome recorded at path if that run completed with this same config (a sweep being re-run)."""
    from physgrad.results import read_final

    if not path.exists():
        return None
    try:
        attrs, last_eval = read_final(path)
    except ValueError:
        return None
    stored = OmegaConf.create(attrs.get("config", "{}"))
    if attrs.get("status") != "completed" or comparable_config(stored) != comparable_config(cfg):
        return None
    final = {k: float(v) for k, v in last_eval.items() if k not in ("iteration", "wall_time")}
    return Outcome("completed", "already completed: skipped (overwrite=true runs it again)",
                   int(attrs.get("iterations", 0)), float(attrs.get("train_seconds", 0)), final)


def start_from(path: str, params, scene_name: str) -> tuple[Any, dict]:
    """The final network of the run at path, in the structure and dtype of params, and attributes that record
    where it came from; UserError (one line) if it is missing or does not fit this scene's network."""
    from physgrad.results import Run, read_final, read_params

    if not Path(path).is_file():
        raise UserError(f"init_from={path}: no such file: give the results.h5 of an earlier run")
    try:
        flat = read_params(path)
        source = Run(Path(path), read_final(path)[0], {}, {})  # attributes only, not the curves
    except ValueError as error:
        raise UserError(f"init_from={error}") from None
    own, unravel = ravel_pytree(params)
    if flat.shape != own.shape or source.attrs.get("task") != scene_name:
        raise UserError(f"init_from={path}: that run trained a {source.attrs.get('task')} network with {flat.size} "
                        f"parameters, this one is {scene_name} with {own.size}: use a run of the same scene")
    attrs = {"init_from": str(path), "init_variant": source.variant,
             "init_iterations": int(source.attrs.get("iterations", 0)),
             "init_train_seconds": float(source.attrs.get("train_seconds", 0.0))}
    return unravel(jnp.asarray(flat, own.dtype)), attrs


def seed_paths(cfg: DictConfig, out_dir: str | Path) -> list[tuple[int, Path]]:
    """(seed, results file) of every seed a job trains: out_dir/results.h5 for one seed, out_dir/seed=<s>/
    results.h5 for seeds > 1 (seed, seed + 1, ...)."""
    count = cfg.get("seeds", 1)
    count = count if isinstance(count, int) and count > 0 else 1
    if count == 1:
        return [(cfg.seed, Path(out_dir) / "results.h5")]
    return [(cfg.seed + i, Path(out_dir) / f"seed={cfg.seed + i}" / "results.h5") for i in range(count)]


def job_outcome(outcomes: list[Outcome]) -> Outcome:
    """One outcome for a job of several seeds: the first that did not complete, else the first seed's."""
    if len(outcomes) == 1:
        return outcomes[0]
    worst = next((o for o in outcomes if o.status != "completed"), outcomes[0])
    reasons = "; ".join(f"seed #{i}: {o.reason}" for i, o in enumerate(outcomes) if o.reason)
    return Outcome(worst.status, reasons or None, worst.iterations, worst.train_seconds, outcomes[0].final_eval)


def build_seeds(cfg: DictConfig, seeds: list[int], batch_size: int) -> tuple[Scene, Seeds]:
    """The scene and, stacked over the given seeds, what differs between them: data (test set, fixed training
    set), initial network and minibatch key, each from its own split of PRNGKey(seed). UserError if the batch
    does not fit the training set."""
    keys = [jax.random.split(jax.random.PRNGKey(seed), 3) for seed in seeds]  # data, init, minibatches
    scenes = [build_scene(cfg.task, key[0], cfg.get("unroll")) for key in keys]
    scene = scenes[0]  # the physics and the network; only the data differ between seeds
    if scene.train_size is not None and batch_size > scene.train_size:
        raise UserError(f"trainer.batch_size={batch_size} is larger than the training set: use at most "
                        f"{scene.train_size} (task.train_size)")
    return scene, Seeds(params=stack([scene.init_params(key[1]) for key in keys]),
                        train_keys=jnp.stack([key[2] for key in keys]), train_sets=stack([s.train_set for s in scenes]),
                        test_sets=stack([s.test_set for s in scenes]))


def run_experiment(cfg: DictConfig, out_dir: str | Path) -> tuple[Outcome, Path]:
    """Run one job into out_dir/results.h5 (seeds > 1: one file per seed under out_dir/seed=<s>/, trained
    together in one vectorised step); a refused job leaves a file with status refused and the reason.
    A job that completed before with the same config is not run again unless overwrite=true."""
    paths = seed_paths(cfg, out_dir)
    where = paths[0][1] if len(paths) == 1 else Path(out_dir)
    if not cfg.get("overwrite", False):
        previous = [finished_before(path, cfg) for _, path in paths]
        if all(previous):
            return job_outcome(previous), where
    try:
        settings = check_config(cfg)
        if len(paths) > 1 and cfg.get("init_from"):
            raise UserError(f"init_from starts one network: use seeds=1 (not seeds={len(paths)}) with it")
        if len(paths) > 1 and cfg.optim.get("retry_float64"):
            # its lax.cond traced under x64 does not batch under vmap (jax 0.10): a known limitation
            raise UserError(f"seeds={len(paths)} cannot retry failed factorisations in float64: add "
                            "optim.retry_float64=false, or use seeds=1")
        set_precision(cfg.precision)
        logging.getLogger("jax").setLevel(logging.WARNING)
        scene, seeds = build_seeds(cfg, [seed for seed, _ in paths], settings.batch_size)
        rule = build_rule(cfg.optim)
        origin = {}
        if cfg.get("init_from"):
            first, origin = start_from(cfg.init_from, seeds.network(), cfg.task.name)
            seeds = dataclasses.replace(seeds, params=stack([first]))
    except UserError as error:
        for seed, path in paths:
            attrs = run_attributes(cfg, cfg.get("unroll") if _has_time_axis(cfg) else None)
            ResultsWriter(path, {**attrs, "seed": seed}).finish("refused", str(error))
        return Outcome("refused", str(error), 0, 0.0, {}), where

    attrs = run_attributes(cfg, scene.steps)
    if origin:
        attrs["variant"] += f" (from {origin['init_variant']})"
    if len(paths) > 1:
        attrs["wall_time_shared_by"] = len(paths)  # every seed's wall_time is the one shared vectorised run
    writers = [ResultsWriter(path, {
        **attrs, **origin, "seed": seed,
        "batch_size": settings.batch_size,
        "n_params": count_params(seeds.network()),
        "device": str(jax.devices()[0].device_kind),
    }) for seed, path in paths]
    label = f"{cfg.task.name}/{cfg.optim.name} seed {cfg.seed}" + (f" (+{len(paths) - 1})" if len(paths) > 1 else "")
    outcomes = train(scene, rule, seeds, writers, settings, label=label)
    from physgrad.plots import plot_run  # matplotlib only once training is over
    from physgrad.results import read_run

    for _, path in paths:
        plot_run(read_run(path), path.with_name("loss.png"))
    return job_outcome(outcomes), where
