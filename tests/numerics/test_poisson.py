import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import count_params
from physgrad.tasks.poisson import build, laplace, laplace_eigenvalues, smooth_fields, solve_poisson


def dense_laplace(n):
    basis = jnp.eye(n * n).reshape(n * n, n, n)
    return jax.vmap(laplace)(basis).reshape(n * n, n * n).T


# make test-long: the larger grid; make test keeps the closed form on the 3 x 3 grid
@pytest.mark.parametrize("n", [3, pytest.param(8, marks=pytest.mark.long)])
def test_laplace_matches_closed_form_eigenvalues(x64, n):
    matrix = np.asarray(dense_laplace(n))
    np.testing.assert_allclose(matrix, matrix.T, atol=0)
    expected = np.sort(np.asarray(laplace_eigenvalues(n)).ravel())
    np.testing.assert_allclose(np.linalg.eigvalsh(matrix), expected, rtol=1e-12, atol=1e-12)
    assert expected.max() < 0  # negative definite


def test_laplace_stencil_by_hand(x64):
    x = jnp.zeros((3, 3)).at[1, 1].set(1.0).at[0, 0].set(2.0)
    y = laplace(x)
    assert y[1, 1] == -4.0  # centre: -4 * 1, neighbours 0
    assert y[0, 0] == -8.0  # corner: ghost cells are 0
    assert y[0, 1] == 1.0 + 2.0  # neighbours (1,1) and (0,0)


def test_solve_then_apply_returns_input(x64):
    y = jax.random.normal(jax.random.PRNGKey(0), (5, 8, 8))
    np.testing.assert_allclose(laplace(solve_poisson(y)), y, atol=1e-12)
    np.testing.assert_allclose(solve_poisson(laplace(y)), y, atol=1e-12)


def test_smooth_fields_are_normalised_and_smoother_with_smoothness():
    rough = smooth_fields(jax.random.PRNGKey(1), 64, 8, 0.0, jnp.float32)
    smooth = smooth_fields(jax.random.PRNGKey(1), 64, 8, 1.0, jnp.float32)
    for fields in (rough, smooth):
        np.testing.assert_allclose(fields.mean(axis=(1, 2)), 0, atol=1e-5)
        np.testing.assert_allclose(fields.std(axis=(1, 2)), 1, atol=1e-4)
    # a smoother spectrum leaves less energy in the Laplacian (the high frequencies)
    assert jnp.mean(laplace(smooth) ** 2) < 0.5 * jnp.mean(laplace(rough) ** 2)


def test_reference_network_and_data():
    scene = build(jax.random.PRNGKey(0), grid=8, smoothness=1.0, test_size=16)
    params = scene.init_params(jax.random.PRNGKey(1))
    assert count_params(params) == 24_896
    batch = scene.sample_train(jax.random.PRNGKey(2), 64)
    assert batch["target"].shape == (64, 64)
    np.testing.assert_allclose(
        batch["target"], laplace(batch["field"].reshape(64, 8, 8)).reshape(64, 64), atol=1e-5
    )
    # a network that returned the true field would have zero loss and zero field error
    y = scene.batch_output(params, batch)
    assert y.shape == (64, 64)
    exact = jax.vmap(scene.sample_loss)(batch["target"], batch)
    np.testing.assert_allclose(exact, 0, atol=0)
    loss = scene.batch_loss(y, batch)
    np.testing.assert_allclose(
        loss,
        np.mean(0.5 * np.sum((np.asarray(y) - np.asarray(batch["target"])) ** 2, 1)),
        rtol=1e-5,
    )
