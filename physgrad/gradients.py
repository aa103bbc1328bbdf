"""Gradient routes: how a training step turns (scene, params, batch) into the loss, the gradient handed to the
update rule, the rule's extra arguments and logged scalars. A route is a value chosen once per run:

- Regular(mode): one forward and one backward pass through the scene's output with the gradient stops of a
  backprop-through-time mode (R, M or S; R for a scene without time);
- Combined(): the stabilised gradient C of the StableBPTT paper from two passes (M and R);
- JacobianPass(): y and J = dy/dtheta from one per-sample reverse pass, for rules that need J (Gauss-Newton,
  HIG); the gradient is J^T g, and J and g = dL/dy go to the rule as extra arguments.

Every route logs ``output_max_abs``, the largest |y| of the batch's physical output (where a blow-up of the
physics shows first).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from physgrad import UserError
from physgrad.unroll import MODES, PHYSICS_ONLY, REGULAR, Backprop

BACKPROP_MODES = ("R", "M", "S", "C")


def _loss_and_pullback(scene, sample_output, params, batch):
    """(loss, dL/dtheta, max |y|) from one forward and one backward pass of the batch output."""
    y, pullback = jax.vjp(lambda p: jax.vmap(sample_output, in_axes=(None, 0))(p, batch), params)
    loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
    return loss, pullback(output_grad)[0], jnp.max(jnp.abs(y))


@dataclass(frozen=True)
class Regular:
    """dL/dtheta through the output with the gradient stops of ``backprop`` (R: plain backpropagation)."""

    backprop: Backprop = REGULAR

    def __call__(self, scene, params, batch):
        loss, grads, output_max = _loss_and_pullback(scene, scene.backprop_output(self.backprop), params, batch)
        return loss, grads, {}, {"output_max_abs": output_max}


@dataclass(frozen=True)
class Combined:
    """C = combine_signs(g_M, g_R) from the physics-only (M) and the regular (R) gradient, with its diagnostics:
    cos_physics_regular = cos(g_M, g_R) and zeroed_fraction, the share of components C sets to zero."""

    def __call__(self, scene, params, batch):
        loss, g_regular, output_max = _loss_and_pullback(scene, scene.sample_output, params, batch)
        _, g_physics, _ = _loss_and_pullback(scene, scene.backprop_output(PHYSICS_ONLY), params, batch)
        logs = {"output_max_abs": output_max, "cos_physics_regular": tree_cosine(g_physics, g_regular),
                "zeroed_fraction": sign_disagreement(g_physics, g_regular)}
        return loss, combine_signs(g_physics, g_regular), {}, logs


@dataclass(frozen=True)
class JacobianPass:
    """y and J from one per-sample reverse pass (output_and_jacobian); gradient J^T g; extra arguments
    jacobian=J and output_grad=g for the rule."""

    def __call__(self, scene, params, batch):
        y, jac = output_and_jacobian(scene.sample_output, params, batch)
        loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
        grads = ravel_pytree(params)[1](jac.T @ output_grad.reshape(-1).astype(jac.dtype))
        return loss, grads, {"jacobian": jac, "output_grad": output_grad}, {"output_max_abs": jnp.max(jnp.abs(y))}


def route_for(backprop: str | None, uses_jacobian: bool):
    """The route of a rule: the Jacobian pass for rules that take J, else the backprop mode's (None: R)."""
    if backprop is not None and backprop not in BACKPROP_MODES:
        raise UserError(f"optim.backprop={backprop!r} is not allowed: choose one of {', '.join(BACKPROP_MODES)} "
                        "or null")
    if uses_jacobian:
        if backprop is not None:
            raise UserError(f"optim.backprop={backprop} applies to gradient-based rules: the Jacobian rules "
                            "differentiate the regular rollout; remove optim.backprop")
        return JacobianPass()
    if backprop == "C":
        return Combined()
    return Regular(MODES[backprop or "R"])


def combine_signs(g_physics, g_regular):
    """C = g_M where sign(g_M) == sign(g_R), else 0, per parameter element (its magnitude is always g_M's)."""
    return jax.tree_util.tree_map(lambda m, r: jnp.where(jnp.sign(m) == jnp.sign(r), m, jnp.zeros_like(m)),
                                  g_physics, g_regular)


def tree_cosine(a, b) -> jax.Array:
    """<a, b> / (|a| |b|) over whole pytrees; 0 where either is the zero vector (the angle is undefined)."""
    dot = sum(jnp.vdot(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    norms = optax.tree.norm(a) * optax.tree.norm(b)
    return jnp.where(norms > 0, dot / jnp.where(norms > 0, norms, 1.0), 0.0)


def sign_disagreement(a, b) -> jax.Array:
    """Fraction of components where sign(a) != sign(b): the ones the combined gradient sets to zero."""
    leaves = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    differ = sum(jnp.sum(jnp.sign(x) != jnp.sign(y)) for x, y in leaves)
    return differ / sum(x.size for x in jax.tree_util.tree_leaves(a))


def output_and_jacobian(sample_output, params, batch) -> tuple[jax.Array, jax.Array]:
    """y (batch, k) and J = dy/dtheta (m x n, m = batch * k) from one per-sample reverse-mode pass, vmapped
    over the batch: J's rows are sample major, its columns follow ravel_pytree(params). The forward pass that
    builds each sample's pullback also gives y, so a step needs no separate forward or gradient pass
    (dL/dtheta = J^T g)."""
    flat, unravel = ravel_pytree(params)

    def output_twice(flat_params, sample):
        y = sample_output(unravel(flat_params), sample)
        return y, y

    jac, y = jax.vmap(jax.jacrev(output_twice, has_aux=True), in_axes=(None, 0))(flat, batch)
    return y, jac.reshape(-1, flat.size)
