"""SOAP (Vyas et al. 2024, arXiv 2409.11321, "SOAP: Improving and Stabilizing Shampoo using Adam"):
Adam run in the eigenbasis of Shampoo's preconditioner, as an optax GradientTransformation.

For a weight matrix with gradient G (m x n), Shampoo's factors are moving averages

    L <- b L + (1 - b) G G^T,    R <- b R + (1 - b) G^T G,

and Q_L, Q_R their eigenvectors, recomputed every `precondition_frequency` steps. Each step rotates
the gradient into that basis, G' = Q_L^T G Q_R, keeps Adam's second moment there,

    V <- b2 V + (1 - b2) G'^2,

keeps the first moment M <- b1 M + (1 - b1) G in the parameters' own basis, and rotates Adam's
normalised step back:

    update = -lr Q_L [ (Q_L^T M Q_R) / (1 - b1^t) / (sqrt(V / (1 - b2^t)) + eps) ] Q_R^T.

Every other leaf (biases, and a side of a matrix longer than `max_precondition_dim`, whose basis
stays the identity) gets Adam's step. As in the authors' code, each step uses the basis the earlier
steps found and then updates the factors (and, every `precondition_frequency` of Adam's steps, the
basis) with its gradient; the first step only sets the factors and the basis and moves nothing, so
that V is accumulated in the basis it is read in from its first value; at each recomputation the
eigenvectors come in the order of their eigenvalues, which V keeps. Where Shampoo's basis is the
identity (every G G^T and G^T G diagonal with ascending entries), SOAP is Adam one step later.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax


class SoapState(NamedTuple):
    count: jax.Array  # steps taken (the skipped first one included)
    mu: optax.Updates  # first moment, in the parameters' basis
    nu: optax.Updates  # second moment, in the eigenbasis
    left: optax.Updates  # L (m x m) per matrix leaf; a (0, 0) array for the others
    right: optax.Updates  # R (n x n)
    basis_left: optax.Updates  # Q_L
    basis_right: optax.Updates  # Q_R


def _preconditioned(leaf: jax.Array, max_dim: int) -> tuple[bool, bool]:
    """Which sides of a leaf get Shampoo's basis: both sides of a matrix, each up to max_dim."""
    if leaf.ndim != 2:
        return False, False
    return leaf.shape[0] <= max_dim, leaf.shape[1] <= max_dim


def _eigenbasis(factor: jax.Array) -> jax.Array:
    """The factor's eigenvectors, in ascending order of their eigenvalues (a tiny multiple of the
    identity keeps a rank-deficient factor's null space well defined)."""
    size = factor.shape[0]
    jitter = 1e-30 + 1e-12 * jnp.trace(factor) / size
    return jnp.linalg.eigh(factor + jitter * jnp.eye(size, dtype=factor.dtype))[1]


def _sides(leaf: jax.Array, max_dim: int) -> tuple[int, int]:
    """The sizes of a leaf's factors L and R: 0 for a side without Shampoo's basis."""
    use_left, use_right = _preconditioned(leaf, max_dim)
    return (leaf.shape[0] if use_left else 0), (leaf.shape[1] if use_right else 0)


def _initial_state(params: optax.Params, max_dim: int) -> SoapState:
    """Zero moments and factors, and the identity basis, per leaf."""

    def square(leaf: jax.Array, side: int) -> jax.Array:
        size = _sides(leaf, max_dim)[side]
        return jnp.zeros((size, size), leaf.dtype)

    def identity(leaf: jax.Array, side: int) -> jax.Array:
        return jnp.eye(_sides(leaf, max_dim)[side], dtype=leaf.dtype)

    return SoapState(
        count=jnp.zeros((), jnp.int32),
        mu=jax.tree_util.tree_map(jnp.zeros_like, params),
        nu=jax.tree_util.tree_map(jnp.zeros_like, params),
        left=jax.tree_util.tree_map(lambda p: square(p, 0), params),
        right=jax.tree_util.tree_map(lambda p: square(p, 1), params),
        basis_left=jax.tree_util.tree_map(lambda p: identity(p, 0), params),
        basis_right=jax.tree_util.tree_map(lambda p: identity(p, 1), params),
    )


def _rotate(x: jax.Array, q_left: jax.Array, q_right: jax.Array) -> jax.Array:
    """Into the eigenbasis: Q_L^T x Q_R (the identity on a side without a basis)."""
    if q_left.shape[0]:
        x = q_left.T @ x
    if q_right.shape[0]:
        x = x @ q_right
    return x


def _rotate_back(x: jax.Array, q_left: jax.Array, q_right: jax.Array) -> jax.Array:
    """Out of the eigenbasis: Q_L x Q_R^T."""
    if q_left.shape[0]:
        x = q_left @ x
    if q_right.shape[0]:
        x = x @ q_right.T
    return x


class _Moments(NamedTuple):
    b1: float
    b2: float
    factor_b2: float
    eps: float


def _leaf_step(
    arrays: tuple[jax.Array, ...], count: jax.Array, refresh: jax.Array, moments: _Moments
) -> tuple[jax.Array, ...]:
    """One leaf's normalised step (zero on the first step), and its state after it: (step, mu,
    nu, L, R, Q_L, Q_R)."""
    g, mu, nu, left, right, q_left, q_right = arrays
    b1, b2, factor_b2, eps = moments
    first = count == 1
    # this step, in the basis the earlier steps found (the first step moves nothing)
    steps = jnp.maximum(count - 1, 1).astype(g.dtype)  # Adam's steps: the first skipped
    new_mu = b1 * mu + (1 - b1) * g
    new_nu = b2 * nu + (1 - b2) * _rotate(g, q_left, q_right) ** 2
    m_hat = _rotate(new_mu, q_left, q_right) / (1 - b1**steps)
    v_hat = new_nu / (1 - b2**steps)
    step = _rotate_back(m_hat / (jnp.sqrt(v_hat) + eps), q_left, q_right)
    # then Shampoo's factors, and every `frequency` steps the basis, for the next steps
    if left.shape[0]:
        left = factor_b2 * left + (1 - factor_b2) * (g @ g.T)
        q_left = jax.lax.cond(refresh, _eigenbasis, lambda _: q_left, left)
    if right.shape[0]:
        right = factor_b2 * right + (1 - factor_b2) * (g.T @ g)
        q_right = jax.lax.cond(refresh, _eigenbasis, lambda _: q_right, right)
    return (
        jnp.where(first, jnp.zeros_like(step), step),
        jnp.where(first, mu, new_mu),
        jnp.where(first, nu, new_nu),
        left,
        right,
        q_left,
        q_right,
    )


def soap(
    learning_rate: optax.ScalarOrSchedule,
    b1: float = 0.95,
    b2: float = 0.95,
    shampoo_b2: float | None = None,
    eps: float = 1e-8,
    precondition_frequency: int = 10,
    max_precondition_dim: int = 10_000,
) -> optax.GradientTransformation:
    """SOAP as in the module docstring. shampoo_b2: the factors' averaging (default b2, as the
    authors' code); precondition_frequency: the steps between recomputations of the basis;
    max_precondition_dim: a longer side of a matrix keeps the identity basis."""
    moments = _Moments(b1, b2, b2 if shampoo_b2 is None else shampoo_b2, eps)
    frequency = int(precondition_frequency)
    if frequency < 1:
        raise ValueError(f"precondition_frequency={precondition_frequency}: give 1 or more")

    def init(params: optax.Params) -> SoapState:
        return _initial_state(params, max_precondition_dim)

    def update(
        updates: optax.Updates, state: SoapState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, SoapState]:
        del params
        count = state.count + 1
        # after the first step, and after every `frequency` of Adam's steps (count - 1)
        refresh = jnp.logical_or(state.count == 0, (count - 1) % frequency == 0)
        leaves, tree = jax.tree_util.tree_flatten(updates)
        parts = [jax.tree_util.tree_leaves(part) for part in state[1:]]
        stepped = [_leaf_step(arrays, count, refresh, moments) for arrays in zip(leaves, *parts)]
        columns = [jax.tree_util.tree_unflatten(tree, list(c)) for c in zip(*stepped)]
        rate = learning_rate(state.count) if callable(learning_rate) else learning_rate
        directions = jax.tree_util.tree_map(lambda s: -rate * s, columns[0])
        return directions, SoapState(count, *columns[1:])

    return optax.GradientTransformation(init, update)
