"""From a composed config to a finished run: validate, refuse what does not apply, build, train,
write."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from omegaconf import DictConfig, OmegaConf

from physgrad.errors import FolderOwned, UserError
from physgrad.files import own_folder
from physgrad.gradients import JacobianPass
from physgrad.interrupts import stop_on_signals
from physgrad.machine import machine_attributes
from physgrad.nets import count_params
from physgrad.optim import UpdateRule, build_rule, matrix_leaves, needs_value_arguments
from physgrad.optim.capabilities import batches_over_seeds, capabilities
from physgrad.results import ResultsWriter, read_final, record_outcome
from physgrad.resume import finished_before, start_from
from physgrad.runner import Outcome, TrainerSettings, train
from physgrad.sweeps import mark_stopped, watching
from physgrad.tasks import Scene, build_scene
from physgrad.training import Seeds, stack
from physgrad.validate import choice, finite_numbers, flag, number
from physgrad.version import __version__

log = logging.getLogger("physgrad")
SEED_LIMIT = 2**32
# seeds trained together in one vectorised step: each has its own data, network and results file, so
# memory and the files grow with it; more seeds than this are a sweep (seed=0,1,... -m), which also
# runs in parallel
SEEDS_LIMIT = 1024


def check_config(cfg: DictConfig) -> TrainerSettings:
    """The run's own keys (top level and trainer) validated, NaN and infinity refused everywhere,
    and an unroll length refused for a scene without time (its task config has no `unroll`). The
    task and optim settings are checked by the code that reads them (the scene's build function, the
    update rule's factory)."""
    finite_numbers(OmegaConf.to_container(cfg, resolve=True))
    choice("precision", cfg.get("precision"), (32, 64))
    flag("overwrite", cfg.get("overwrite"))
    flag("trainer.validation", cfg.trainer.get("validation", False))
    if cfg.get("init_from") is not None and (
        not isinstance(cfg.init_from, str) or not cfg.init_from.strip()
    ):
        raise UserError(
            f"init_from={cfg.init_from!r} is not allowed: use the path of a results.h5, or leave "
            "init_from out (null) to start from a fresh network"
        )
    # PRNGKey(seed) keeps the low 32 bits of the seed: seeds 2^32 apart would be the same run
    number("seed", cfg.get("seed"), 0, SEED_LIMIT, integer=True)
    number("seeds", cfg.get("seeds"), 1, SEEDS_LIMIT + 1, integer=True)
    if cfg.seed + cfg.seeds > SEED_LIMIT:
        raise UserError(
            f"seed={cfg.seed} with seeds={cfg.seeds} reaches seed {cfg.seed + cfg.seeds - 1}: "
            "seeds must "
            f"stay below {SEED_LIMIT} (2^32), so use seed <= {SEED_LIMIT - cfg.seeds}"
        )
    for section in ("task", "optim"):
        if not isinstance(cfg[section].get("name"), str) or not cfg[section].name:
            raise UserError(
                f"the {section} config has no name: add one (e.g. name: mine), it labels results"
            )
    if cfg.get("unroll") is not None:
        if "unroll" not in cfg.task:
            raise UserError(
                f"task={cfg.task.name} has no time axis: remove unroll={cfg.unroll} "
                "(unroll applies to temporal scenes only)"
            )
        number("unroll", cfg.unroll, 1, integer=True)
    elif "unroll" in cfg.task:
        number("task.unroll", cfg.task.unroll, 1, integer=True)
    return TrainerSettings.from_config(cfg.trainer)


def effective_unroll(cfg: DictConfig) -> int | None:
    """The number of time steps: the top-level unroll, else the scene's own; None for a scene
    without time."""
    if "unroll" not in cfg.task:
        return None
    return cfg.unroll if cfg.get("unroll") is not None else cfg.task.unroll


def check_applies(scene: Scene, cfg: DictConfig) -> None:
    """Refuse a backprop-through-time mode on a scene whose network does not act inside a rollout:
    the scene's
    traits decide, whatever the rule."""
    backprop = cfg.optim.get("backprop")
    if backprop is None or scene.closed_loop:
        return
    if not scene.time_axis:
        why = "has no time axis"
    elif "closed_loop" in cfg.task:
        why = "has an open-loop controller: set task.closed_loop=true, or"
    else:
        why = "has an open-loop controller"
    raise UserError(
        f"optim={cfg.optim.name} needs a closed-loop controller in time "
        f"(optim.backprop={backprop}), "
        f"and task={cfg.task.name} {why}{':' if why[-1] != ',' else ''} use a rule without "
        "optim.backprop (adam, gd, gauss_newton, hig)"
    )


def set_precision(bits: int) -> None:
    """Set every time: Hydra's launchers reuse processes, so a previous job's x64 flag would
    leak."""
    jax.config.update("jax_enable_x64", bits == 64)


PRESET_BACKPROP = {"bptt": "R", "stable_bptt": "C"}


def variant_label(optim_cfg) -> str:
    """The optim name, plus the backprop mode and clipping where they differ from what the name
    implies (so that a report keeps `bptt` with mode M apart from plain `bptt`): e.g. bptt[M],
    stable_bptt[clip=norm], lion[C]."""
    name = str(optim_cfg.get("name", "?"))
    backprop, clip = optim_cfg.get("backprop"), optim_cfg.get("clip", "none")
    marks = [] if backprop == PRESET_BACKPROP.get(name) else [str(backprop)]
    marks += [] if clip == "none" else [f"clip={clip}"]
    return f"{name}[{','.join(marks)}]" if marks else name


def run_attributes(cfg: DictConfig, unroll: int | None = None) -> dict:
    """Root attributes of results.h5; unroll is the effective number of time steps (temporal scenes
    only)."""
    attrs = {
        "task": str(cfg.task.get("name", "?")),
        "optim": str(cfg.optim.get("name", "?")),
        "variant": variant_label(cfg.optim),
        "seed": cfg.seed if isinstance(cfg.seed, int) else str(cfg.seed),
        "precision": str(cfg.precision),
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "physgrad_version": __version__,
        "jax_version": jax.__version__,
    }
    if unroll is not None:
        attrs["unroll"] = unroll
    return attrs


def seed_paths(cfg: DictConfig, out_dir: str | Path) -> list[tuple[int, Path]]:
    """(seed, results file) of every seed a job trains: out_dir/results.h5 for one seed,
    out_dir/seed=<s>/ results.h5 for seeds > 1 (seed, seed + 1, ...)."""
    count = cfg.get("seeds", 1)
    count = count if isinstance(count, int) and count > 0 else 1
    if count == 1:
        return [(cfg.seed, Path(out_dir) / "results.h5")]
    return [
        (cfg.seed + i, Path(out_dir) / f"seed={cfg.seed + i}" / "results.h5") for i in range(count)
    ]


def job_outcome(outcomes: list[Outcome]) -> Outcome:
    """One outcome for a job of several seeds: the first that did not complete, else the first
    seed's."""
    if len(outcomes) == 1:
        return outcomes[0]
    worst = next((o for o in outcomes if o.status != "completed"), outcomes[0])
    reasons = "; ".join(f"seed #{i}: {o.reason}" for i, o in enumerate(outcomes) if o.reason)
    return Outcome(
        worst.status, reasons or None, worst.iterations, worst.train_seconds, outcomes[0].final_eval
    )


def build_seeds(
    cfg: DictConfig, seeds: list[int], batch_size: int, checkpoint: Callable[[], None] | None = None
) -> tuple[Scene, Seeds]:
    """The scene and, stacked over the given seeds, what differs between them: data (test set, fixed
    training set), initial network and minibatch key, each from its own split of PRNGKey(seed).
    UserError if the batch does not fit the training set."""
    keys = [
        jax.random.split(jax.random.PRNGKey(seed), 3) for seed in seeds
    ]  # data, init, minibatches
    scenes = []
    for key in keys:  # checkpoint (a pending stop) between seeds: a thousand of them take a while
        if checkpoint is not None:
            checkpoint()
        scenes.append(build_scene(cfg.task, key[0], effective_unroll(cfg)))
    scene = scenes[0]  # the physics and the network; only the data differ between seeds
    if scene.train_size is not None and batch_size > scene.train_size:
        raise UserError(
            f"trainer.batch_size={batch_size} is larger than the training set: use at most "
            f"{scene.train_size} (task.train_size)"
        )
    validation = None
    if cfg.trainer.get("validation", False):
        validation = stack([validation_set(cfg, s, key[0]) for s, key in zip(scenes, keys)])
    return scene, Seeds(
        params=stack([scene.init_params(key[1]) for key in keys]),
        train_keys=jnp.stack([key[2] for key in keys]),
        train_sets=stack([s.train_set for s in scenes]),
        test_sets=stack([s.test_set for s in scenes]),
        validation_sets=validation,
    )


VALIDATION_KEY = 1  # fold_in(data key, 1): the data key of the default validation set


def validation_set(cfg: DictConfig, scene: Scene, data_key):
    """The scene's validation_set if it has one; else the test set of the same scene built from
    another data key (fold_in(data key, VALIDATION_KEY)): held-out samples of the same distribution,
    disjoint from the test set by construction. UserError if that set equals the test set (a scene
    whose data ignore the key)."""
    if scene.validation_set is not None:
        return scene.validation_set
    other = build_scene(
        cfg.task, jax.random.fold_in(data_key, VALIDATION_KEY), effective_unroll(cfg)
    ).test_set
    same = jax.tree_util.tree_structure(other) == jax.tree_util.tree_structure(
        scene.test_set
    ) and all(
        a.shape == b.shape and bool(jnp.array_equal(a, b))
        for a, b in zip(jax.tree_util.tree_leaves(other), jax.tree_util.tree_leaves(scene.test_set))
    )
    if same:
        raise UserError(
            f"task={cfg.task.get('name')} builds the same test set from every data key, so it has "
            "no "
            "validation data: give its Scene a validation_set, or draw its data from `key` "
            "(docs/extending.md)"
        )
    return other


def check_scene_values(scene: Scene, seeds: Seeds, name: str) -> None:
    """What a scene gives is what the runner needs (UserError, one line, else): a per-sample loss
    that is one real floating-point number (an integer loss has no gradient, a vector would be
    averaged silently), and held-out data without NaN or infinity (a test loss over them would be
    NaN from the start)."""
    params = seeds.network()
    sample = jax.tree_util.tree_map(lambda leaf: leaf[0, 0], seeds.test_sets)
    output = scene.sample_output if scene.test_output is None else scene.test_output
    loss = jax.eval_shape(lambda p, s: scene.sample_loss(output(p, s), s), params, sample)
    if not hasattr(loss, "shape") or loss.shape != ():
        raise UserError(
            f"task={name}: sample_loss returns {getattr(loss, 'shape', type(loss).__name__)} per "
            "sample; it must return one number (reduce it, e.g. jnp.sum or jnp.mean)"
        )
    if not jnp.issubdtype(loss.dtype, jnp.floating):
        raise UserError(
            f"task={name}: sample_loss returns {loss.dtype}; it must be a real float (compute it "
            "in "
            "floating point; for a complex output take abs() or .real)"
        )
    for which, data in (("test_set", seeds.test_sets), ("validation_set", seeds.validation_sets)):
        bad = sum(
            int(jnp.size(leaf) - jnp.isfinite(leaf).sum())
            for leaf in jax.tree_util.tree_leaves(data)
            if jnp.issubdtype(leaf.dtype, jnp.inexact)
        )
        if bad:
            raise UserError(
                f"task={name}: its {which} holds {bad} values that are NaN or infinite: a held-out "
                "loss over it is not a number; fix the data the scene's build function draws"
            )


def prepare(
    cfg: DictConfig,
    seed_list: list[int],
    settings: TrainerSettings,
    checkpoint: Callable[[], None] | None = None,
) -> tuple[Scene, UpdateRule, Seeds]:
    """Precision set, the update rule and the seeds' scenes built, and what does not apply refused
    (UserError): everything a run (and `make bench`) does before compiling."""
    set_precision(cfg.precision)
    logging.getLogger("jax").setLevel(logging.WARNING)
    rule = build_rule(cfg.optim)
    scene, seeds = build_seeds(cfg, seed_list, settings.batch_size, checkpoint)
    check_scene_values(scene, seeds, cfg.task.name)
    check_applies(scene, cfg)
    kind = capabilities(cfg.optim)
    if kind.needs_matrices and not matrix_leaves(seeds.network()):
        raise UserError(
            f"optim={cfg.optim.name} orthogonalises the network's matrices and "
            f"task={cfg.task.name}'s "
            "network has none (no 2-D parameters): its Muon partition would be empty; use adam"
        )
    if not rule.uses_jacobian and needs_value_arguments(rule.transform, seeds.network()):
        rule = rule._replace(gradient=dataclasses.replace(rule.gradient, with_value=True))
    if rule.uses_jacobian:
        # a training sample: what J is taken of (a scene's test samples may hold other fields)
        sample = jax.tree_util.tree_map(
            lambda leaf: leaf[0], scene.sample_train(jax.random.PRNGKey(0), 1)
        )
        rule = rule._replace(
            gradient=JacobianPass.for_network(
                scene.sample_output, seeds.network(), sample, with_value=rule.gradient.with_value
            )
        )
        if kind.needs_layer_factors and rule.gradient.plan is None:
            raise UserError(
                f"optim={cfg.optim.name} needs the Jacobian in layer factors and "
                f"task={cfg.task.name} "
                f"gives it per sample ({rule.gradient.why_per_sample}): use levenberg_marquardt or "
                "gauss_newton"
            )
    return scene, rule, seeds


def set_aside_unreadable(path: Path) -> Path | None:
    """A results.h5 that cannot be read (damaged, or not a physgrad file) is renamed, never deleted,
    so the job can run again; returns the new name."""
    if not path.exists():
        return None
    try:
        read_final(path)
        return None
    except ValueError:
        aside = path.with_name(f"{path.name}.unreadable-{time.strftime('%Y%m%dT%H%M%S')}")
        os.replace(path, aside)
        log.warning("%s could not be read: set aside as %s, the job runs again", path, aside.name)
        return aside


def run_experiment(
    cfg: DictConfig,
    out_dir: str | Path,
    sweep: Path | None = None,
    on_owned: Callable[[], None] | None = None,
) -> tuple[Outcome, Path]:
    """Run one job into out_dir/results.h5 (seeds > 1: one file per seed under out_dir/seed=<s>/,
    trained together in one vectorised step); a refused job leaves a file with status refused and
    the reason. A job that completed before with the same config is not run again unless
    overwrite=true. The job holds out_dir for its whole duration (another live process writing
    there: refused, nothing touched) and handles SIGINT and SIGTERM from start-up until its files
    are final; in a sweep (sweep: its folder) a signal to the job stops the sweep, and the sweep's
    stop reaches the job (physgrad.sweeps). on_owned runs once the folder is held, before anything
    else is written into it (the command line's provenance, .hydra/). A failure before training
    leaves files with status failed; ResultsWriteError if they cannot be written."""
    try:
        on_first = None if sweep is None else (lambda name: mark_stopped(sweep, name))
        with own_folder(out_dir), stop_on_signals(on_first) as stop, watching(sweep, stop):
            if on_owned is not None:
                on_owned()
            seeds = cfg.get("seeds", 1)
            if (
                isinstance(seeds, int) and seeds > SEEDS_LIMIT
            ):  # refused before one file per seed is named
                return Outcome(
                    "refused",
                    f"seeds={seeds} is more than {SEEDS_LIMIT} seeds in one process: sweep "
                    f"them instead (physgrad run -m seed=0,1,2,...), or use seeds <= {SEEDS_LIMIT}",
                    0,
                    0.0,
                    {},
                ), Path(out_dir)
            paths = seed_paths(cfg, out_dir)
            where = paths[0][1] if len(paths) == 1 else Path(out_dir)
            if cfg.get("init_from") and any(
                Path(str(cfg.init_from)).resolve() == path.resolve() for _, path in paths
            ):
                # refused without a results file: writing one would destroy the network it names
                return Outcome(
                    "refused",
                    f"init_from={cfg.init_from} is this job's own results file, which the "
                    "run would overwrite: start from another run's results.h5",
                    0,
                    0.0,
                    {},
                ), where
            return run_owned(cfg, paths, stop), where
    except FolderOwned as error:
        return Outcome("refused", str(error), 0, 0.0, {}), Path(out_dir) / (
            "results.h5" if cfg.get("seeds", 1) == 1 else ""
        )


def run_owned(cfg: DictConfig, paths: list[tuple[int, Path]], stop) -> Outcome:
    """run_experiment, once the job folder is held and signals are handled. Until training starts a
    signal ends the job at once (resume checks, building many seeds' data: nothing is half done
    there), its files saying interrupted; from then on the training loop acts on it between
    steps."""
    stop.raising = True
    try:
        stop.raise_if_stopped()  # a signal that came before
        return set_up_and_train(cfg, paths, stop)
    except KeyboardInterrupt as interrupt:
        stop.raising = False
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} before training"
        for seed, path in paths:
            if stop.at_once:  # a second signal: stop writing files too
                break
            with contextlib.suppress(OSError):
                record_outcome(
                    path,
                    {**run_attributes(cfg, effective_unroll(cfg)), "seed": seed},
                    "interrupted",
                    why,
                )
        return Outcome("interrupted", why, 0, 0.0, {})
    finally:
        stop.raising = False


def set_up_and_train(cfg: DictConfig, paths: list[tuple[int, Path]], stop) -> Outcome:
    for _, path in paths:
        stop.raise_if_stopped()
        set_aside_unreadable(path)
    if not cfg.get("overwrite", False):
        previous = []
        for _, path in paths:
            stop.raise_if_stopped()
            previous.append(finished_before(path, cfg))
        if all(previous):
            return job_outcome(previous)
    try:
        settings = check_config(cfg)
        if len(paths) > 1 and cfg.get("init_from"):
            raise UserError(
                f"init_from starts one network: use seeds=1 (not seeds={len(paths)}) with it"
            )
        if len(paths) > 1 and not batches_over_seeds(cfg.optim):
            # its lax.cond traced under x64 does not batch under vmap (jax 0.10): a known limitation
            raise UserError(
                f"seeds={len(paths)} cannot retry failed factorisations in float64: add "
                "optim.retry_float64=false, or use seeds=1"
            )
        scene, rule, seeds = prepare(
            cfg, [seed for seed, _ in paths], settings, stop.raise_if_stopped
        )
        origin = {}
        if cfg.get("init_from"):
            first, origin = start_from(cfg.init_from, seeds.network(), cfg.task.name)
            seeds = dataclasses.replace(seeds, params=stack([first]))
    except UserError as error:
        stop.raising = False
        for seed, path in paths:
            record_outcome(
                path,
                {**run_attributes(cfg, effective_unroll(cfg)), "seed": seed},
                "refused",
                str(error),
            )
        return Outcome("refused", str(error), 0, 0.0, {})
    except Exception as error:  # before training: the files say failed, with the reason
        stop.raising = False
        reason = f"{type(error).__name__}: {error}".splitlines()[0]
        for seed, path in paths:
            record_outcome(
                path, {**run_attributes(cfg, effective_unroll(cfg)), "seed": seed}, "failed", reason
            )
        raise

    attrs = run_attributes(cfg, scene.unroll)
    if rule.uses_jacobian:
        attrs["jacobian"] = rule.gradient.name
    if origin:
        attrs["variant"] += f" (from {origin['init_variant']})"
    if len(paths) > 1:
        attrs["wall_time_shared_by"] = len(
            paths
        )  # every seed's wall_time is the one shared vectorised run
    writers = [
        ResultsWriter(
            path,
            {
                **attrs,
                **origin,
                "seed": seed,
                "batch_size": settings.batch_size,
                "n_params": count_params(seeds.network()),
                **machine_attributes(),
            },
        )
        for seed, path in paths
    ]
    label = f"{cfg.task.name}/{cfg.optim.name} seed {cfg.seed}" + (
        f" (+{len(paths) - 1})" if len(paths) > 1 else ""
    )
    stop.raising = False  # the training loop acts on signals between steps
    outcomes = train(scene, rule, seeds, writers, settings, label=label, stop=stop)
    try:
        draw_run_figures(scene, seeds, writers, outcomes, stop)
    except Exception as error:  # noqa: BLE001 - the results are final: a figure (a scene's own, too) is no failure
        log.warning(
            "figures of %s not drawn: %s: %s",
            paths[0][1].parent,
            type(error).__name__,
            str(error).splitlines()[0] if str(error) else "",
        )
    return job_outcome(outcomes)


FIGURE_SEEDS = 8  # per-seed figures drawn for a job of many seeds (about half a second each)


def draw_run_figures(
    scene: Scene, seeds: Seeds, writers: list[ResultsWriter], outcomes: list[Outcome], stop=None
) -> None:
    """loss.png per seed (the first FIGURE_SEEDS of a job of more: physgrad report draws them all
    together), and the scene's own figure of the trained network where it has one; none for a run
    written aside of a completed results.h5 it did not replace (the figures beside it are that
    run's). A signal (stop) ends the drawing: the results are final already."""
    from physgrad.plots import plot_run  # matplotlib only once training is over
    from physgrad.results import read_params, read_run

    unravel = ravel_pytree(seeds.network())[1]
    if len(writers) > FIGURE_SEEDS:
        log.info(
            "loss.png drawn for the first %d of %d seeds: physgrad report %s draws them all",
            FIGURE_SEEDS,
            len(writers),
            writers[0].path.parent.parent,
        )
    for index, writer in enumerate(writers[:FIGURE_SEEDS]):
        if stop is not None and stop.signal_name is not None:
            return
        path = writer.path
        if writer.live != path:
            log.warning(
                "%s kept (completed); this run ended %s and is in %s",
                path,
                outcomes[index].status,
                writer.live.name,
            )
            continue
        plot_run(read_run(path), path.with_name("loss.png"))
        # a network was saved; not after an interrupt, whose user wants the process to end now (an
        # abandoned step may still hold the cores)
        if scene.figure is not None and outcomes[index].status not in ("diverged", "interrupted"):
            test_set = jax.tree_util.tree_map(lambda leaf: leaf[index], seeds.test_sets)
            scene.figure(
                unravel(jnp.asarray(read_params(path))), test_set, path.with_name("scene.png")
            )
