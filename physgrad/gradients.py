"""Gradient passes: how a training step turns (scene, params, batch) into the loss, the gradient
handed to the update rule, the rule's extra arguments and logged scalars. A pass is a value chosen
once per run:

- Regular(mode): one forward and one backward pass through the scene's output with the gradient
  stops of a backprop-through-time mode (R, M or S; R for a scene without time);
- Combined(): the stabilised gradient C of the StableBPTT paper from two passes (M and R);
- JacobianPass(plan): y and J = dy/dtheta, for rules that need J (Gauss-Newton, HIG), in layer
  factors where the network allows it (physgrad.jacobians); the gradient is J^T g, and J and g =
  dL/dy go to the rule as extra arguments.

Every pass logs ``output_max_abs``, the largest |y| of the batch's physical output (where a blow-up
of the physics shows first).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from physgrad.errors import UserError
from physgrad.jacobians import LayerPlan, dense_jacobian, layer_jacobian, plan_layers
from physgrad.tridiagonal import jacobian_route
from physgrad.unroll import MODES, PHYSICS_ONLY, REGULAR, Backprop

if TYPE_CHECKING:
    from physgrad.nets import Params, Pytree
    from physgrad.tasks import Scene

BACKPROP_MODES = ("R", "M", "S", "C")


def batch_loss_fn(scene: Scene, batch: Pytree) -> Callable[[Params], jax.Array]:
    """theta -> L(y(theta)) on one batch, through the regular output: what a line search
    (optax.lbfgs) or a gain ratio (Levenberg-Marquardt) evaluates at trial parameters (optax's extra
    argument value_fn)."""
    return lambda p: scene.batch_loss(
        jax.vmap(scene.sample_output, in_axes=(None, 0))(p, batch), batch
    )


def _loss_and_pullback(
    scene: Scene,
    sample_output: Callable[[Params, Pytree], jax.Array],
    params: Params,
    batch: Pytree,
) -> tuple[jax.Array, Params, jax.Array]:
    """(loss, dL/dtheta, max |y|) from one forward and one backward pass of the batch output."""
    y, pullback = jax.vjp(lambda p: jax.vmap(sample_output, in_axes=(None, 0))(p, batch), params)
    loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
    return loss, pullback(output_grad)[0], jnp.max(jnp.abs(y))


@dataclass(frozen=True)
class Regular:
    """dL/dtheta through the output with the gradient stops of ``backprop`` (R: plain
    backpropagation)."""

    backprop: Backprop = REGULAR
    with_value: bool = (
        False  # give the rule optax's extra arguments value, grad and value_fn (e.g. optax.lbfgs)
    )

    def __call__(
        self, scene: Scene, params: Params, batch: Pytree
    ) -> tuple[jax.Array, Params, dict[str, Any], dict[str, jax.Array]]:
        loss, grads, output_max = _loss_and_pullback(
            scene, scene.backprop_output(self.backprop), params, batch
        )
        extra = (
            {"value": loss, "grad": grads, "value_fn": batch_loss_fn(scene, batch)}
            if self.with_value
            else {}
        )
        return loss, grads, extra, {"output_max_abs": output_max}


@dataclass(frozen=True)
class Combined:
    """C = combine_signs(g_M, g_R) from the physics-only (M) and the regular (R) gradient, with its
    diagnostics: cos_physics_regular = cos(g_M, g_R) and zeroed_fraction, the share of components C
    sets to zero."""

    with_value: bool = False  # as Regular's

    def __call__(
        self, scene: Scene, params: Params, batch: Pytree
    ) -> tuple[jax.Array, Params, dict[str, Any], dict[str, jax.Array]]:
        loss, g_regular, output_max = _loss_and_pullback(scene, scene.sample_output, params, batch)
        _, g_physics, _ = _loss_and_pullback(
            scene, scene.backprop_output(PHYSICS_ONLY), params, batch
        )
        logs = {
            "output_max_abs": output_max,
            "cos_physics_regular": tree_cosine(g_physics, g_regular),
            "zeroed_fraction": sign_disagreement(g_physics, g_regular),
        }
        combined = combine_signs(g_physics, g_regular)
        extra = (
            {"value": loss, "grad": combined, "value_fn": batch_loss_fn(scene, batch)}
            if self.with_value
            else {}
        )
        return loss, combined, extra, logs


@dataclass(frozen=True)
class JacobianPass:
    """y and J, in factors when the network allows it (plan: physgrad.jacobians.plan_layers) and
    else from one per-sample reverse pass; gradient J^T g; extra arguments jacobian=J and
    output_grad=g for the rule."""

    plan: LayerPlan | None = None
    why_per_sample: str = ""
    with_value: bool = (
        False  # also give value (the batch loss) and value_fn (Levenberg-Marquardt's gain ratio)
    )

    @classmethod
    def for_network(
        cls,
        sample_output: Callable[[Params, Pytree], jax.Array],
        params: Params,
        sample: Pytree,
        with_value: bool = False,
    ) -> "JacobianPass":
        """The layer-factorised pass where plan_layers allows it, else the per-sample pass with the
        reason."""
        plan = plan_layers(sample_output, params, sample)
        return (
            cls(plan, "", with_value)
            if isinstance(plan, LayerPlan)
            else cls(None, plan, with_value)
        )

    @property
    def name(self) -> str:
        """The form of J, as the results file names it (attribute ``jacobian``)."""
        if self.plan is not None:
            return "layer-factorised"
        return "per-sample" + (f": {self.why_per_sample}" if self.why_per_sample else "")

    def __call__(
        self, scene: Scene, params: Params, batch: Pytree
    ) -> tuple[jax.Array, Params, dict[str, Any], dict[str, jax.Array]]:
        with jacobian_route():  # a scene's small solves take the path fastest for many rows
            if self.plan is None:
                y, jac = dense_jacobian(scene.sample_output, params, batch)
            else:
                y, jac = layer_jacobian(scene.sample_output, params, batch, self.plan)
        loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
        grads = ravel_pytree(params)[1](
            jac.transpose_apply(output_grad.reshape(-1).astype(jac.dtype))
        )
        extra = {"jacobian": jac, "output_grad": output_grad}
        if self.with_value:
            extra.update(value=loss, value_fn=batch_loss_fn(scene, batch))
        return loss, grads, extra, {"output_max_abs": jnp.max(jnp.abs(y))}


def gradient_pass(
    backprop: str | None, uses_jacobian: bool, with_value: bool = False
) -> Regular | Combined | JacobianPass:
    """The gradient pass of a rule: the Jacobian pass for rules that take J, else the backprop
    mode's (None: R); with_value: the rule also takes optax's extra arguments value (and grad) and
    value_fn."""
    if backprop is not None and backprop not in BACKPROP_MODES:
        raise UserError(
            f"optim.backprop={backprop!r} is not allowed: choose one of "
            f"{', '.join(BACKPROP_MODES)} or null"
        )
    if uses_jacobian:
        if backprop is not None:
            raise UserError(
                f"optim.backprop={backprop} applies to gradient-based rules: the Jacobian rules "
                "differentiate the regular rollout; remove optim.backprop"
            )
        return JacobianPass(with_value=with_value)
    if backprop == "C":
        return Combined(with_value)
    return Regular(MODES[backprop or "R"], with_value)


def combine_signs(g_physics: Params, g_regular: Params) -> Params:
    """C = g_M where sign(g_M) == sign(g_R), else 0, per parameter element (its magnitude is always
    g_M's)."""
    return jax.tree_util.tree_map(
        lambda m, r: jnp.where(jnp.sign(m) == jnp.sign(r), m, jnp.zeros_like(m)),
        g_physics,
        g_regular,
    )


def tree_cosine(a: Params, b: Params) -> jax.Array:
    """<a, b> / (|a| |b|) over whole pytrees; 0 where either is the zero vector (the angle is
    undefined)."""
    dot = sum(
        jnp.vdot(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    )
    norms = optax.tree.norm(a) * optax.tree.norm(b)
    return jnp.where(norms > 0, dot / jnp.where(norms > 0, norms, 1.0), 0.0)


def sign_disagreement(a: Params, b: Params) -> jax.Array:
    """Fraction of components where sign(a) != sign(b): the ones the combined gradient sets to
    zero."""
    leaves = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    differ = sum(jnp.sum(jnp.sign(x) != jnp.sign(y)) for x, y in leaves)
    return differ / sum(x.size for x in jax.tree_util.tree_leaves(a))
