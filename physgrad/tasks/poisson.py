"""Poisson inverse problem (HIG paper): find x on an N x N grid with Laplace(x) = y*.

Cell-centred grid, spacing 1, zero Dirichlet boundary (ghost cells 0), 5-point stencil:
    (Laplace x)_{ij} = x_{i+1,j} + x_{i-1,j} + x_{i,j+1} + x_{i,j-1} - 4 x_{ij}.
The network maps y* (N^2) to x_hat (N^2); the physical output is y = Laplace(x_hat) and the
per-sample loss is 1/2 * sum_cells (y - y*)^2.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.validate import number

if TYPE_CHECKING:
    from jax.typing import DTypeLike

    from physgrad.nets import Params


def laplace(x: jax.Array) -> jax.Array:
    """5-point Laplacian with zero ghost cells over the last two axes."""
    padded = jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(1, 1), (1, 1)])
    return (
        padded[..., 2:, 1:-1]
        + padded[..., :-2, 1:-1]
        + padded[..., 1:-1, 2:]
        + padded[..., 1:-1, :-2]
        - 4.0 * x
    )


def laplace_eigenvalues(n: int) -> jax.Array:
    """lambda_ij = -4 sin^2(pi i / (2(N+1))) - 4 sin^2(pi j / (2(N+1))), i, j = 1..N."""
    one_d = -4.0 * jnp.sin(jnp.pi * jnp.arange(1, n + 1) / (2 * (n + 1))) ** 2
    return one_d[:, None] + one_d[None, :]


def sine_basis(n: int, dtype: DTypeLike | None = None) -> jax.Array:
    """Orthonormal, symmetric DST-I matrix S_ik = sqrt(2/(N+1)) sin(pi i k / (N+1)): the
    eigenvectors of the 1-D Dirichlet Laplacian."""
    idx = jnp.arange(1, n + 1, dtype=dtype)
    return jnp.sqrt(2.0 / (n + 1)) * jnp.sin(jnp.pi * idx[:, None] * idx[None, :] / (n + 1))


def solve_poisson(y: jax.Array) -> jax.Array:
    """x with Laplace(x) = y: X = S [(S Y S) / lambda] S, S the sine basis."""
    s = sine_basis(y.shape[-1], y.dtype)
    return s @ ((s @ y @ s) / laplace_eigenvalues(y.shape[-1]).astype(y.dtype)) @ s


def smooth_fields(
    key: jax.Array, count: int, n: int, smoothness: float, dtype: DTypeLike
) -> jax.Array:
    """Random fields: complex Gaussian Fourier coefficients weighted by (1/|k|^2)^smoothness, the k
    = 0 mode dropped (the reference's |k|^2 <= 0.1 cut removes only that mode on integer wave
    numbers), real part of the inverse FFT, each sample normalised to mean 0 and standard deviation
    1."""
    k = jnp.fft.fftfreq(n) * n
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    weight = jnp.where(k2 > 0.1, 1.0 / jnp.where(k2 > 0.1, k2, 1.0) ** smoothness, 0.0)
    real, imag = jax.random.normal(key, (2, count, n, n), dtype)
    field = jnp.real(jnp.fft.ifft2((real + 1j * imag) * weight)).astype(dtype)
    field = field - field.mean(axis=(-2, -1), keepdims=True)
    return field / field.std(axis=(-2, -1), keepdims=True)


def build(key: jax.Array, *, grid: int, smoothness: float, test_size: int) -> Scene:
    n = number("task.grid", grid, 2, integer=True)
    smoothness = number("task.smoothness", smoothness, 0)
    test_size = number("task.test_size", test_size, 1, integer=True)
    dtype = jnp.zeros(()).dtype  # float64 under precision=64
    cells = n * n
    # 64 -> 64 -> 128 -> 64 -> 64 at N = 8: 24,896 params
    sizes = [
        cells,
        cells,
        2 * cells,
        cells,
        cells,
    ]

    def make_batch(k: jax.Array, count: int) -> dict[str, jax.Array]:
        fields = smooth_fields(k, count, n, smoothness, dtype)
        return {
            "target": laplace(fields).reshape(count, cells),
            "field": fields.reshape(count, cells),
        }

    def predict(params: Params, sample: dict[str, jax.Array]) -> jax.Array:
        return apply_mlp(params, sample["target"], hidden="tanh")

    def sample_output(params: Params, sample: dict[str, jax.Array]) -> jax.Array:
        return laplace(predict(params, sample).reshape(n, n)).reshape(cells)

    def sample_loss(y: jax.Array, sample: dict[str, jax.Array]) -> jax.Array:
        return 0.5 * jnp.sum((y - sample["target"]) ** 2)

    def sample_metrics(
        params: Params, sample: dict[str, jax.Array], y: jax.Array
    ) -> dict[str, jax.Array]:
        return {"field_error": jnp.mean(jnp.abs(predict(params, sample) - sample["field"]))}

    return Scene(
        init_params=lambda k: init_mlp(k, sizes, dtype),
        draw_batch=lambda k, count, train_set: make_batch(
            k, count
        ),  # fresh every iteration, as the reference
        test_set=make_batch(key, test_size),
        sample_output=sample_output,
        sample_loss=sample_loss,
        sample_metrics=sample_metrics,
    )
