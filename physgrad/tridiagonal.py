"""Solving one small tridiagonal system A x = r per sample, by the path that is fast on the device.

A has `lower` (lower[0] = 0), `diagonal` and `upper` (upper[-1] = 0), all of length N. Three paths
give the same x to float tolerance (tests/numerics/test_tridiagonal.py) and differ only in speed:

- "library": jax.lax.linalg.tridiagonal_solve (LAPACK gtsv on the CPU, cuSPARSE gtsv2 on a GPU).
  The fastest on the CPU, and on a GPU for a plain gradient; on a GPU, inside the per-sample
  `jacrev` under `vmap` of the Jacobian route (one system, many right-hand sides), it is 34x slower
  than "dense" (docs/benchmarks.md).
- "thomas": the Thomas algorithm as two `lax.scan`s of N steps (forward elimination, back
  substitution), no pivoting: c'_0 = c_0 / b_0, r'_0 = r_0 / b_0,
  m_i = b_i - a_i c'_{i-1}, c'_i = c_i / m_i, r'_i = (r_i - a_i r'_{i-1}) / m_i,
  x_{N-1} = r'_{N-1}, x_i = r'_i - c'_i x_{i+1}.
  Element-wise over every batch dimension `vmap`, `jvp` and `jacrev` add, so it batches on any
  device.
- "dense": A assembled as an N x N matrix and jnp.linalg.solve (LU with partial pivoting): batched
  LU of small matrices, O(N^3); its transpose reuses the LU factors for every right-hand side.

The path is chosen per jax backend and per route (FASTEST): a Jacobian pass traces the scene inside
jacobian_route(), so the same scene takes "dense" there and "library" for a plain gradient on a
GPU, without the user choosing.

Without pivoting, Thomas needs nonzero pivots m_i. For Crank-Nicolson of a Schroedinger equation,
A = I + i dt/2 H with H real symmetric, so A's Hermitian part is I (positive definite); every Schur
complement keeps a positive definite Hermitian part, so Re(m_i) > 0 and elimination without
pivoting is stable (its growth factor is bounded; George, Ikramov and Kucherov 2000). A scene
with another tridiagonal matrix takes "library" or "dense" unless the same argument holds.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
from jax import lax

Solve = Callable[[jax.Array, jax.Array, jax.Array, jax.Array], jax.Array]


def library_solve(
    lower: jax.Array, diagonal: jax.Array, upper: jax.Array, rhs: jax.Array
) -> jax.Array:
    """x of A x = rhs by jax.lax.linalg.tridiagonal_solve."""
    return lax.linalg.tridiagonal_solve(lower, diagonal, upper, rhs[:, None])[:, 0]


def thomas_solve(
    lower: jax.Array, diagonal: jax.Array, upper: jax.Array, rhs: jax.Array
) -> jax.Array:
    """x of A x = rhs by the Thomas algorithm (module docstring), two scans of N steps."""

    def eliminate(
        previous: tuple[jax.Array, jax.Array], row: tuple[jax.Array, ...]
    ) -> tuple[tuple[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
        upper_prev, rhs_prev = previous
        a, b, c, r = row
        pivot = b - a * upper_prev
        reduced = (c / pivot, (r - a * rhs_prev) / pivot)
        return reduced, reduced

    dtype = jnp.result_type(lower, diagonal, upper, rhs)
    zero = jnp.zeros((), dtype)
    rows = tuple(v.astype(dtype) for v in (lower, diagonal, upper, rhs))
    _, (upper_reduced, rhs_reduced) = lax.scan(eliminate, (zero, zero), rows)

    def substitute(x_next: jax.Array, row: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, ...]:
        c, r = row
        x = r - c * x_next
        return x, x

    _, x = lax.scan(substitute, zero, (upper_reduced, rhs_reduced), reverse=True)
    return x


def dense_solve(
    lower: jax.Array, diagonal: jax.Array, upper: jax.Array, rhs: jax.Array
) -> jax.Array:
    """x of A x = rhs with A assembled densely (LU with partial pivoting)."""
    matrix = jnp.diag(diagonal) + jnp.diag(lower[1:], -1) + jnp.diag(upper[:-1], 1)
    return jnp.linalg.solve(matrix, rhs)


SOLVES: dict[str, Solve] = {"library": library_solve, "thomas": thomas_solve, "dense": dense_solve}

# The path per (jax backend, route), from the rows of experiments/device_paths.py tridiagonal in
# docs/benchmarks.md (quantum scene, N = 14 and 32). A backend not listed takes the CPU's.
FASTEST: dict[tuple[str, str], str] = {
    ("cpu", "gradient"): "library",
    ("cpu", "jacobian"): "library",
    ("gpu", "gradient"): "library",
    ("gpu", "jacobian"): "dense",
}
ROUTES = ("gradient", "jacobian")
_route = contextvars.ContextVar("physgrad_tridiagonal_route", default="gradient")


@contextlib.contextmanager
def jacobian_route() -> Iterator[None]:
    """What is traced inside is a per-sample Jacobian (many right-hand sides per system)."""
    token = _route.set("jacobian")
    try:
        yield
    finally:
        _route.reset(token)


def fastest(backend: str, route: str) -> str:
    """The name of the path FASTEST gives `backend` on `route`."""
    key = (backend, route) if (backend, route) in FASTEST else ("cpu", route)
    return FASTEST[key]


def solve_for(backend: str) -> Solve:
    """The tridiagonal solve a scene uses on `backend` (jax.default_backend()): at trace time it
    takes the path of the route being traced."""

    def solve(lower: jax.Array, diagonal: jax.Array, upper: jax.Array, rhs: jax.Array) -> jax.Array:
        return SOLVES[fastest(backend, _route.get())](lower, diagonal, upper, rhs)

    return solve
