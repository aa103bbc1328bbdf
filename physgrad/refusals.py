"""What a run refuses once its scene and rule are built, each with one line (UserError) that says
what to change: a mode that does not apply to the scene, a scene whose loss or held-out data the
runner cannot use, a rule whose needs the network does not meet, a network started from the job's
own results file, and seeds trained together where that cannot be done. What the config alone
decides is refused at the door (physgrad.job_spec); the task and optim settings themselves are
checked by the code that reads them (the scene's build function, the update rule's factory)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp

from physgrad.errors import UserError
from physgrad.gradients import JacobianPass
from physgrad.job_spec import JobSpec
from physgrad.optim import matrix_leaves
from physgrad.optim.capabilities import Capabilities
from physgrad.tasks import Scene
from physgrad.training import Seeds


def starts_from_itself(spec: JobSpec, paths: list[tuple[int, Path]]) -> str | None:
    """Why a job whose init_from is one of its own results files is refused (writing one would
    destroy the network it names), or None."""
    if spec.init_from and any(
        Path(spec.init_from).resolve() == path.resolve() for _, path in paths
    ):
        return (
            f"init_from={spec.init_from} is this job's own results file, which the "
            "run would overwrite: start from another run's results.h5"
        )
    return None


def check_seeds_together(spec: JobSpec, count: int) -> None:
    """Seeds trained together (count > 1) refused with init_from (it starts one network)."""
    if count > 1 and spec.init_from:
        raise UserError(f"init_from starts one network: use seeds=1 (not seeds={count}) with it")


def check_applies(scene: Scene, spec: JobSpec) -> None:
    """Refuse a backprop-through-time mode on a scene whose network does not act inside a rollout:
    the scene's traits decide, whatever the rule."""
    backprop = spec.optim.get("backprop")
    if backprop is None or scene.closed_loop:
        return
    if not scene.time_axis:
        why = "has no time axis"
    elif "closed_loop" in spec.task:
        why = "has an open-loop controller: set task.closed_loop=true, or"
    else:
        why = "has an open-loop controller"
    raise UserError(
        f"optim={spec.rule_name} needs a closed-loop controller in time "
        f"(optim.backprop={backprop}), "
        f"and task={spec.task_name} {why}{':' if why[-1] != ',' else ''} use a rule without "
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


def check_matrices(spec: JobSpec, kind: Capabilities, seeds: Seeds) -> None:
    """A rule that orthogonalises the network's matrices (Muon) refused for a network without
    any."""
    if kind.needs_matrices and not matrix_leaves(seeds.network()):
        raise UserError(
            f"optim={spec.rule_name} orthogonalises the network's matrices and "
            f"task={spec.task_name}'s "
            "network has none (no 2-D parameters): its Muon partition would be empty; use adam"
        )


def check_layer_factors(spec: JobSpec, kind: Capabilities, gradient: JacobianPass) -> None:
    """A rule that needs the Jacobian in layer factors (K-FAC) refused where the network gives it
    per sample."""
    if kind.needs_layer_factors and gradient.plan is None:
        raise UserError(
            f"optim={spec.rule_name} needs the Jacobian in layer factors and task={spec.task_name} "
            f"gives it per sample ({gradient.why_per_sample}): use levenberg_marquardt or "
            "gauss_newton"
        )
