"""The Jacobian pass: Gauss-Newton and half-inverse gradients from one truncated-SVD kernel.

With J = dy/dtheta (m x n, m = batch * output components) and g = dL/dy, the family of directions is
    d = V diag(s^-kappa) U^T g,    J = U diag(s) V^T (thin SVD),
kappa = 1: Gauss-Newton (J^+ g), kappa = 1/2: half-inverse gradient, kappa = -1: the plain gradient
J^T g. Truncation is relative: singular values s <= tau * max(s) are dropped and contribute exactly
0. Two routes compute it (`optim.route`): the thin SVD in the run's precision, or the m x m Gram
  matrix J J^T with
eigh in float64 (about 5x faster at the reference sizes; docs/decisions.md has the measurements).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from physgrad.jacobians import as_jacobian
from physgrad.optim.capabilities import GRAM_MIN_TAU
from physgrad.validate import choice, flag, number

if TYPE_CHECKING:
    from physgrad.jacobians import DenseJacobian, LayerJacobian

ROUTES = ("auto", "svd", "gram")
# The Gram route resolves singular values down to about sqrt(m * eps_64) * max(s) (~1e-6 at m =
# 4096), so it is used for truncations at or above GRAM_MIN_TAU (kept with the rules'
# capabilities, which charge a tuned tau below it the SVD's cost); smaller tau (and m > n) take
# the SVD.


def _kept_scale(s: jax.Array, kappa: float, tau: float, power: float = 1.0) -> jax.Array:
    """s^(-kappa * power) where s > tau * max(s), exactly 0 elsewhere (never inf or NaN, also for s
    = 0)."""
    keep = s > tau * jnp.max(s)
    safe_s = jnp.where(keep, s, 1.0)  # 0 ** -kappa would be inf, and inf * 0 is NaN
    return jnp.where(keep, safe_s ** (-kappa * power), 0.0)


def svd_direction(
    jac: DenseJacobian | LayerJacobian, output_grad: jax.Array, kappa: float, tau: float
) -> tuple[jax.Array, jax.Array]:
    """V diag(s^-kappa) U^T g from the thin SVD J = U diag(s) V^T, in J's precision; and the number
    of singular values kept."""
    u, s, vt = jnp.linalg.svd(jac.dense(), full_matrices=False)
    return vt.T @ (_kept_scale(s, kappa, tau) * (u.T @ output_grad)), _kept_count(s, tau)


def gram_direction(
    jac: DenseJacobian | LayerJacobian, output_grad: jax.Array, kappa: float, tau: float
) -> tuple[jax.Array, jax.Array]:
    """J^T U diag(lambda^-(kappa+1)/2) U^T g from J J^T = U diag(lambda) U^T, formed and decomposed
    in float64; and the number of singular values kept.

    Equal to V diag(s^-kappa) U^T g because lambda = s^2 and V = J^T U diag(1/s); the m x m Gram
    matrix costs O(m^2 n) from a dense J (O(m^2 * layer widths) from the layer factors,
    physgrad.jacobians), and float64 keeps the squared condition number (1/tau^2) resolvable.
    Truncation: lambda > tau^2 max(lambda), i.e. s > tau max(s)."""
    with jax.enable_x64(True):
        lam, u = jnp.linalg.eigh(jac.gram64())
        # eigh may return tiny negative eigenvalues; s = sqrt(max(lambda, 0)) and the rule drops
        # them
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


def _direction(
    jac: DenseJacobian | LayerJacobian | jax.Array,
    output_grad: jax.Array,
    kappa: float,
    tau: float,
    route: str,
) -> tuple[jax.Array, jax.Array]:
    jac = as_jacobian(jac)
    route = resolve_route(route, tau, jac.shape)
    return (gram_direction if route == "gram" else svd_direction)(jac, output_grad, kappa, tau)


def truncated_spectral_direction(
    jac: DenseJacobian | LayerJacobian | jax.Array,
    output_grad: jax.Array,
    kappa: float,
    tau: float,
    route: str = "svd",
) -> jax.Array:
    """V diag(s^-kappa) U^T g over the singular values with s > tau * max(s); the rest contribute 0.

    jac: an m x n matrix, or one of the forms of physgrad.jacobians. An all-zero J has max(s) = 0,
    keeps nothing and gives a zero direction (never NaN)."""
    return _direction(jac, output_grad, kappa, tau, route)[0]


SEEDS_AXIS = "seeds"  # the vmap axis of the seeds (or trial members) trained together


def any_seed(flag: jax.Array) -> jax.Array:
    """Whether flag holds for any of the seeds trained together in one vmapped step (the axis
    SEEDS_AXIS, physgrad.training.over_seeds): one predicate, not batched; outside such a vmap,
    flag itself."""
    try:
        return jax.lax.psum(flag.astype(jnp.int32), SEEDS_AXIS) > 0
    except NameError:  # not under the seeds' vmap: one run
        return flag


class SpectralState(NamedTuple):
    """failures: steps whose factorisation returned non-finite values from finite inputs (LAPACK did
    not converge), counted so that the runner can name the cause when the update turns non-finite;
    kept: the number of singular values the last step kept (s > tau * max(s))."""

    failures: jax.Array
    kept: jax.Array

    def logs(self) -> dict:
        """Logged with every training step (physgrad.optim.state_logs), as svd_failures and
        kept_singular_values."""
        return {"svd_failures": self.failures, "kept_singular_values": self.kept}


class JacobianRule(optax.GradientTransformationExtraArgs):
    """An update rule on the Jacobian pass: its update takes the extra arguments ``jacobian`` (J, m
    x n) and ``output_grad`` (g = dL/dy), so the training step builds J for it instead of a gradient
    pass."""


def spectral_direction(
    kappa: float, tau: float, route: str = "auto", retry_float64: bool = False
) -> optax.GradientTransformationExtraArgs:
    """Replaces the gradient by V diag(s^-kappa) U^T g.

    Needs the extra arguments jacobian J (m x n: a matrix or a form from physgrad.jacobians) and
    output_grad g = dL/dy (shape (batch, k)); the incoming gradient gives only the pytree structure,
    since J^T g carries no more than J and g.
    A factorisation that fails (non-finite direction from a finite J and g) is counted in the state;
    with retry_float64 it is repeated in float64 first (the failed step only), and counted if that
    fails too. Seeds trained together retry in one float64 factorisation of them all where any
    failed, and each keeps its own float32 result unless its own failed.
    """

    def init(params: optax.Params) -> SpectralState:
        return SpectralState(failures=jnp.zeros((), jnp.int32), kept=jnp.zeros((), jnp.int32))

    def update(
        updates: optax.Updates,
        state: SpectralState,
        params: optax.Params | None = None,
        *,
        jacobian: DenseJacobian | LayerJacobian | jax.Array,
        output_grad: jax.Array,
    ) -> tuple[optax.Updates, SpectralState]:
        jac = as_jacobian(jacobian)
        g = output_grad.reshape(-1).astype(jac.dtype)
        direction, kept = _direction(jac, g, kappa, tau, route)
        inputs_finite = jac.finite() & jnp.isfinite(g).all()
        failed = inputs_finite & ~jnp.isfinite(direction).all()
        if retry_float64:

            def in_float64() -> tuple[jax.Array, jax.Array]:
                wide, wide_kept = _direction(
                    jac.astype(jnp.float64), g.astype(jnp.float64), kappa, tau, route
                )
                # only a seed whose factorisation failed takes the float64 result
                return (
                    jnp.where(failed, wide.astype(jac.dtype), direction),
                    jnp.where(failed, wide_kept, kept),
                )

            # traced whole under x64 (a cond traced so batches under vmap), on one predicate for all
            # seeds trained together, so that it stays a cond: float64 only in a step where one
            # failed
            with jax.enable_x64(True):
                direction, kept = jax.lax.cond(
                    any_seed(failed), in_float64, lambda: (direction, kept)
                )
            failed = inputs_finite & ~jnp.isfinite(direction).all()
        state = SpectralState(failures=state.failures + failed.astype(jnp.int32), kept=kept)
        return ravel_pytree(updates)[1](direction), state

    return optax.GradientTransformationExtraArgs(init, update)


def spectral_rule(
    learning_rate: float, kappa: float, tau: float, route: str = "auto", retry_float64: bool = False
) -> JacobianRule:
    """theta <- theta - lr * V diag(s^-kappa) U^T g (lr in the mean-loss convention): Gauss-Newton
    at kappa = 1, HIG at kappa = 1/2, gradient descent at kappa = -1. Checks its own settings
    (optim.*)."""
    if not isinstance(learning_rate, jax.Array):  # an array: trials' values held in the state
        number("optim.learning_rate", learning_rate, 0, open_low=True)
    number("optim.kappa", kappa)
    number("optim.tau", tau, 0, 1)
    choice("optim.route", route, ROUTES)
    flag("optim.retry_float64", retry_float64)
    return JacobianRule(
        *optax.chain(
            spectral_direction(kappa, tau, route, retry_float64), optax.scale(-learning_rate)
        )
    )


def hig(learning_rate: float, tau: float) -> JacobianRule:
    """Half-inverse gradients: theta <- theta - lr * V diag(s^-1/2) U^T g."""
    return spectral_rule(learning_rate, 0.5, tau)


def gauss_newton(learning_rate: float, tau: float) -> JacobianRule:
    """Gauss-Newton: theta <- theta - lr * J^+ g with the truncated pseudo-inverse."""
    return spectral_rule(learning_rate, 1.0, tau)


# --- Levenberg-Marquardt
# ----------------------------------------------------------------------------------

# the relative damping mu stays within this (no under- or overflow of lambda)
DAMPING_RANGE = (
    1e-12,
    1e12,
)


def _eigenbasis(
    jac: DenseJacobian | LayerJacobian, g: jax.Array, tau: float, route: str
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """(l, U, c, keep): the squared singular values l = s^2 of J, the left singular vectors U, the
    coefficients c = U^T g and the kept ones (s > tau max(s)), from the thin SVD (J's precision) or,
    on the Gram route, from eigh(J J^T) in float64 (call under jax.enable_x64 for that route)."""
    route = resolve_route(route, tau, jac.shape)
    if route == "gram":
        lam, u = jnp.linalg.eigh(jac.gram64())
        lam = jnp.maximum(lam, 0.0)
    else:
        u, s, _ = jnp.linalg.svd(jac.dense(), full_matrices=False)
        lam = s**2
    g = g.astype(u.dtype)
    keep = lam > tau**2 * jnp.max(lam)
    return lam, u, u.T @ g, keep


class MarquardtRule(JacobianRule):
    """A Jacobian rule that also takes the extra arguments value and value_fn (its gain ratio)."""


class MarquardtState(NamedTuple):
    """mu: the relative damping (lambda = mu * max s^2); nu: Nielsen's growth factor after a
    rejected step; rejected: whether the last step was rejected (the loss did not fall); failures,
    kept: as SpectralState."""

    mu: jax.Array
    nu: jax.Array
    rejected: jax.Array
    failures: jax.Array
    kept: jax.Array

    def logs(self) -> dict:
        return {
            "damping": self.mu,
            "rejected_step": self.rejected.astype(self.mu.dtype),
            "svd_failures": self.failures,
            "kept_singular_values": self.kept,
        }


def marquardt_direction(
    jac: DenseJacobian | LayerJacobian | jax.Array,
    g: jax.Array,
    mu: jax.Array | float,
    tau: float,
    route: str,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """d = J^T (J J^T + lambda I)^-1 g over the kept singular values, lambda = mu * max(s^2)
    (relative, so mu is free of the problem's scale); also (l w, c) for the model's predicted
    reduction, with w = 1 / (l + lambda)."""
    jac = as_jacobian(jac)
    route_taken = resolve_route(route, tau, jac.shape)
    with jax.enable_x64(True) if route_taken == "gram" else contextlib.nullcontext():
        lam, u, c, keep = _eigenbasis(jac, g, tau, route_taken)
        damping = jnp.asarray(mu, lam.dtype) * jnp.max(lam)
        w = jnp.where(keep, 1.0 / jnp.where(keep, lam + damping, 1.0), 0.0)
        direction = jac.transpose_apply((u @ (w * c)).astype(lam.dtype)).astype(jac.dtype)
        return (
            direction,
            (lam * w).astype(jac.dtype),
            c.astype(jac.dtype),
            jnp.sum(keep).astype(jnp.int32),
        )


def marquardt_rule(
    learning_rate: float = 1.0,
    damping: float = 1e-3,
    tau: float = 1e-6,
    route: str = "auto",
    adapt: bool = True,
) -> JacobianRule:
    """Levenberg-Marquardt: h = -lr J^T (J J^T + lambda I)^-1 g with lambda = damping * max(s^2)
    (relative damping mu), on the Jacobian pass of Gauss-Newton and HIG (layer factors included).

    mu -> 0 gives the (truncated) Gauss-Newton step, a large mu the scaled gradient step -lr J^T g /
    lambda. adapt (Nielsen, 1999): the gain ratio rho = (L(theta) - L(theta + h)) / (m(0) - m(h)) on
    the step's batch, with the model m(h) = L + g^T J h + (|J h|^2 + lambda |h|^2) / (2 lr) that h
    minimises; rho > 0 accepts the step and sets mu <- mu * max(1/3, 1 - (2 rho - 1)^3), nu <- 2;
    otherwise the step is rejected (a zero update) and mu <- mu * nu, nu <- 2 nu. Needs the extra
    arguments jacobian, output_grad, value (the batch loss) and value_fn (the batch loss as a
    function of the parameters), which the Jacobian pass gives."""
    number("optim.learning_rate", learning_rate, 0, open_low=True)
    number("optim.damping", damping, DAMPING_RANGE[0], DAMPING_RANGE[1])
    number("optim.tau", tau, 0, 1)
    choice("optim.route", route, ROUTES)
    flag("optim.adapt", adapt)

    def init(params: optax.Params) -> MarquardtState:
        dtype = jnp.asarray(ravel_pytree(params)[0]).dtype
        zero = jnp.zeros((), jnp.int32)
        return MarquardtState(
            mu=jnp.asarray(damping, dtype),
            nu=jnp.asarray(2.0, dtype),
            rejected=jnp.zeros((), bool),
            failures=zero,
            kept=zero,
        )

    def update(
        updates: optax.Updates,
        state: MarquardtState,
        params: optax.Params | None = None,
        *,
        jacobian: DenseJacobian | LayerJacobian | jax.Array,
        output_grad: jax.Array,
        value: jax.Array | None = None,
        value_fn: Callable[[optax.Params], jax.Array] | None = None,
    ) -> tuple[optax.Updates, MarquardtState]:
        jac = as_jacobian(jacobian)
        g = output_grad.reshape(-1).astype(jac.dtype)
        direction, lw, c, kept = marquardt_direction(jac, g, state.mu, tau, route)
        failed = jac.finite() & jnp.isfinite(g).all() & ~jnp.isfinite(direction).all()
        step = -learning_rate * direction
        unravel = ravel_pytree(updates)[1]
        mu, nu, rejected = state.mu, state.nu, jnp.zeros((), bool)
        if adapt:
            if value_fn is None or value is None or params is None:
                raise TypeError(
                    "Levenberg-Marquardt with adapt=true needs params, value and value_fn"
                )
            flat = ravel_pytree(params)[0]
            predicted = learning_rate * jnp.sum(lw * c**2 * (1.0 - 0.5 * lw))
            actual = value - value_fn(ravel_pytree(params)[1](flat + step))
            rho = actual / jnp.where(predicted > 0, predicted, 1.0)
            accept = jnp.isfinite(actual) & (actual > 0) & (predicted > 0)
            shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            mu = jnp.clip(jnp.where(accept, mu * shrink, mu * nu), *DAMPING_RANGE).astype(
                state.mu.dtype
            )
            nu = jnp.where(accept, 2.0, 2.0 * nu).astype(state.nu.dtype)
            rejected = ~accept
            step = jnp.where(accept, step, jnp.zeros_like(step))
        state = MarquardtState(
            mu=mu,
            nu=jnp.minimum(nu, 2.0**30),
            rejected=rejected,
            failures=state.failures + failed.astype(jnp.int32),
            kept=kept,
        )
        return unravel(step.astype(ravel_pytree(updates)[0].dtype)), state

    return MarquardtRule(init, update)
