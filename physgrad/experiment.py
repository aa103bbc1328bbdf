"""From a checked job (physgrad.job_spec.JobSpec) to a finished run: hold the job folder, skip what
finished before, build, refuse what does not apply to the built scene (physgrad.refusals), train,
write. run_experiment takes a composed config through the door (job_spec.check) first."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from omegaconf import DictConfig

from physgrad.errors import FolderOwned, UserError, innermost_cause
from physgrad.files import own_folder
from physgrad.gradients import JacobianPass
from physgrad.interrupts import StopRequest, stop_on_signals
from physgrad.job_spec import JobSpec, Member, Refusal, check
from physgrad.machine import machine_attributes
from physgrad.members import job_outcome, set_precision
from physgrad.nets import count_params
from physgrad.optim import UpdateRule, build_rule, needs_value_arguments
from physgrad.optim.capabilities import capabilities
from physgrad.refusals import (
    check_applies,
    check_layer_factors,
    check_matrices,
    check_scene_values,
    check_seeds_together,
    starts_from_itself,
)
from physgrad.results import ResultsWriter, record_outcome
from physgrad.resume import finished_before, set_aside_unreadable, start_from
from physgrad.run_figures import draw_run_figures
from physgrad.runner import Outcome, quiet_callback_failures, train
from physgrad.sweeps import in_launcher, mark_stopped, watching
from physgrad.tasks import Scene, build_scene
from physgrad.trainer_settings import TrainerSettings
from physgrad.training import Seeds, stack

log = logging.getLogger("physgrad")


def build_seeds(
    spec: JobSpec, seeds: list[int], batch_size: int, checkpoint: Callable[[], None] | None = None
) -> tuple[Scene, Seeds]:
    """The scene and, stacked over the given seeds, what differs between them: data (test set, fixed
    training set), initial network and minibatch key, each from its own split of PRNGKey(seed).
    UserError if the batch does not fit the training set."""
    # data, init, minibatches
    keys = [jax.random.split(jax.random.PRNGKey(seed), 3) for seed in seeds]
    built = {}  # the members of trial_values share one seed: its scene is built once
    for seed, key in zip(seeds, keys):
        if seed in built:
            continue
        if checkpoint is not None:  # a pending stop, between seeds: a thousand take a while
            checkpoint()
        built[seed] = build_scene(spec.task, key[0], spec.unroll)
    scenes = [built[seed] for seed in seeds]
    scene = scenes[0]  # the physics and the network; only the data differ between seeds
    check_batch_size(scene, batch_size)
    validation = None
    if spec.validation:
        validation = stack([validation_set(spec, s, key[0]) for s, key in zip(scenes, keys)])
    return scene, Seeds(
        params=stack([scene.init_params(key[1]) for key in keys]),
        train_keys=jnp.stack([key[2] for key in keys]),
        train_sets=stack([s.train_set for s in scenes]),
        test_sets=stack([s.test_set for s in scenes]),
        validation_sets=validation,
    )


def check_batch_size(scene: Scene, batch_size: int) -> None:
    """UserError if the batch does not fit the scene's training set."""
    if scene.train_size is not None and batch_size > scene.train_size:
        raise UserError(
            f"trainer.batch_size={batch_size} is larger than the training set: use at most "
            f"{scene.train_size} (task.train_size)"
        )


VALIDATION_KEY = 1  # fold_in(data key, 1): the data key of the default validation set


def validation_set(spec: JobSpec, scene: Scene, data_key: jax.Array) -> Any:
    """The scene's validation_set if it has one; else the test set of the same scene built from
    another data key (fold_in(data key, VALIDATION_KEY)): held-out samples of the same distribution,
    disjoint from the test set by construction. UserError if that set equals the test set (a scene
    whose data ignore the key)."""
    if scene.validation_set is not None:
        return scene.validation_set
    other_key = jax.random.fold_in(data_key, VALIDATION_KEY)
    other = build_scene(spec.task, other_key, spec.unroll).test_set
    same = jax.tree_util.tree_structure(other) == jax.tree_util.tree_structure(
        scene.test_set
    ) and all(
        a.shape == b.shape and bool(jnp.array_equal(a, b))
        for a, b in zip(jax.tree_util.tree_leaves(other), jax.tree_util.tree_leaves(scene.test_set))
    )
    if same:
        raise UserError(
            f"task={spec.task_name} builds the same test set from every data key, so it has "
            "no validation data: give its Scene a validation_set, or draw its data from `key` "
            "(docs/extending.md)"
        )
    return other


def prepare(
    spec: JobSpec,
    seed_list: list[int],
    checkpoint: Callable[[], None] | None = None,
    built: tuple[Scene, Seeds] | None = None,
) -> tuple[Scene, UpdateRule, Seeds]:
    """Precision set, the update rule and the seeds' scenes built, and what does not apply refused
    (UserError): everything a run (and `make bench`) does before compiling. built: the scene and
    seeds of another job with the same scene_key, used instead of building them again."""
    set_precision(spec.precision)
    logging.getLogger("jax").setLevel(logging.WARNING)
    quiet_callback_failures()  # building a scene's data can run its solver too
    rule = build_rule(spec.optim, spec.trial_values)
    batch_size = spec.trainer.batch_size
    if built is None:
        scene, seeds = build_seeds(spec, seed_list, batch_size, checkpoint)
    else:
        scene, seeds = built
        check_batch_size(scene, batch_size)
    check_scene_values(scene, seeds, spec.task_name)
    check_applies(scene, spec)
    kind = capabilities(spec.optim)
    check_matrices(spec, kind, seeds)
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
        check_layer_factors(spec, kind, rule.gradient)
    return scene, rule, seeds


def run_experiment(
    cfg: DictConfig,
    out_dir: str | Path,
    sweep: Path | None = None,
    on_owned: Callable[[], None] | None = None,
) -> tuple[Outcome, Path]:
    """run_job of the composed config checked at the door (physgrad.job_spec.check)."""
    return run_job(check(cfg), out_dir, sweep, on_owned)


def run_job(
    job: JobSpec | Refusal,
    out_dir: str | Path,
    sweep: Path | None = None,
    on_owned: Callable[[], None] | None = None,
) -> tuple[Outcome, Path]:
    """Run one job into out_dir/results.h5 (seeds > 1: one file per seed under out_dir/seed=<s>/,
    trained together in one vectorised step); a refused job (a Refusal, or one refused once its
    scene is built) leaves a file per member with status refused and the reason. A job that
    completed before with the same config is not run again unless overwrite=true. The job holds
    out_dir for its whole duration (another live process writing there: refused, nothing touched)
    and handles SIGINT and SIGTERM from start-up until its files are final; in a sweep (sweep: its
    folder) a signal to the job stops the sweep where the job runs in the sweep's launching process
    (else the job alone), and the sweep's stop reaches the job (physgrad.sweeps). on_owned runs
    once the folder is held, before anything else is written into it (the command line's
    provenance, .hydra/). A failure before training leaves files with status failed;
    ResultsWriteError if they cannot be written."""
    try:
        # a signal to the process that launched the sweep is the user's: the sweep stops; one to a
        # worker or a scheduler's job (scancel, a time limit) ends that job alone
        on_first = (
            (lambda name: mark_stopped(sweep, name))
            if sweep is not None and in_launcher()
            else None
        )
        with own_folder(out_dir), stop_on_signals(on_first) as stop, watching(sweep, stop):
            if on_owned is not None:
                on_owned()
            paths = [(member.seed, Path(out_dir) / member.path) for member in job.members]
            where = paths[0][1] if len(paths) == 1 else Path(out_dir)
            if isinstance(job, Refusal):
                for _, path in paths:
                    set_aside_unreadable(path)
                record_before_training(job.members, paths, "refused", job.reason)
                return refused(job.reason), where
            why = starts_from_itself(job, paths)  # refused without a results file
            if why is not None:
                return refused(why), where
            return run_owned(job, paths, stop), where
    except FolderOwned as error:
        return refused(str(error)), Path(out_dir) / ("results.h5" if len(job.members) == 1 else "")


def refused(reason: str) -> Outcome:
    """The outcome of a job refused before training."""
    return Outcome("refused", reason, 0, 0.0, {})


def record_before_training(
    members: tuple[Member, ...],
    paths: list[tuple[int, Path]],
    status: str,
    reason: str,
    stop: StopRequest | None = None,
) -> None:
    """A results file of attributes only (status and reason) for every member of a job that ended
    before training; with stop, no more of them once a second signal came (stop.at_once) and a file
    that cannot be written is skipped."""
    for (_, path), member in zip(paths, members):
        if stop is not None and stop.at_once:  # a second signal: stop writing files too
            break
        with contextlib.suppress(OSError) if stop is not None else contextlib.nullcontext():
            record_outcome(path, member.attributes, status, reason)


def run_owned(spec: JobSpec, paths: list[tuple[int, Path]], stop: StopRequest) -> Outcome:
    """run_job, once the job folder is held and signals are handled. Until training starts a
    signal ends the job at once (resume checks, building many seeds' data: nothing is half done
    there), its files saying interrupted; from then on the training loop acts on it between
    steps."""
    stop.raising = True
    try:
        stop.raise_if_stopped()  # a signal that came before
        return set_up_and_train(spec, paths, stop)
    except KeyboardInterrupt as interrupt:
        stop.raising = False
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} before training"
        record_before_training(spec.members, paths, "interrupted", why, stop)
        return Outcome("interrupted", why, 0, 0.0, {})
    finally:
        stop.raising = False


def set_up_and_train(spec: JobSpec, paths: list[tuple[int, Path]], stop: StopRequest) -> Outcome:
    """The job's steps once it holds its folder: the outcome of an earlier run with the same config
    (unless overwrite=true), else the building and what the built scene refuses (refused or
    failed: files that say so), the results files, training, and the figures."""
    earlier = finished_earlier(spec, paths, stop)
    if earlier is not None:
        return earlier
    try:
        scene, rule, seeds, origin = set_up(spec, paths, stop)
    except UserError as error:
        stop.raising = False
        record_before_training(spec.members, paths, "refused", str(error))
        return refused(str(error))
    except Exception as error:  # before training: the files say failed, with the reason
        stop.raising = False
        record_before_training(spec.members, paths, "failed", innermost_cause(error))
        raise
    attrs = [job_attributes(member, scene, rule, origin, len(paths)) for member in spec.members]
    writers = open_writers(paths, attrs, spec.trainer, seeds)
    stop.raising = False  # the training loop acts on signals between steps
    outcomes = train(scene, rule, seeds, writers, spec.trainer, label=spec.label, stop=stop)
    try:
        if spec.figures:
            draw_run_figures(scene, seeds, writers, outcomes, stop)
    except Exception as error:  # noqa: BLE001 - the results are final: a figure (a scene's own, too) is no failure
        log.warning(
            "figures of %s not drawn: %s: %s",
            paths[0][1].parent,
            type(error).__name__,
            str(error).splitlines()[0] if str(error) else "",
        )
    return job_outcome(outcomes)


def finished_earlier(
    spec: JobSpec, paths: list[tuple[int, Path]], stop: StopRequest
) -> Outcome | None:
    """Unreadable results files set aside; then, unless overwrite=true, the outcome of the run that
    finished every member's file before with the same config, or None if the job is to run."""
    for _, path in paths:
        stop.raise_if_stopped()
        set_aside_unreadable(path)
    if spec.overwrite:
        return None
    previous = []
    for (seed, path), member in zip(paths, spec.members):
        stop.raise_if_stopped()
        previous.append(finished_before(path, member.config, seed))
    return job_outcome(previous) if all(previous) else None


def set_up(
    spec: JobSpec, paths: list[tuple[int, Path]], stop: StopRequest
) -> tuple[Scene, UpdateRule, Seeds, dict]:
    """The scene, rule and seeds built (prepare), and the network init_from names put in place,
    with the attributes of its origin; UserError for what is refused."""
    check_seeds_together(spec, len(paths))
    scene, rule, seeds = prepare(spec, [seed for seed, _ in paths], stop.raise_if_stopped)
    origin = {}
    if spec.init_from:
        first, origin = start_from(spec.init_from, seeds.network(), spec.task_name)
        seeds = dataclasses.replace(seeds, params=stack([first]))
    return scene, rule, seeds, origin


def job_attributes(
    member: Member, scene: Scene, rule: UpdateRule, origin: dict, count: int
) -> dict:
    """The root attributes of a member's file: the run's (members.run_attributes, with the time
    steps the scene unrolls), the form of J a rule uses, the origin of a network started from
    another run's (init_from), and, for members trained together, their number."""
    attrs = {k: v for k, v in member.attributes.items() if k != "unroll"}
    if scene.unroll is not None:
        attrs["unroll"] = scene.unroll
    if rule.uses_jacobian:
        attrs["jacobian"] = rule.gradient.name
    if origin:
        attrs["variant"] += f" (from {origin['init_variant']})"
    if count > 1:
        # every seed's wall_time is the one shared vectorised run
        attrs["wall_time_shared_by"] = count
    return {**attrs, **origin}


def open_writers(
    paths: list[tuple[int, Path]], attrs: list[dict], settings: TrainerSettings, seeds: Seeds
) -> list[ResultsWriter]:
    """One ResultsWriter per member (its first write made): the member's attributes (attrs, one per
    path), its seed, and the machine's."""
    return [
        ResultsWriter(
            path,
            {
                **member_attrs,
                "seed": seed,
                "batch_size": settings.batch_size,
                "n_params": count_params(seeds.network()),
                **machine_attributes(),
            },
        )
        for (seed, path), member_attrs in zip(paths, attrs)
    ]
