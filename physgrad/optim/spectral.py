"""The Jacobian route: Gauss-Newton and half-inverse gradients from one truncated-SVD kernel.

With J = dy/dtheta (m x n, m = batch * output components) and g = dL/dy, the family of directions is
    d = V diag(s^-kappa) U^T g,    J = U diag(s) V^T (thin SVD),
kappa = 1: Gauss-Newton (J^+ g), kappa = 1/2: half-inverse gradient, kappa = -1: the plain gradient J^T g.
Truncation is relative: singular values s <= tau * max(s) are dropped and contribute exactly 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree


def truncated_spectral_direction(jac: jax.Array, output_grad: jax.Array, kappa: float, tau: float) -> jax.Array:
    """V diag(s^-kappa) U^T g over the singular values with s > tau * max(s); the rest contribute 0.

    An all-zero J has max(s) = 0, keeps nothing and gives a zero direction (never NaN)."""
    u, s, vt = jnp.linalg.svd(jac, full_matrices=False)
    keep = s > tau * jnp.max(s)
    safe_s = jnp.where(keep, s, 1.0)  # 0 ** -kappa would be inf, and inf * 0 is NaN
    scale = jnp.where(keep, safe_s ** (-kappa), 0.0)
    return vt.T @ (scale * (u.T @ output_grad))


def per_sample_jacobian(sample_output, params, batch) -> jax.Array:
    """J (m x n) from per-sample reverse mode, vmapped over the batch: rows are sample major, columns follow
    ravel_pytree(params). Each sample's cotangent rows travel back through that sample only."""
    flat, unravel = ravel_pytree(params)
    jac = jax.vmap(jax.jacrev(lambda f, sample: sample_output(unravel(f), sample)), in_axes=(None, 0))(flat, batch)
    return jac.reshape(-1, flat.size)


class SpectralState(NamedTuple):
    """Stateless: every step uses only the current Jacobian."""


def spectral_direction(kappa: float, tau: float) -> optax.GradientTransformationExtraArgs:
    """Replaces the gradient by V diag(s^-kappa) U^T g.

    Needs the extra arguments sample_output (params, sample) -> y_i, batch and output_grad g = dL/dy
    (shape (batch, k)); the incoming gradient itself is not used, since J^T g carries no more than J and g.
    """

    def init(params):
        return SpectralState()

    def update(updates, state, params=None, *, sample_output, batch, output_grad):
        if params is None:
            raise ValueError("spectral_direction needs params to build the Jacobian")
        jac = per_sample_jacobian(sample_output, params, batch)
        direction = truncated_spectral_direction(jac, output_grad.reshape(-1).astype(jac.dtype), kappa, tau)
        return ravel_pytree(params)[1](direction), state

    return optax.GradientTransformationExtraArgs(init, update)


def spectral_rule(learning_rate: float, kappa: float, tau: float) -> optax.GradientTransformationExtraArgs:
    """theta <- theta - lr * V diag(s^-kappa) U^T g (lr in the mean-loss convention)."""
    return optax.chain(spectral_direction(kappa, tau), optax.scale(-learning_rate))


def hig(learning_rate: float, tau: float) -> optax.GradientTransformationExtraArgs:
    """Half-inverse gradients: theta <- theta - lr * V diag(s^-1/2) U^T g."""
    return spectral_rule(learning_rate, 0.5, tau)


def gauss_newton(learning_rate: float, tau: float) -> optax.GradientTransformationExtraArgs:
    """Gauss-Newton: theta <- theta - lr * J^+ g with the truncated pseudo-inverse."""
    return spectral_rule(learning_rate, 1.0, tau)
