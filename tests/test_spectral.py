"""The truncated-SVD kernel and the Gauss-Newton / HIG transformations against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.optim.spectral import (gauss_newton, hig, per_sample_jacobian, spectral_rule,
                                     truncated_spectral_direction)


def random_orthogonal(key, n):
    q, _ = jnp.linalg.qr(jax.random.normal(key, (n, n)))
    return q


@pytest.mark.parametrize("kappa", [1.0, 0.5, 0.0, -1.0])
def test_diagonal_jacobian_closed_form(x64, kappa):
    s = jnp.array([4.0, 1.0, 0.25, 1e-9])
    jac = jnp.zeros((4, 6)).at[jnp.arange(4), jnp.arange(4)].set(s)
    g = jnp.array([1.0, -2.0, 3.0, 5.0])
    direction = truncated_spectral_direction(jac, g, kappa, tau=1e-6)
    # s_i^-kappa * g_i on the kept diagonal entries; the entry with s = 1e-9 <= 1e-6 * 4 contributes exactly 0
    expected = jnp.zeros(6).at[:3].set(s[:3] ** -kappa * g[:3])
    np.testing.assert_allclose(direction, expected, rtol=1e-12, atol=0)
    assert direction[3] == 0.0


def test_rotated_jacobian_closed_form(x64):
    """J = U diag(s) V^T with known factors: the direction is V diag(s^-1/2) U^T g."""
    u = random_orthogonal(jax.random.PRNGKey(0), 5)
    v = random_orthogonal(jax.random.PRNGKey(1), 8)[:, :5]
    s = jnp.array([3.0, 2.0, 1.0, 0.5, 0.1])
    jac = u @ jnp.diag(s) @ v.T
    g = jax.random.normal(jax.random.PRNGKey(2), (5,))
    np.testing.assert_allclose(truncated_spectral_direction(jac, g, 0.5, 1e-6), v @ (s ** -0.5 * (u.T @ g)),
                               rtol=1e-10, atol=1e-12)
    # tau between 0.1/3 and 0.5/3 drops exactly the smallest singular value
    truncated = truncated_spectral_direction(jac, g, 0.5, 0.1)
    np.testing.assert_allclose(truncated, v[:, :4] @ (s[:4] ** -0.5 * (u.T @ g)[:4]), rtol=1e-10, atol=1e-12)


def test_zero_jacobian_gives_zero_update(x64):
    for dtype in (jnp.float32, jnp.float64):
        direction = truncated_spectral_direction(jnp.zeros((3, 7), dtype), jnp.ones(3, dtype), 0.5, 1e-6)
        assert jnp.all(direction == 0.0) and direction.shape == (7,)


def test_kappa_minus_one_is_the_plain_gradient(x64):
    jac = jax.random.normal(jax.random.PRNGKey(3), (6, 10))
    g = jax.random.normal(jax.random.PRNGKey(4), (6,))
    np.testing.assert_allclose(truncated_spectral_direction(jac, g, -1.0, 0.0), jac.T @ g, rtol=1e-10, atol=1e-12)


def linear_problem(key, batch=3, outputs=2, params=7):
    """Per-sample y_i = A_i theta (a pytree of two leaves), per-sample loss 1/2 |y_i - b_i|^2, mean over i."""
    ka, kb, kt = jax.random.split(key, 3)
    data = {"a": jax.random.normal(ka, (batch, outputs, params)), "b": jax.random.normal(kb, (batch, outputs))}
    theta = {"w": jax.random.normal(kt, (params - 2,)), "c": jnp.zeros(2)}

    def sample_output(p, sample):
        return sample["a"] @ jnp.concatenate([p["w"], p["c"]])

    def batch_loss(p):
        y = jax.vmap(sample_output, in_axes=(None, 0))(p, data)
        return jnp.mean(0.5 * jnp.sum((y - data["b"]) ** 2, axis=1)), y

    return data, theta, sample_output, batch_loss


def step(rule, params, data, sample_output, batch_loss):
    (loss, y), grads = jax.value_and_grad(batch_loss, has_aux=True)(params)
    output_grad = (y - data["b"]) / y.shape[0]  # dL/dy for the mean loss
    updates, _ = rule.update(grads, rule.init(params), params, sample_output=sample_output, batch=data,
                             output_grad=output_grad)
    return optax.apply_updates(params, updates), loss


def test_per_sample_jacobian_matches_dense_jacobian(x64):
    data, theta, sample_output, _ = linear_problem(jax.random.PRNGKey(5))
    jac = per_sample_jacobian(sample_output, theta, data)
    # ravel_pytree orders leaves by key: "c" before "w"
    dense = jnp.concatenate([data["a"][..., 5:], data["a"][..., :5]], axis=-1).reshape(6, 7)
    np.testing.assert_allclose(jac, dense, rtol=1e-12)


def test_gauss_newton_solves_linear_least_squares_in_one_step(x64):
    """Mean-loss convention: g = (y - b) / B, so the full Gauss-Newton step is lr = B."""
    data, theta, sample_output, batch_loss = linear_problem(jax.random.PRNGKey(6))
    solved, before = step(gauss_newton(3.0, 1e-10), theta, data, sample_output, batch_loss)
    after, _ = batch_loss(solved)
    # 6 equations, 7 unknowns: an exact solution exists and Gauss-Newton lands on it
    assert before > 1.0
    np.testing.assert_allclose(after, 0.0, atol=1e-20)


def test_hig_transformation_equals_kernel(x64):
    data, theta, sample_output, batch_loss = linear_problem(jax.random.PRNGKey(7))
    new, _ = step(hig(0.3, 1e-6), theta, data, sample_output, batch_loss)
    jac = per_sample_jacobian(sample_output, theta, data)
    y = jax.vmap(sample_output, in_axes=(None, 0))(theta, data)
    expected = -0.3 * truncated_spectral_direction(jac, ((y - data["b"]) / 3).ravel(), 0.5, 1e-6)
    flat = jnp.concatenate([new["c"] - theta["c"], new["w"] - theta["w"]])
    np.testing.assert_allclose(flat, expected, rtol=1e-10, atol=1e-14)


def test_kappa_minus_one_rule_takes_a_gradient_descent_step(x64):
    data, theta, sample_output, batch_loss = linear_problem(jax.random.PRNGKey(8))
    new, _ = step(spectral_rule(0.1, -1.0, 0.0), theta, data, sample_output, batch_loss)
    grads = jax.grad(lambda p: batch_loss(p)[0])(theta)
    for key in theta:
        np.testing.assert_allclose(new[key], theta[key] - 0.1 * grads[key], rtol=1e-10, atol=1e-14)


def test_missing_extra_arguments_are_an_error():
    rule = hig(1.0, 1e-6)
    params = {"w": jnp.ones(3)}
    with pytest.raises(TypeError):
        rule.update(params, rule.init(params), params)
