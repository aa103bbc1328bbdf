"""From a composed config to a finished run: validate, refuse what does not apply, build, train, write."""

from __future__ import annotations

import logging
from pathlib import Path

import jax
from omegaconf import DictConfig, OmegaConf

import physgrad
from physgrad import UserError
from physgrad.nets import count_params
from physgrad.optim import BACKPROP_MODES, CLIPPING, OPTIMS, build_rule
from physgrad.results import ResultsWriter
from physgrad.runner import Outcome, TrainerSettings, train
from physgrad.tasks import build_scene, traits
from physgrad.validate import choice, number


def check_config(cfg: DictConfig) -> TrainerSettings:
    """Every key the run reads, validated; combinations the scene cannot use are refused with the reason."""
    choice(cfg, "precision", (32, 64))
    number(cfg, "seed", 0, integer=True)
    optim = choice(cfg, "optim.name", OPTIMS)
    number(cfg, "optim.lr", 0, open_low=True)
    if optim in ("hig", "gauss_newton"):
        number(cfg, "optim.tau", 0, 1)
        number(cfg, "optim.kappa")
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


def run_experiment(cfg: DictConfig, out_dir: str | Path) -> tuple[Outcome, Path]:
    """Run one job into out_dir/results.h5; a refused job leaves a file with status refused and the reason."""
    path = Path(out_dir) / "results.h5"
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
    except UserError as error:
        ResultsWriter(path, run_attributes(cfg, cfg.get("unroll") if _has_time_axis(cfg) else None)).finish(
            "refused", str(error))
        return Outcome("refused", str(error), 0, 0.0, {}), path

    params = scene.init_params(init_key)
    writer = ResultsWriter(path, {
        **run_attributes(cfg, scene.steps),
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
