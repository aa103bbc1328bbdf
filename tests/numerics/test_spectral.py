"""The truncated-SVD kernel and the Gauss-Newton / HIG transformations against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.jacobians import dense_jacobian
from physgrad.optim.spectral import (
    gauss_newton,
    hig,
    resolve_route,
    spectral_rule,
    truncated_spectral_direction,
)
from tests.helpers import float32_factorisation_fails

ROUTES = pytest.mark.parametrize("route", ["svd", "gram"])


def output_and_jacobian(sample_output, params, batch):
    y, jac = dense_jacobian(sample_output, params, batch)
    return y, jac.matrix


def random_orthogonal(key, n):
    q, _ = jnp.linalg.qr(jax.random.normal(key, (n, n)))
    return q


@ROUTES
@pytest.mark.parametrize("kappa", [1.0, 0.5, 0.0, -1.0])
def test_diagonal_jacobian_closed_form(x64, kappa, route):
    s = jnp.array([4.0, 1.0, 0.25, 1e-9])
    jac = jnp.zeros((4, 6)).at[jnp.arange(4), jnp.arange(4)].set(s)
    g = jnp.array([1.0, -2.0, 3.0, 5.0])
    direction = truncated_spectral_direction(jac, g, kappa, tau=1e-6, route=route)
    # s_i^-kappa * g_i on the kept diagonal entries; the entry with s = 1e-9 <= 1e-6 * 4 contributes
    # exactly 0
    expected = jnp.zeros(6).at[:3].set(s[:3] ** -kappa * g[:3])
    np.testing.assert_allclose(direction, expected, rtol=1e-12, atol=0)
    assert direction[3] == 0.0


@ROUTES
def test_rotated_jacobian_closed_form(x64, route):
    """J = U diag(s) V^T with known factors: the direction is V diag(s^-1/2) U^T g."""
    u = random_orthogonal(jax.random.PRNGKey(0), 5)
    v = random_orthogonal(jax.random.PRNGKey(1), 8)[:, :5]
    s = jnp.array([3.0, 2.0, 1.0, 0.5, 0.1])
    jac = u @ jnp.diag(s) @ v.T
    g = jax.random.normal(jax.random.PRNGKey(2), (5,))
    np.testing.assert_allclose(
        truncated_spectral_direction(jac, g, 0.5, 1e-6, route),
        v @ (s**-0.5 * (u.T @ g)),
        rtol=1e-10,
        atol=1e-12,
    )
    # tau between 0.1/3 and 0.5/3 drops exactly the smallest singular value
    truncated = truncated_spectral_direction(jac, g, 0.5, 0.1, route)
    np.testing.assert_allclose(
        truncated, v[:, :4] @ (s[:4] ** -0.5 * (u.T @ g)[:4]), rtol=1e-10, atol=1e-12
    )


@ROUTES
def test_zero_jacobian_gives_zero_update(x64, route):
    for dtype in (jnp.float32, jnp.float64):
        direction = truncated_spectral_direction(
            jnp.zeros((3, 7), dtype), jnp.ones(3, dtype), 0.5, 1e-6, route
        )
        assert jnp.all(direction == 0.0) and direction.shape == (7,) and direction.dtype == dtype


@ROUTES
def test_kappa_minus_one_is_the_plain_gradient(x64, route):
    jac = jax.random.normal(jax.random.PRNGKey(3), (6, 10))
    g = jax.random.normal(jax.random.PRNGKey(4), (6,))
    np.testing.assert_allclose(
        truncated_spectral_direction(jac, g, -1.0, 0.0, route), jac.T @ g, rtol=1e-10, atol=1e-12
    )


def test_float32_gram_route_resolves_a_wide_spectrum():
    """A float32 J with singular values from 1 down to 1e-5 and tau = 1e-6 keeps them all. The Gram
    route works in float64 on J as given, so it reproduces the exact direction of that float32 J to
    ~1e-6 although s^2 spans 1e-10, which a float32 Gram matrix (relative error ~1e-7 of max s^2)
    could not resolve."""
    m, n = 40, 90
    u = np.linalg.qr(np.random.default_rng(0).normal(size=(m, m)))[0]
    v = np.linalg.qr(np.random.default_rng(1).normal(size=(n, m)))[0]
    s = np.logspace(0, -5, m)
    jac32 = (u * s) @ v.T
    jac32 = jac32.astype(np.float32)
    g = np.random.default_rng(2).normal(size=m)
    # the exact direction of the float32 matrix, from a float64 SVD of it
    u64, s64, vt64 = np.linalg.svd(jac32.astype(np.float64), full_matrices=False)
    exact = vt64.T @ (s64**-0.5 * (u64.T @ g))
    gram = np.asarray(
        truncated_spectral_direction(
            jnp.asarray(jac32), jnp.asarray(g, jnp.float32), 0.5, 1e-6, "gram"
        )
    )
    assert gram.dtype == np.float32
    # measured 5e-8; a float32 SVD of the same J misses by 1e-3
    assert np.linalg.norm(gram - exact) / np.linalg.norm(exact) < 1e-6


def test_auto_route_takes_gram_only_where_it_resolves_tau():
    assert resolve_route("auto", 1e-6, (512, 2956)) == "gram"
    assert resolve_route("auto", 1e-8, (512, 2956)) == "svd"  # s^2 below float64's reach
    # tall J: its Gram matrix is the larger one
    assert resolve_route("auto", 1e-5, (300, 200)) == "svd"
    assert resolve_route("svd", 1e-2, (2, 5)) == "svd"


def linear_problem(key, batch=3, outputs=2, params=7):
    """Per-sample y_i = A_i theta (a pytree of two leaves), per-sample loss 1/2 |y_i - b_i|^2, mean
    over i."""
    ka, kb, kt = jax.random.split(key, 3)
    data = {
        "a": jax.random.normal(ka, (batch, outputs, params)),
        "b": jax.random.normal(kb, (batch, outputs)),
    }
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
    _, jac = output_and_jacobian(sample_output, params, data)
    updates, _ = rule.update(
        grads, rule.init(params), params, jacobian=jac, output_grad=output_grad
    )
    return optax.apply_updates(params, updates), loss


def test_output_and_jacobian_match_the_dense_jacobian_and_the_forward_pass(x64):
    data, theta, sample_output, _ = linear_problem(jax.random.PRNGKey(5))
    y, jac = output_and_jacobian(sample_output, theta, data)
    np.testing.assert_allclose(
        y, jax.vmap(sample_output, in_axes=(None, 0))(theta, data), rtol=1e-12
    )
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
    y, jac = output_and_jacobian(sample_output, theta, data)
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


@pytest.mark.parametrize("retry", [True, False])
def test_a_failed_factorisation_is_retried_in_float64_and_counted_only_if_it_stays_failed(
    monkeypatch, retry
):
    float32_factorisation_fails(monkeypatch)
    data, theta, sample_output, batch_loss = linear_problem(jax.random.PRNGKey(9))
    (loss, y), _ = jax.value_and_grad(batch_loss, has_aux=True)(theta)
    g = (y - data["b"]) / 3
    rule = spectral_rule(1.0, 0.5, 1e-6, "svd", retry_float64=retry)
    _, jac = output_and_jacobian(sample_output, theta, data)
    updates, state = jax.jit(lambda p, s: rule.update(p, s, p, jacobian=jac, output_grad=g))(
        theta, rule.init(theta)
    )
    failures = optax.tree.get(state, "failures")
    if retry:
        with jax.enable_x64(True):
            expected = -truncated_spectral_direction(
                jac.astype(jnp.float64), g.ravel().astype(jnp.float64), 0.5, 1e-6
            )
        flat = jnp.concatenate([updates["c"], updates["w"]])
        assert flat.dtype == jnp.float32 and failures == 0
        np.testing.assert_allclose(flat, expected, rtol=1e-5, atol=1e-6)
    else:
        assert failures == 1 and not jnp.isfinite(updates["w"]).any()


def test_seeds_trained_together_retry_only_the_seed_whose_factorisation_failed(monkeypatch):
    """Three seeds in one vmapped step (the seeds' named axis, as physgrad.training vectorises):
    the float32 factorisation fails for seed 1 only. Seed 1 takes the float64 result; seeds 0 and
    2 keep their own float32 update bit for bit; none is counted as failed; and the retry stays one
    cond for all seeds (float64 only in a step where one failed), not a select that computes it
    every step."""
    import physgrad.optim.spectral as spectral
    from physgrad.jacobians import as_jacobian
    from physgrad.training import over_seeds

    real = spectral._direction

    def flaky(jac, g, kappa, tau, route="svd"):  # fails where J's first entry is above 1, in f32
        result, kept = real(jac, g, kappa, tau, route)
        bad = (as_jacobian(jac).dense()[0, 0] > 1.0) & (jac.dtype == jnp.float32)
        return jnp.where(bad, jnp.nan, result), kept

    monkeypatch.setattr(spectral, "_direction", flaky)
    rule = spectral_rule(1.0, 0.5, 1e-6, "svd", retry_float64=True)
    seeds = []
    for key in range(3):
        data, theta, sample_output, batch_loss = linear_problem(jax.random.PRNGKey(20 + key))
        first = 2.0 if key == 1 else -2.0  # only seed 1's factorisation fails
        data["a"] = data["a"].at[:, 0, 0].set(first)
        (_, y), _ = jax.value_and_grad(batch_loss, has_aux=True)(theta)
        _, jac = output_and_jacobian(sample_output, theta, data)
        seeds.append((theta, jac, (y - data["b"]) / 3))
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *seeds)

    def update(theta, jac, g):
        return rule.update(theta, rule.init(theta), theta, jacobian=jac, output_grad=g)

    together = over_seeds(update, 3, (0, 0, 0))
    (updates, state) = jax.jit(together)(*stacked)
    assert optax.tree.get(state, "failures").tolist() == [0, 0, 0]
    for index, (theta, jac, g) in enumerate(seeds):
        alone, _ = jax.jit(update)(theta, jac, g)
        mine = jax.tree_util.tree_map(lambda leaf: leaf[index], updates)
        if index == 1:
            with jax.enable_x64(True):
                expected = -truncated_spectral_direction(
                    jac.astype(jnp.float64), g.ravel().astype(jnp.float64), 0.5, 1e-6
                )
            flat = jnp.concatenate([mine["c"], mine["w"]])
            np.testing.assert_allclose(flat, expected, rtol=1e-5, atol=1e-6)
        else:
            for key in theta:
                np.testing.assert_array_equal(mine[key], alone[key])
    jaxpr = jax.make_jaxpr(together)(*stacked).jaxpr
    names = {eqn.primitive.name for eqn in jaxpr.eqns}
    conds = [eqn for eqn in jaxpr.eqns if eqn.primitive.name == "cond"]
    # one predicate for all seeds: the cond's predicate is a scalar, reduced over the seeds' axis
    assert "psum" in names and conds and all(eqn.invars[0].aval.shape == () for eqn in conds)


def test_non_finite_jacobian_is_not_counted_as_a_factorisation_failure():
    rule = spectral_rule(1.0, 0.5, 1e-6, "svd")
    params = {"w": jnp.ones(3)}
    batch = {"a": jnp.full((2, 3), jnp.inf)}
    _, jac = output_and_jacobian(lambda p, s: s["a"] * p["w"], params, batch)
    _, state = rule.update(
        params, rule.init(params), params, jacobian=jac, output_grad=jnp.ones((2, 3))
    )
    assert optax.tree.get(state, "failures") == 0


@pytest.mark.parametrize("route", ["svd", "gram", "auto"])
def test_the_configured_route_is_the_one_that_runs(monkeypatch, route):
    """optim.route from the config reaches the kernel: a stand-in for each route records which one
    ran."""
    import physgrad.optim.spectral as spectral
    from physgrad.optim import build_rule
    from tests.helpers import load

    ran = []
    monkeypatch.setattr(
        spectral,
        "svd_direction",
        lambda jac, g, kappa, tau: ran.append("svd") or (jac.dense().T @ g, 0),
    )
    monkeypatch.setattr(
        spectral,
        "gram_direction",
        lambda jac, g, kappa, tau: ran.append("gram") or (jac.dense().T @ g, 0),
    )
    rule = build_rule(load("optim=hig", f"optim.route={route}").optim)
    params = {"w": jnp.ones(5)}
    rule.transform.update(
        params,
        rule.transform.init(params),
        params,
        jacobian=jnp.ones((3, 5)),
        output_grad=jnp.ones((3, 1)),
    )
    # traced twice (the float64 retry's branch too), always by the configured kernel; auto: a wide J
    # and the default tau take the Gram route
    assert ran and set(ran) == {{"auto": "gram"}.get(route, route)}


def test_the_toy_physics_scales_the_network_s_second_output_and_not_the_target():
    from physgrad.nets import apply_mlp
    from physgrad.tasks import build_scene
    from tests.helpers import load

    scene = build_scene(
        load("task=toy", "task.scale=0.25", "task.test_size=4").task, jax.random.PRNGKey(0)
    )
    params = scene.init_params(jax.random.PRNGKey(1))
    sample = jax.tree_util.tree_map(lambda leaf: leaf[0], scene.test_set)
    np.testing.assert_allclose(
        scene.sample_output(params, sample),
        jnp.array([1.0, 0.25]) * apply_mlp(params, sample["x"], hidden="tanh"),
        rtol=1e-6,
    )
    np.testing.assert_allclose(
        sample["target"],
        jnp.array([jnp.sin(6 * sample["x"][0]), jnp.cos(9 * sample["x"][0])]),
        rtol=1e-5,
    )
