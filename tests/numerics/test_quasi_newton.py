"""Numerics layer: the self-scaled Broyden family (physgrad.optim.quasi_newton) against independent
references: the update against the Hessian form of the same family written with NumPy (its inverse
taken by LAPACK), finite termination of BFGS with exact line searches on a quadratic, the whole rule
(zoom line search included) against SciPy's BFGS on the Rosenbrock function, and the refusal of a
network too large for a dense matrix."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.optimize

from physgrad.errors import UserError
from physgrad.optim.quasi_newton import VARIANTS, self_scaled_broyden, updated_inverse_hessian


def reference_parameters(variant, a, b, h, first, size):
    """theta_k and tau_k as Al-Baali and Khalfan state them, scalar by scalar."""
    if variant == "bfgs":
        return 0.0, 1.0
    if variant == "ssbfgs":
        return 0.0, (h if first else min(1.0, 1.0 / b))
    c = math.sqrt(a / (1 + a))
    rho_minus = min(1.0, h * (1 - c))
    theta = max((rho_minus - 1) / a, min(1 / rho_minus, (1 - b) / b))
    sigma = 1 + theta * a
    if first:
        return theta, h / sigma
    rho = min(1.0, 1.0 / b)
    root = abs(sigma) ** (1 / (1 - size))
    return theta, (min(rho * root, sigma) if theta <= 0 else rho * min(root, 1 / theta))


def reference_update(variant, inverse_hessian, s, y, previous_grad, step_size, first):
    """The family in its Hessian form, B_{k+1} = tau (B - B s s^T B / s^T B s + theta (s^T B s) w
    w^T) + y y^T / y^T s with w = y / y^T s - B s / s^T B s, on B = H^-1; returned inverted."""
    B = np.linalg.inv(inverse_hessian)
    Bs = B @ s
    sBs, ys = s @ Bs, y @ s
    h = y @ inverse_hessian @ y / ys
    b = -step_size * (s @ previous_grad) / ys
    theta, tau = reference_parameters(variant, b * h - 1, b, h, first, len(s))
    w = y / ys - Bs / sBs
    new = tau * (B - np.outer(Bs, Bs) / sBs + theta * sBs * np.outer(w, w)) + np.outer(y, y) / ys
    return np.linalg.inv(new)


@pytest.mark.parametrize("first", [True, False])
@pytest.mark.parametrize("variant", VARIANTS)
def test_the_update_is_the_inverse_of_the_hessian_form(variant, first, x64):
    rng = np.random.default_rng(3)
    size = 6
    thetas = []
    # the true Hessian a multiple of B = H^-1 plus a perturbation: b_k = s^T B s / y^T s about 1 /
    # scale, so that SSBroyden's theta_k falls below, inside and above its bounds
    for scale in (0.2, 0.7, 1.0, 1.4, 3.0, 10.0):
        m = rng.normal(size=(size, size))
        inverse_hessian = m @ m.T / size + 0.5 * np.eye(size)
        previous_grad = rng.normal(size=size)
        step_size = rng.uniform(0.1, 2.0)
        s = -step_size * inverse_hessian @ previous_grad  # a step along -H g
        e = 0.3 * rng.normal(size=(size, size))
        hessian = scale * np.linalg.inv(inverse_hessian) + e @ e.T
        y = hessian @ s  # the change of gradient of a convex quadratic
        ys = y @ s
        b = step_size**2 * previous_grad @ inverse_hessian @ previous_grad / ys
        h = y @ inverse_hessian @ y / ys
        thetas.append(reference_parameters("ssbroyden", b * h - 1, b, h, first, size)[0])
        got, updated = updated_inverse_hessian(
            variant,
            jnp.asarray(inverse_hessian),
            jnp.asarray(s),
            jnp.asarray(y),
            jnp.asarray(previous_grad),
            jnp.asarray(step_size),
            jnp.asarray(first),
        )
        want = reference_update(variant, inverse_hessian, s, y, previous_grad, step_size, first)
        assert bool(updated)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10)
        # the secant condition every member satisfies: H_{k+1} y = s
        np.testing.assert_allclose(np.asarray(got) @ y, s, rtol=1e-8, atol=1e-12)
    assert min(thetas) < 0 < max(thetas) and any(0 < t < 1 for t in thetas), thetas


def test_a_step_without_positive_curvature_keeps_the_matrix(x64):
    inverse_hessian = jnp.eye(3) * 2.0
    s = jnp.array([1.0, 0.0, 0.0])
    for y in (jnp.array([-1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]), jnp.full(3, jnp.nan)):
        got, updated = updated_inverse_hessian(
            "ssbroyden", inverse_hessian, s, y, -s, jnp.asarray(1.0), jnp.asarray(False)
        )
        assert not bool(updated)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(inverse_hessian))


@pytest.mark.parametrize("variant", VARIANTS)
def test_exact_line_searches_end_on_a_quadratic_in_n_steps(variant, x64):
    """On f = 1/2 x^T A x - c^T x with exact line searches the family's directions are conjugate, so
    the minimum A^-1 c is reached in n steps; BFGS's H_n is then A^-1 itself (scaling keeps the
    directions, not the matrix)."""
    rng = np.random.default_rng(0)
    size = 7
    m = rng.normal(size=(size, size))
    A = m @ m.T + 0.1 * np.eye(size)
    c = rng.normal(size=size)
    x = np.zeros(size)
    H = np.eye(size)
    count = 0
    for _ in range(size):
        g = A @ x - c
        d = H @ g
        alpha = (g @ d) / (d @ A @ d)  # the exact minimiser along -d
        s = -alpha * d
        x = x + s
        H, updated = updated_inverse_hessian(
            variant,
            jnp.asarray(H),
            jnp.asarray(s),
            jnp.asarray(A @ s),
            jnp.asarray(g),
            jnp.asarray(alpha),
            jnp.asarray(count == 0),
        )
        H = np.asarray(H)
        count += int(updated)
    np.testing.assert_allclose(x, np.linalg.solve(A, c), rtol=1e-7, atol=1e-9)
    if variant == "bfgs":
        np.testing.assert_allclose(H, np.linalg.inv(A), rtol=1e-6, atol=1e-8)


def rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


# make test-long: SSBFGS and SSBroyden (the same zoom line search, another update); make test keeps
# BFGS here and every variant's update against its Hessian form
# (test_the_update_is_the_inverse_of_the_hessian_form)
@pytest.mark.parametrize(
    "variant", [v if v == "bfgs" else pytest.param(v, marks=pytest.mark.long) for v in VARIANTS]
)
def test_the_rule_with_its_line_search_finds_scipys_bfgs_minimum_of_rosenbrock(variant, x64):
    start = np.array([-1.2, 1.0, -0.5, 0.8])
    scipy_result = scipy.optimize.minimize(
        lambda x: float(rosenbrock(jnp.asarray(x))),
        start,
        jac=lambda x: np.asarray(jax.grad(rosenbrock)(jnp.asarray(x))),
        method="BFGS",
        options={"gtol": 1e-10},
    )
    rule = self_scaled_broyden(variant=variant)

    @jax.jit
    def step(x, state):
        value, grad = jax.value_and_grad(rosenbrock)(x)
        updates, state = rule.update(grad, state, x, value=value, grad=grad, value_fn=rosenbrock)
        return optax.apply_updates(x, updates), state

    x, state = jnp.asarray(start), rule.init(jnp.asarray(start))
    for _ in range(150):
        x, state = step(x, state)
    # SciPy's BFGS took 36 iterations from this start; the family's members within 150, to the
    # same minimum (1, 1, 1, 1) within 1e-8
    assert scipy_result.success
    np.testing.assert_allclose(np.asarray(x), scipy_result.x, atol=1e-8)
    np.testing.assert_allclose(np.asarray(x), np.ones(4), atol=1e-8)
    assert int(state[0].count) > 10  # the matrix was updated, not left the identity


def test_a_network_larger_than_max_parameters_is_refused_in_one_line():
    rule = self_scaled_broyden(variant="ssbfgs", max_parameters=10)
    with pytest.raises(UserError) as refused:
        rule.init({"w": jnp.zeros((3, 4))})
    message = str(refused.value)
    assert "\n" not in message and "12 parameters" in message
    assert "optim.max_parameters=10" in message and "optim=lbfgs" in message
    with pytest.raises(UserError, match="optim.variant=dfp"):
        self_scaled_broyden(variant="dfp")


# L-BFGS in make test; SSBroyden (the same zoom line search, read the same way) in make test-long
@pytest.mark.parametrize("rule", ["lbfgs", pytest.param("ssbroyden", marks=pytest.mark.long)])
def test_the_logged_line_search_evaluations_are_the_evaluations_made(rule):
    """What the calibrated clock charges a line-search step (physgrad.optim.state_logs'
    linesearch_evaluations) against a count kept outside the rule: every evaluation of the loss the
    jitted update makes calls back once (jax.debug.callback in the loss), over 25 steps on the
    Rosenbrock function with the direction scaled by 30 before the line search (what tuning the
    learning rate of these rules does), where the zoom line search needs from 1 to many
    evaluations a step."""
    from physgrad.optim import LINE_SEARCH_LOG, state_logs

    calls = []

    def loss(x):
        jax.debug.callback(lambda: calls.append(1))
        return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2)

    scale = 30.0
    transform = optax.lbfgs(scale) if rule == "lbfgs" else self_scaled_broyden(scale)
    params = jnp.array([-1.2, 1.0, -0.5, 0.8])
    state = transform.init(params)

    @jax.jit
    def update(params, state):
        value, grad = jax.value_and_grad(loss)(params)
        updates, state = transform.update(
            grad, state, params, value=value, grad=grad, value_fn=loss
        )
        return optax.apply_updates(params, updates), state, state_logs(state)[LINE_SEARCH_LOG]

    counts = []
    for _ in range(25):
        before = len(calls) + 1  # the step's own evaluation of the loss for its gradient
        params, state, logged = update(params, state)
        jax.effects_barrier()
        counts.append((len(calls) - before, float(logged)))
    assert [made for made, _ in counts] == [logged for _, logged in counts]
    assert max(made for made, _ in counts) > 1 and min(made for made, _ in counts) >= 1
