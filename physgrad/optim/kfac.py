"""K-FAC on physgrad's layer factors: Gauss-Newton curvature approximated per layer by a Kronecker
product.

For a dense layer z = a W + b, write a_bar = [a, 1] and W_bar = [W; b] ((in + 1) x out). Row r = (s,
k) of the network-through-physics Jacobian J holds a_bar_s (outer) delta_sk for W_bar
(physgrad.jacobians.LayerJacobian), so the layer's block of the Gauss-Newton matrix J^T J is
    C_l = sum_s sum_k (a_bar_s a_bar_s^T) (x) (delta_sk delta_sk^T).
K-FAC (Martens and Grosse, ICML 2015) replaces the sum of products by the product of the means,
    C_l ~ B * A_l (x) G_l,    A_l = (1/B) sum_s a_bar_s a_bar_s^T,    G_l = (1/B) sum_s sum_k
    delta_sk delta_sk^T,
and ignores the blocks between layers, so the Gauss-Newton system J^T J d = J^T g splits into one
small solve per layer:
    D_l = (1/B) (A_l + pi sqrt(gamma) I)^-1 grad_W_bar (G_l + sqrt(gamma) / pi I)^-1,     theta <-
    theta - lr D.
The cotangents delta are the exact ones of every output component (not sampled), so the factors are
those of the Gauss-Newton matrix of the rules beside it ("K-FAC-expand" in the terms of Eschenhagen
et al., NeurIPS 2023). Damping is factored Tikhonov damping, relative like Levenberg-Marquardt's:
with the factors' mean eigenvalues
m_A = tr(A)/dim A and m_G = tr(G)/dim G, gamma is scaled by m_A m_G and pi = sqrt(m_A / m_G)
balances it, so the two added terms are sqrt(gamma) m_A I and sqrt(gamma) m_G I and gamma is free of
the problem's scale. The factors are the step's batch's own, as Gauss-Newton, HIG and
Levenberg-Marquardt use J of the batch only (no running average over steps: docs/decisions.md).
Costs per step: J in layer factors (as Gauss-Newton and HIG) and per layer two symmetric solves of
sizes in + 1 and out, instead of the m x m eigendecomposition of J J^T.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.errors import UserError
from physgrad.jacobians import LayerJacobian, as_jacobian
from physgrad.optim.spectral import JacobianRule
from physgrad.validate import number

if TYPE_CHECKING:
    import optax

    from physgrad.jacobians import DenseJacobian


class KroneckerRule(JacobianRule):
    """A Jacobian rule that needs J in layer factors (a network built with physgrad.nets.apply_mlp,
    applied once per sample)."""


class KroneckerState(NamedTuple):
    """failures: steps whose solves gave non-finite values from a finite J and g."""

    failures: jax.Array

    def logs(self) -> dict:
        return {"svd_failures": self.failures}


def batch_factors(jac: LayerJacobian) -> tuple[tuple, tuple]:
    """Per layer (A_l, G_l) of one batch: A_l = (1/B) sum_s a_bar_s a_bar_s^T with a_bar = [a, 1],
    and G_l = (1/B) sum_s sum_k delta_sk delta_sk^T."""
    inputs, cotangents = [], []
    for a, delta in zip(jac.inputs, jac.cotangents):
        batch = a.shape[0]
        a_bar = jnp.concatenate([a, jnp.ones((batch, 1), a.dtype)], axis=1)
        inputs.append(a_bar.T @ a_bar / batch)
        flat = delta.reshape(-1, delta.shape[-1])
        cotangents.append(flat.T @ flat / batch)
    return tuple(inputs), tuple(cotangents)


def _damped(factor: jax.Array, sqrt_gamma: jax.Array) -> jax.Array:
    """factor + sqrt(gamma) * mean eigenvalue * I (an all-zero factor gets sqrt(gamma) * I)."""
    mean = jnp.trace(factor) / factor.shape[0]
    mean = jnp.where(mean > 0, mean, 1.0)
    return factor + sqrt_gamma * mean * jnp.eye(factor.shape[0], dtype=factor.dtype)


def kronecker_direction(
    jac: LayerJacobian,
    gradient: jax.Array,
    inputs_factors: Sequence[jax.Array],
    cotangents_factors: Sequence[jax.Array],
    damping: float,
) -> jax.Array:
    """D = per layer (1/B) (A_l + pi sqrt(gamma) I)^-1 grad_W_bar (G_l + sqrt(gamma)/pi I)^-1, in
    the ravel_pytree order of the parameters (jac.plan.leaves), from the flat gradient J^T g; solved
    in float64."""
    batch = jac.inputs[0].shape[0]
    plan = jac.plan
    sizes = [
        jac.inputs[layer].shape[1] * jac.cotangents[layer].shape[2]
        if kind == "w"
        else jac.cotangents[layer].shape[2]
        for layer, kind in plan.leaves
    ]
    offsets = [sum(sizes[:i]) for i in range(len(sizes))]
    where = {leaf: (offset, size) for leaf, offset, size in zip(plan.leaves, offsets, sizes)}
    parts = [None] * len(plan.leaves)
    with jax.enable_x64(True):
        sqrt_gamma = jnp.sqrt(jnp.asarray(damping, jnp.float64))
        g64 = gradient.astype(jnp.float64)
        for layer, (a_factor, g_factor) in enumerate(zip(inputs_factors, cotangents_factors)):
            fan_in, fan_out = jac.inputs[layer].shape[1], jac.cotangents[layer].shape[2]
            w_offset, w_size = where[(layer, "w")]
            b_offset, b_size = where[(layer, "b")]
            kernel = g64[w_offset : w_offset + w_size].reshape(fan_in, fan_out)
            bias = g64[b_offset : b_offset + b_size].reshape(1, fan_out)
            grad_bar = jnp.concatenate([kernel, bias], axis=0)
            left = _damped(a_factor.astype(jnp.float64), sqrt_gamma)
            right = _damped(g_factor.astype(jnp.float64), sqrt_gamma)
            # A^-1 X G^-1 with symmetric A and G: two solves, G^-1 applied to X^T's columns
            step = jnp.linalg.solve(right, jnp.linalg.solve(left, grad_bar).T).T / batch
            parts[plan.leaves.index((layer, "w"))] = step[:fan_in].reshape(-1)
            parts[plan.leaves.index((layer, "b"))] = step[fan_in].reshape(-1)
        return jnp.concatenate(parts).astype(gradient.dtype)


def kfac(learning_rate: float, damping: float = 1e-3) -> KroneckerRule:
    """K-FAC: theta <- theta - lr * D, D the layer-wise Kronecker-factored Gauss-Newton step above,
    from the batch's layer factors. damping: gamma, relative to the factors' mean eigenvalues.
    Refused for a network whose Jacobian is not layer-factorised (physgrad.experiment.prepare says
    why)."""
    number("optim.learning_rate", learning_rate, 0, open_low=True)
    number("optim.damping", damping, 0)

    def init(params: optax.Params) -> KroneckerState:
        return KroneckerState(jnp.zeros((), jnp.int32))

    def update(
        updates: optax.Updates,
        state: KroneckerState,
        params: optax.Params | None = None,
        *,
        jacobian: DenseJacobian | LayerJacobian | jax.Array,
        output_grad: jax.Array,
    ) -> tuple[optax.Updates, KroneckerState]:
        jac = as_jacobian(jacobian)
        if not isinstance(jac, LayerJacobian):
            raise UserError(
                "optim=kfac needs the Jacobian in layer factors (a network built with "
                "physgrad.nets.apply_mlp, each layer applied once per sample): use "
                "levenberg_marquardt or gauss_newton"
            )
        flat, unravel = ravel_pytree(updates)
        inputs_factor, cotangents_factor = batch_factors(jac)
        gradient = jac.transpose_apply(output_grad.reshape(-1).astype(jac.dtype))
        direction = kronecker_direction(jac, gradient, inputs_factor, cotangents_factor, damping)
        failed = jac.finite() & jnp.isfinite(output_grad).all() & ~jnp.isfinite(direction).all()
        state = KroneckerState(state.failures + failed.astype(jnp.int32))
        return unravel((-learning_rate * direction).astype(flat.dtype)), state

    return KroneckerRule(init, update)
