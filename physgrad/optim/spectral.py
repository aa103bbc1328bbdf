"""The Jacobian route: Gauss-Newton and half-inverse gradients from one truncated-SVD kernel.

With J = dy/dtheta (m x n, m = batch * output components) and g = dL/dy, the family of directions is
    d = V diag(s^-kappa) U^T g,    J = U diag(s) V^T (thin SVD),
kappa = 1: Gauss-Newton (J^+ g), kappa = 1/2: half-inverse gradient, kappa = -1: the plain gradient J^T g.
Truncation is relative: singular values s <= tau * max(s) are dropped and contribute exactly 0.
Two routes compute it (`optim.route`): the thin SVD in the run's precision, or the m x m Gram matrix J J^T with
eigh in float64 (about 5x faster at the reference sizes; docs/decisions.md has the measurements).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from physgrad.jacobians import as_jacobian
from physgrad.validate import choice, flag, number


ROUTES = ("auto", "svd", "gram")
# The Gram route resolves singular values down to about sqrt(m * eps_64) * max(s) (~1e-6 at m = 4096), so it is
# used for truncations at or above this; smaller tau (and m > n) take the SVD.
GRAM_MIN_TAU = 1e-6


def _kept_scale(s: jax.Array, kappa: float, tau: float, power: float = 1.0) -> jax.Array:
    """s^(-kappa * power) where s > tau * max(s), exactly 0 elsewhere (never inf or NaN, also for s = 0)."""
    keep = s > tau * jnp.max(s)
    safe_s = jnp.where(keep, s, 1.0)  # 0 ** -kappa would be inf, and inf * 0 is NaN
    return jnp.where(keep, safe_s ** (-kappa * power), 0.0)


def svd_direction(jac, output_grad: jax.Array, kappa: float, tau: float) -> tuple[jax.Array, jax.Array]:
    """V diag(s^-kappa) U^T g from the thin SVD J = U diag(s) V^T, in J's precision; and the number of singular
    values kept."""
    u, s, vt = jnp.linalg.svd(jac.dense(), full_matrices=False)
    return vt.T @ (_kept_scale(s, kappa, tau) * (u.T @ output_grad)), _kept_count(s, tau)


def gram_direction(jac, output_grad: jax.Array, kappa: float, tau: float) -> tuple[jax.Array, jax.Array]:
    """J^T U diag(lambda^-(kappa+1)/2) U^T g from J J^T = U diag(lambda) U^T, formed and decomposed in float64;
    and the number of singular values kept.

    Equal to V diag(s^-kappa) U^T g because lambda = s^2 and V = J^T U diag(1/s); the m x m Gram matrix costs
    O(m^2 n) from a dense J (O(m^2 * layer widths) from the layer factors, physgrad.jacobians), and float64
    keeps the squared condition number (1/tau^2) resolvable. Truncation: lambda > tau^2 max(lambda), i.e.
    s > tau max(s)."""
    with jax.enable_x64(True):
        lam, u = jnp.linalg.eigh(jac.gram64())
        # eigh may return tiny negative eigenvalues; s = sqrt(max(lambda, 0)) and the rule drops them
        s = jnp.sqrt(jnp.maximum(lam, 0.0))
        weights = u @ (_kept_scale(s, kappa + 1.0, tau) * (u.T @ output_grad.astype(jnp.float64)))
        return jac.transpose_apply(weights).astype(jac.dtype), _kept_count(s, tau)


def _kept_count(s: jax.Array, tau: float) -> jax.Array:
    return jnp.sum(s > tau * jnp.max(s)).astype(jnp.int32)


def resolve_route(route: str, tau: float, shape: tuple[int, int]) -> str:
    """auto: the float64 Gram route for a wide J (m <= n) and tau >= GRAM_MIN_TAU, else the SVD."""
    if route != "auto":
        return route
    return "gram" if shape[0] <= shape[1] and tau >= GRAM_MIN_TAU else "svd"


def _direction(jac, output_grad, kappa: float, tau: float, route: str) -> tuple[jax.Array, jax.Array]:
    jac = as_jacobian(jac)
    route = resolve_route(route, tau, jac.shape)
    return (gram_direction if route == "gram" else svd_direction)(jac, output_grad, kappa, tau)


def truncated_spectral_direction(jac, output_grad: jax.Array, kappa: float, tau: float,
                                 route: str = "svd") -> jax.Array:
    """V diag(s^-kappa) U^T g over the singular values with s > tau * max(s); the rest contribute 0.

    jac: an m x n matrix, or one of the forms of physgrad.jacobians. An all-zero J has max(s) = 0, keeps
    nothing and gives a zero direction (never NaN)."""
    return _direction(jac, output_grad, kappa, tau, route)[0]


class SpectralState(NamedTuple):
    """failures: steps whose factorisation returned non-finite values from finite inputs (LAPACK did not
    converge), counted so that the runner can name the cause when the update turns non-finite; kept: the
    number of singular values the last step kept (s > tau * max(s))."""

    failures: jax.Array
    kept: jax.Array

    def logs(self) -> dict:
        """Logged with every training step (physgrad.optim.state_logs), as svd_failures and kept_singular_values."""
        return {"svd_failures": self.failures, "kept_singular_values": self.kept}


class JacobianRule(optax.GradientTransformationExtraArgs):
    """An update rule on the Jacobian route: its update takes the extra arguments ``jacobian`` (J, m x n) and
    ``output_grad`` (g = dL/dy), so the training step builds J for it instead of a gradient pass."""


def spectral_direction(kappa: float, tau: float, route: str = "auto",
                       retry_float64: bool = False) -> optax.GradientTransformationExtraArgs:
    """Replaces the gradient by V diag(s^-kappa) U^T g.

    Needs the extra arguments jacobian J (m x n: a matrix or a form from physgrad.jacobians) and output_grad
    g = dL/dy (shape (batch, k)); the incoming gradient gives only the pytree structure, since J^T g carries no
    more than J and g.
    A factorisation that fails (non-finite direction from a finite J and g) is counted in the state; with
    retry_float64 it is repeated in float64 first (the failed step only), and counted if that fails too.
    """

    def init(params):
        return SpectralState(failures=jnp.zeros((), jnp.int32), kept=jnp.zeros((), jnp.int32))

    def update(updates, state, params=None, *, jacobian, output_grad):
        jac = as_jacobian(jacobian)
        g = output_grad.reshape(-1).astype(jac.dtype)
        direction, kept = _direction(jac, g, kappa, tau, route)
        inputs_finite = jac.finite() & jnp.isfinite(g).all()
        failed = inputs_finite & ~jnp.isfinite(direction).all()
        if retry_float64:
            def in_float64():
                with jax.enable_x64(True):
                    wide, wide_kept = _direction(jac.astype(jnp.float64), g.astype(jnp.float64), kappa, tau, route)
                return wide.astype(jac.dtype), wide_kept

            direction, kept = jax.lax.cond(failed, in_float64, lambda: (direction, kept))
            failed = inputs_finite & ~jnp.isfinite(direction).all()
        state = SpectralState(failures=state.failures + failed.astype(jnp.int32), kept=kept)
        return ravel_pytree(updates)[1](direction), state

    return optax.GradientTransformationExtraArgs(init, update)


def spectral_rule(learning_rate: float, kappa: float, tau: float, route: str = "auto",
                  retry_float64: bool = False) -> JacobianRule:
    """theta <- theta - lr * V diag(s^-kappa) U^T g (lr in the mean-loss convention): Gauss-Newton at kappa = 1,
    HIG at kappa = 1/2, gradient descent at kappa = -1. Checks its own settings (optim.*)."""
    number("optim.learning_rate", learning_rate, 0, open_low=True)
    number("optim.kappa", kappa)
    number("optim.tau", tau, 0, 1)
    choice("optim.route", route, ROUTES)
    flag("optim.retry_float64", retry_float64)
    return JacobianRule(*optax.chain(spectral_direction(kappa, tau, route, retry_float64),
                                     optax.scale(-learning_rate)))


def hig(learning_rate: float, tau: float) -> JacobianRule:
    """Half-inverse gradients: theta <- theta - lr * V diag(s^-1/2) U^T g."""
    return spectral_rule(learning_rate, 0.5, tau)


def gauss_newton(learning_rate: float, tau: float) -> JacobianRule:
    """Gauss-Newton: theta <- theta - lr * J^+ g with the truncated pseudo-inverse."""
    return spectral_rule(learning_rate, 1.0, tau)
