"""From a composed config to a finished run: validate, refuse what does not apply, build, train, write."""

from __future__ import annotations

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
from physgrad.runner import Outcome, TrainerSettings, train
from physgrad.tasks import build_scene, traits
from physgrad.validate import choice, number


def check_config(cfg: DictConfig) -> TrainerSettings:
    """Every key the run reads, validated; combinations the scene cannot use are refused with the reason."""
    choice(cfg, "precision", (32, 64))
    choice(cfg, "overwrite", (False, True))
    if cfg.get("init_from") is not None and not isinstance(cfg.init_from, str):
        raise UserError(f"init_from={cfg.init_from!r} is not allowed: use the path of a results.h5, or null")
    number(cfg, "seed", 0, integer=True)
    optim = choice(cfg, "optim.name", OPTIMS)
    number(cfg, "optim.lr", 0, open_low=True)
    if optim in ("hig", "gauss_newton"):
        number(cfg, "optim.tau", 0, 1)
        number(cfg, "optim.kappa")
        choice(cfg, "optim.route", ROUTES)
        choice(cfg, "optim.retry_float64", (True, False))
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
    from physgrad.results import read_run

    if not path.exists():
        return None
    try:
        run = read_run(path)
    except ValueError:
        return None
    stored = OmegaConf.create(run.attrs.get("config", "{}"))
    if run.attrs.get("status") != "completed" or comparable_config(stored) != comparable_config(cfg):
        return None
    final = {k: float(v[-1]) for k, v in run.eval.items() if v.size and k not in ("iteration", "wall_time")}
    return Outcome("completed", "already completed: skipped (overwrite=true runs it again)",
                   int(run.attrs.get("iterations", 0)), float(run.attrs.get("train_seconds", 0)), final)


def start_from(path: str, params, scene_name: str) -> tuple[Any, dict]:
    """The final network of the run at path, in the structure and dtype of params, and attributes that record
    where it came from; UserError (one line) if it is missing or does not fit this scene's network."""
    from physgrad.results import read_params, read_run

    if not Path(path).is_file():
        raise UserError(f"init_from={path}: no such file: give the results.h5 of an earlier run")
    try:
        flat = read_params(path)
        source = read_run(path)
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


def run_experiment(cfg: DictConfig, out_dir: str | Path) -> tuple[Outcome, Path]:
    """Run one job into out_dir/results.h5; a refused job leaves a file with status refused and the reason.
    A job that completed before with the same config is not run again unless overwrite=true."""
    path = Path(out_dir) / "results.h5"
    if not cfg.get("overwrite", False):
        previous = finished_before(path, cfg)
        if previous is not None:
            return previous, path
    try:
        settings = check_config(cfg)
        set_precision(cfg.precision)
        logging.getLogger("jax").setLevel(logging.WARNING)
        data_key, init_key, train_key = jax.random.split(jax.random.PRNGKey(cfg.seed), 3)
        scene = build_scene(cfg.task, data_key, cfg.get("unroll"))
        if scene.train_size is not None and settings.batch_size > scene.train_size:
            raise UserError(f"trainer.batch_size={settings.batch_size} is larger than the training set: use at most "
                            f"{scene.train_size} (task.train_size)")
        rule = build_rule(cfg.optim)
        params, origin = scene.init_params(init_key), {}
        if cfg.get("init_from"):
            params, origin = start_from(cfg.init_from, params, cfg.task.name)
    except UserError as error:
        ResultsWriter(path, run_attributes(cfg, cfg.get("unroll") if _has_time_axis(cfg) else None)).finish(
            "refused", str(error))
        return Outcome("refused", str(error), 0, 0.0, {}), path

    attrs = run_attributes(cfg, scene.steps)
    if origin:
        attrs["variant"] += f" (from {origin['init_variant']})"
    writer = ResultsWriter(path, {
        **attrs, **origin,
        "batch_size": settings.batch_size,
        "n_params": count_params(params),
        "device": str(jax.devices()[0].device_kind),
    })
    label = f"{cfg.task.name}/{cfg.optim.name} seed {cfg.seed}"
    outcome = train(scene, rule, params, settings, writer, train_key, label=label)
    from physgrad.plots import plot_run  # matplotlib only once training is over
    from physgrad.results import read_run

    plot_run(read_run(path), path.with_name("loss.png"))
    return outcome, path
