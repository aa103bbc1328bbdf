"""Levenberg-Marquardt (physgrad.optim.spectral.marquardt_rule) against closed forms in float64, its
damping adaptation, and the rules that take optax's extra arguments (L-BFGS) through a real run."""

import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
import physgrad.optim
from physgrad.optim.spectral import (
    marquardt_direction,
    marquardt_rule,
    truncated_spectral_direction,
)


def random_problem(m=6, n=10, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.normal(size=(m, n))), jnp.asarray(rng.normal(size=m))


@pytest.mark.parametrize("route", ["svd", "gram"])
def test_vanishing_damping_gives_the_gauss_newton_step(x64, route):
    jac, g = random_problem()
    lm = marquardt_direction(jac, g, 1e-14, 1e-12, route)[0]
    gn = truncated_spectral_direction(jac, g, 1.0, 1e-12, "svd")
    np.testing.assert_allclose(lm, gn, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("route", ["svd", "gram"])
def test_large_damping_gives_a_scaled_gradient_step(x64, route):
    jac, g = random_problem(seed=1)
    mu = 1e8
    lam = mu * float(jnp.max(jnp.linalg.svd(jac, compute_uv=False)) ** 2)
    np.testing.assert_allclose(
        marquardt_direction(jac, g, mu, 1e-12, route)[0], jac.T @ g / lam, rtol=1e-6
    )


def test_damping_interpolates_as_the_closed_form(x64):
    """d = J^T (J J^T + lambda I)^-1 g, solved directly."""
    jac, g = random_problem(seed=2)
    mu = 0.3
    lam = mu * float(jnp.max(jnp.linalg.eigvalsh(jac @ jac.T)))
    direct = jac.T @ jnp.linalg.solve(jac @ jac.T + lam * jnp.eye(6), g)
    np.testing.assert_allclose(marquardt_direction(jac, g, mu, 0.0, "svd")[0], direct, rtol=1e-9)


def linear_least_squares(seed=3, m=9, n=4):
    rng = np.random.default_rng(seed)
    a, b = jnp.asarray(rng.normal(size=(m, n))), jnp.asarray(rng.normal(size=m))

    def loss(theta):
        return 0.5 * jnp.sum((a @ theta - b) ** 2)

    return a, b, loss


def test_a_linear_least_squares_problem_is_solved_in_one_step(x64):
    a, b, loss = linear_least_squares()
    theta = jnp.zeros(4)
    rule = marquardt_rule(learning_rate=1.0, damping=1e-12, tau=1e-10, route="auto")
    state = rule.init(theta)
    update, state = rule.update(
        theta, state, theta, jacobian=a, output_grad=a @ theta - b, value=loss(theta), value_fn=loss
    )
    solution = np.linalg.lstsq(np.asarray(a), np.asarray(b), rcond=None)[0]
    np.testing.assert_allclose(theta + update, solution, rtol=1e-8)
    # rho = 1: mu / 3
    assert not bool(state.rejected) and float(state.mu) == pytest.approx(1e-12 / 3)


def test_a_step_that_raises_the_loss_is_rejected_and_the_damping_grows(x64):
    a, b, loss = linear_least_squares()
    theta = jnp.ones(4)
    rule = marquardt_rule(learning_rate=1.0, damping=1e-2)
    state = rule.init(theta)
    worse = lambda p: loss(p) + 100.0  # noqa: E731 - every trial point looks worse
    for growth in (2.0, 4.0):
        mu_before = float(state.mu)
        update, state = rule.update(
            theta,
            state,
            theta,
            jacobian=a,
            output_grad=a @ theta - b,
            value=loss(theta),
            value_fn=worse,
        )
        assert bool(state.rejected) and np.all(np.asarray(update) == 0.0)
        assert float(state.mu) == pytest.approx(mu_before * growth)
    # the true loss: accepted, nu back to 2
    update, state = rule.update(
        theta, state, theta, jacobian=a, output_grad=a @ theta - b, value=loss(theta), value_fn=loss
    )
    assert (
        not bool(state.rejected) and float(state.nu) == 2.0 and loss(theta + update) < loss(theta)
    )


# both through the runner in make test-long (make test: their rules in test_rule_contract.py, and
# Levenberg-Marquardt through the runner in test_configs.py's pairs)
@pytest.mark.parametrize(
    "optim, batch",
    [
        pytest.param("levenberg_marquardt", 64, marks=pytest.mark.long),
        pytest.param("lbfgs", 1024, marks=pytest.mark.long),
    ],
)
def test_the_rules_train_a_scene_through_the_runner(optim, batch, tmp_path):
    """The well-conditioned toy's loss (lambda = 1) at least halves in 100 steps. L-BFGS gets a
    large batch: at 64 fresh samples per step its line search and curvature pairs follow
    the noise."""
    run = physgrad.run(
        "task=toy",
        "task.scale=1",
        f"optim={optim}",
        "trainer.iterations=100",
        "trainer.eval_every=50",
        "precision=64",
        f"trainer.batch_size={batch}",
        out_dir=tmp_path,
    )
    assert run.attrs["status"] == "completed" and run.eval["loss"][-1] < 0.5 * run.eval["loss"][0]
    if optim == "levenberg_marquardt":
        assert {"damping", "rejected_step", "kept_singular_values"} <= set(run.train)
        assert np.all(run.train["damping"] > 0)


def test_only_rules_that_need_extra_arguments_get_them():
    import optax

    params = jnp.zeros(3)
    assert physgrad.optim.needs_value_arguments(optax.lbfgs(), params)
    assert physgrad.optim.needs_value_arguments(optax.chain(optax.clip(1.0), optax.lbfgs()), params)
    for plain in (optax.adam(1e-3), optax.sgd(0.1), optax.chain(optax.clip(1.0), optax.adam(1e-3))):
        assert not physgrad.optim.needs_value_arguments(plain, params)
