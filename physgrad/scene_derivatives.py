"""The derivative checks of a scene (run by physgrad.scene_check, in float64): each backprop mode's
gradient against the plain loop's and central finite differences, with why they disagree where
they do (a loss not smooth in the parameters; an adaptive solver's error floor, told from a wrong
derivative by tightening its tolerances); and the Jacobian's passes J v, J^T u and J^T g against
jax.jvp, jax.vjp and jax.grad."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.experiment import build_seeds
from physgrad.gradients import JacobianPass
from physgrad.loop_reference import (
    DIRECTIONS,
    dynamics_forward_states,
    finite_difference_check,
    loop_output,
    relative_error,
)
from physgrad.unroll import MODES

if TYPE_CHECKING:
    from physgrad.job_spec import JobSpec
    from physgrad.nets import Params, Pytree
    from physgrad.tasks import Scene

# a scene's solver tolerances (its settings task.rtol and task.atol, where it has them) divided by
# TIGHTER tell an adaptive solver's error floor from a wrong derivative
TOLERANCES = ("rtol", "atol")
TIGHTER = 100.0
DERIVATIVE_RTOL = 1e-7  # a derivative against the plain loop's, and the Jacobian's passes


@dataclass(frozen=True)
class Check:
    name: str
    passed: bool | None  # None: not checked on this scene (detail says why)
    detail: str

    def line(self) -> str:
        mark = "skip" if self.passed is None else "ok  " if self.passed else "FAIL"
        return f"{mark}  {self.name}: {self.detail}"


def batch_loss(
    scene: Scene, output: Callable[[Params, Pytree], jax.Array], batch: Pytree
) -> Callable[[Params], jax.Array]:
    """theta -> the scene's loss of `output` over the batch, one sample at a time."""
    return lambda p: scene.batch_loss(jax.vmap(output, in_axes=(None, 0))(p, batch), batch)


def tighter_scene(spec: JobSpec) -> Scene | None:
    """The scene rebuilt with its solver's tolerances 100 times tighter, where its settings name
    them task.rtol and task.atol (diffrax's names; docs/extending.md); None where they do not."""
    task = spec.task
    if not all(_positive_number(task.get(key)) for key in TOLERANCES):
        return None
    tight = {**task, **{key: float(task[key]) / TIGHTER for key in TOLERANCES}}
    return build_seeds(dataclasses.replace(spec, task=tight), [spec.seed], 1)[0]


def _positive_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0


def gradient_check(
    scene: Scene,
    params: Params,
    batch: Pytree,
    mode: str,
    tighter: Callable[[], Scene | None] = lambda: None,
) -> Check:
    """The gradient of one backprop mode against the plain loop's (temporal scenes) and against
    finite differences; where they disagree, why (_step_hint, _tolerance_hint)."""
    backprop = MODES[mode]
    scan_loss = batch_loss(scene, scene.backprop_output(backprop), batch)
    gradient = jax.grad(scan_loss)(params)
    if scene.dynamics is not None:
        frozen = [
            dynamics_forward_states(scene.dynamics, params, sample_of(batch, i))
            for i in range(batch_size(batch))
        ]

        def loop_loss(p: Params) -> jax.Array:
            outputs = jnp.stack(
                [
                    loop_output(scene.dynamics, p, sample_of(batch, i), backprop, frozen[i])
                    for i in range(batch_size(batch))
                ]
            )
            return scene.batch_loss(outputs, batch)

        against_loop = relative_error(gradient, jax.grad(loop_loss)(params))
        reference = loop_loss
    else:
        against_loop, reference = 0.0, scan_loss
    worst, tolerance = finite_difference_check(reference, params, gradient)
    passed = against_loop <= DERIVATIVE_RTOL and worst <= tolerance
    loop_text = f"against the loop {against_loop:.1e}, " if scene.dynamics is not None else ""
    return Check(
        f"gradient {mode}",
        passed,
        f"{loop_text}against finite differences {worst:.1e} "
        f"(at most {tolerance:.0e}) along {DIRECTIONS} random directions"
        + (
            ""
            if worst <= tolerance
            else _step_hint(reference, params, gradient, worst)
            or _tolerance_hint(tighter(), params, batch, mode, worst)
        ),
    )


def _step_hint(reference: Callable, params: Params, gradient: Params, worst: float) -> str:
    """Why finite differences may disagree: the error again at a 10x smaller step. A loss that is
    not smooth in the parameters (an adaptive solver accepting other steps, a step count or a
    branch that changes) does not settle: said here. An error that settles (a wrong derivative,
    or an adaptive solver's error floor): "" (_tolerance_hint tells them apart)."""
    smaller, _ = finite_difference_check(reference, params, gradient, step_scale=0.1)
    if smaller < 0.5 * worst or smaller > 2 * worst:
        return (
            f"; {smaller:.1e} at a 10x smaller step: the differences do not settle, so the loss "
            "is not smooth in the parameters (an adaptive solver changes its accepted steps): "
            "tighten the solver's tolerances (rtol, atol near 1e-10) or check with a fixed step"
        )
    return ""


def _tolerance_hint(
    tighter: Scene | None, params: Params, batch: Pytree, mode: str, worst: float
) -> str:
    """Where the error settled: whether it follows the solver's tolerances. An adaptive solver's
    accepted steps move with the parameters but are not differentiated (diffrax's controllers), so
    the exact derivative of its discrete solution differs from the loss's own by about its
    tolerances, at any finite-difference step; a wrong derivative does not shrink with them."""
    settled = "; the same at a 10x smaller step"
    if tighter is None:
        return f"{settled}: the derivative itself is off"
    loss = batch_loss(tighter, tighter.backprop_output(MODES[mode]), batch)
    tight, _ = finite_difference_check(loss, params, jax.jit(jax.grad(loss))(params))
    if tight > worst / 3:
        return (
            f"{settled}, {tight:.1e} with the solver's tolerances {TIGHTER:g}x tighter: the "
            "derivative itself is off"
        )
    return (
        f"{settled}, {tight:.1e} with the solver's tolerances {TIGHTER:g}x tighter (task.rtol, "
        "task.atol): "
        "the error follows the tolerances, so it is the adaptive solver's own error floor (its "
        "accepted steps are not differentiated), not a wrong derivative; train at tolerances "
        "that put it below what the study needs, or with a fixed step"
    )


def jacobian_check(scene: Scene, params: Params, batch: Pytree) -> Check:
    first = sample_of(batch, 0)
    route = JacobianPass.for_network(scene.sample_output, params, first)
    loss, gradient, extra, _ = route(scene, params, batch)
    jac = extra["jacobian"]
    flat, unravel = ravel_pytree(params)

    def outputs(flat_params: jax.Array) -> jax.Array:
        return scene.batch_output(unravel(flat_params), batch).reshape(-1)

    v = jax.random.normal(jax.random.PRNGKey(7), flat.shape, flat.dtype)
    u = jax.random.normal(jax.random.PRNGKey(8), outputs(flat).shape, flat.dtype)
    jv, forward = forward_or_reverse(outputs, flat, v)
    jtu = jax.vjp(outputs, flat)[1](u)[0]
    dense = jac.dense()
    errors = {
        "J v": relative_error(dense @ v.astype(dense.dtype), jv),
        "J^T u": relative_error(jac.transpose_apply(u.astype(jac.dtype)), jtu),
        "J^T g": relative_error(
            gradient,
            jax.grad(lambda p: scene.batch_loss(scene.batch_output(p, batch), batch))(params),
        ),
    }
    worst = max(errors.values())
    return Check(
        "jacobian",
        worst <= DERIVATIVE_RTOL,
        f"{route.name}: "
        + ", ".join(f"{k} {e:.1e}" for k, e in errors.items())
        + f" (at most {DERIVATIVE_RTOL:.0e})"
        + (
            ""
            if forward is None
            else f"; J v by reverse mode: the scene has no forward mode ({forward}), which "
            "physgrad's routes do not need"
        ),
    )


def forward_or_reverse(
    outputs: Callable[[jax.Array], jax.Array], flat: jax.Array, v: jax.Array
) -> tuple[jax.Array, str | None]:
    """(J v, None) by forward mode (jax.jvp); where the scene's code has no forward mode (a
    custom_vjp, as diffrax's default adjoint), J v from the rows of J in reverse mode (jax.jacrev)
    and the reason forward mode failed."""
    try:
        return jax.jvp(outputs, (flat,), (v,))[1], None
    except TypeError as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        return jax.jacrev(outputs)(flat) @ v, reason


def batch_size(batch: Pytree) -> int:
    return jax.tree_util.tree_leaves(batch)[0].shape[0]


def sample_of(batch: Pytree, i: int) -> Pytree:
    return jax.tree_util.tree_map(lambda leaf: leaf[i], batch)
