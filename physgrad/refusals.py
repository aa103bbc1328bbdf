"""What a run refuses before it trains, each with one line (UserError) that says what to change:
the run's own keys (top level and trainer), a mode that does not apply to the scene, a scene whose
loss or held-out data the runner cannot use, a rule whose needs the network does not meet, and
seeds trained together where that cannot be done. The task and optim settings themselves are
checked by the code that reads them (the scene's build function, the update rule's factory)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
from omegaconf import DictConfig, OmegaConf

from physgrad.errors import UserError
from physgrad.gradients import JacobianPass
from physgrad.optim import matrix_leaves
from physgrad.optim.capabilities import Capabilities, capabilities, scheduled_update
from physgrad.tasks import Scene
from physgrad.trainer_settings import TrainerSettings
from physgrad.training import Seeds
from physgrad.validate import choice, finite_numbers, flag, number

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
    flag("figures", cfg.get("figures", True))
    flag("trainer.validation", cfg.trainer.get("validation", False))
    if cfg.get("init_from") is not None and (
        not isinstance(cfg.init_from, str) or not cfg.init_from.strip()
    ):
        raise UserError(
            f"init_from={cfg.init_from!r} is not allowed: use the path of a results.h5, or leave "
            "init_from out (null) to start from a fresh network"
        )
    check_seeds(cfg)
    for section in ("task", "optim"):
        if not isinstance(cfg[section].get("name"), str) or not cfg[section].name:
            raise UserError(
                f"the {section} config has no name: add one (e.g. name: mine), it labels results"
            )
    check_unroll(cfg)
    return with_scheduled_update(TrainerSettings.from_config(cfg.trainer), cfg.optim)


def with_scheduled_update(settings: TrainerSettings, optim_cfg: DictConfig) -> TrainerSettings:
    """settings with the rule's update schedule attached where trainer.update_cost charges one; a
    cost given for a rule without one (or trainer.evaluation_cost for a rule that searches no
    line) is refused (its calibration was another rule's). Trials
    cannot vary the schedule: trial_values sets numbers only, and a number fixes the probability,
    which leaves no schedule."""
    if settings.evaluation_cost is not None and not capabilities(optim_cfg).line_search:
        raise UserError(
            f"trainer.evaluation_cost={settings.evaluation_cost:g} charges a line search's "
            f"evaluations, and optim={optim_cfg.get('name')} searches no line: leave "
            "trainer.evaluation_cost and trainer.step_evaluations out (null)"
        )
    if settings.update_cost is None:
        return settings
    schedule = scheduled_update(optim_cfg)
    if schedule is None:
        raise UserError(
            f"trainer.update_cost={settings.update_cost:g} charges a scheduled update, and "
            f"optim={optim_cfg.get('name')} has none (only psgd_kron with "
            "preconditioner_update_probability=null does): leave it out (null)"
        )
    return dataclasses.replace(settings, scheduled_update=schedule)


def check_seeds(cfg: DictConfig) -> None:
    """seed and seeds: integers, seeds at most SEEDS_LIMIT, and every seed below 2^32."""
    # PRNGKey(seed) keeps the low 32 bits of the seed: seeds 2^32 apart would be the same run
    number("seed", cfg.get("seed"), 0, SEED_LIMIT, integer=True)
    number("seeds", cfg.get("seeds"), 1, SEEDS_LIMIT + 1, integer=True)
    if cfg.seed + cfg.seeds > SEED_LIMIT:
        raise UserError(
            f"seed={cfg.seed} with seeds={cfg.seeds} reaches seed {cfg.seed + cfg.seeds - 1}: "
            f"seeds must stay below {SEED_LIMIT} (2^32), so use seed <= {SEED_LIMIT - cfg.seeds}"
        )


def check_unroll(cfg: DictConfig) -> None:
    """The top-level unroll only for a scene with time (its task config has `unroll`), and each a
    positive integer."""
    if cfg.get("unroll") is not None:
        if "unroll" not in cfg.task:
            raise UserError(
                f"task={cfg.task.name} has no time axis: remove unroll={cfg.unroll} "
                "(unroll applies to temporal scenes only)"
            )
        number("unroll", cfg.unroll, 1, integer=True)
    elif "unroll" in cfg.task:
        number("task.unroll", cfg.task.unroll, 1, integer=True)


def too_many_seeds(cfg: DictConfig) -> str | None:
    """Why a job of more than SEEDS_LIMIT seeds is refused before one file per seed is named, or
    None."""
    seeds = cfg.get("seeds", 1)
    if isinstance(seeds, int) and seeds > SEEDS_LIMIT:
        return (
            f"seeds={seeds} is more than {SEEDS_LIMIT} seeds in one process: sweep "
            f"them instead (physgrad run -m seed=0,1,2,...), or use seeds <= {SEEDS_LIMIT}"
        )
    return None


def trial_values_refusal(cfg: DictConfig) -> str | None:
    """Why a job's trial_values (optim key -> one value per member) are refused before one file per
    member is named, or None: each key a number of the optim config, the same number of values
    (1 .. SEEDS_LIMIT) for every key, each a positive finite number, with one seed and no
    init_from."""
    given = cfg.get("trial_values")
    if given is None:
        return None
    from omegaconf import ListConfig

    if not isinstance(given, DictConfig) or not given:
        return (
            "trial_values must map optim keys to lists of values, e.g. "
            "{learning_rate: [0.001, 0.01]}"
        )
    counts = set()
    for key, values in given.items():
        if not isinstance(cfg.optim.get(key), (int, float)) or isinstance(cfg.optim.get(key), bool):
            return (
                f"trial_values.{key}: optim.{key} is not a number of optim={cfg.optim.get('name')}"
            )
        if not isinstance(values, ListConfig) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < float("inf")
            for v in values
        ):
            return f"trial_values.{key}: give a list of positive numbers"
        counts.add(len(values))
    if len(counts) != 1 or not 0 < next(iter(counts)) <= SEEDS_LIMIT:
        return f"trial_values: give every key the same number of values (1 to {SEEDS_LIMIT})"
    if cfg.get("seeds", 1) != 1 or cfg.get("init_from"):
        return (
            "trial_values trains its members on one seed, each from that seed's network: use "
            "seeds=1 and no init_from"
        )
    return None


def starts_from_itself(cfg: DictConfig, paths: list[tuple[int, Path]]) -> str | None:
    """Why a job whose init_from is one of its own results files is refused (writing one would
    destroy the network it names), or None."""
    if cfg.get("init_from") and any(
        Path(str(cfg.init_from)).resolve() == path.resolve() for _, path in paths
    ):
        return (
            f"init_from={cfg.init_from} is this job's own results file, which the "
            "run would overwrite: start from another run's results.h5"
        )
    return None


def check_seeds_together(cfg: DictConfig, count: int) -> None:
    """Seeds trained together (count > 1) refused with init_from (it starts one network)."""
    if count > 1 and cfg.get("init_from"):
        raise UserError(f"init_from starts one network: use seeds=1 (not seeds={count}) with it")


def check_applies(scene: Scene, cfg: DictConfig) -> None:
    """Refuse a backprop-through-time mode on a scene whose network does not act inside a rollout:
    the scene's traits decide, whatever the rule."""
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
            "in floating point; for a complex output take abs() or .real)"
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


def check_matrices(cfg: DictConfig, kind: Capabilities, seeds: Seeds) -> None:
    """A rule that orthogonalises the network's matrices (Muon) refused for a network without
    any."""
    if kind.needs_matrices and not matrix_leaves(seeds.network()):
        raise UserError(
            f"optim={cfg.optim.name} orthogonalises the network's matrices and "
            f"task={cfg.task.name}'s "
            "network has none (no 2-D parameters): its Muon partition would be empty; use adam"
        )


def check_layer_factors(cfg: DictConfig, kind: Capabilities, gradient: JacobianPass) -> None:
    """A rule that needs the Jacobian in layer factors (K-FAC) refused where the network gives it
    per sample."""
    if kind.needs_layer_factors and gradient.plan is None:
        raise UserError(
            f"optim={cfg.optim.name} needs the Jacobian in layer factors and task={cfg.task.name} "
            f"gives it per sample ({gradient.why_per_sample}): use levenberg_marquardt or "
            "gauss_newton"
        )
