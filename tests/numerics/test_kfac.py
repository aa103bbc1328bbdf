"""K-FAC (physgrad.optim.kfac) against its closed form built from the dense Jacobian with Kronecker
products (float64), its limits (no damping on an exactly Kronecker-factored problem: the
Gauss-Newton step; large damping: a scaled gradient step), and through the runner: it trains, and a
network without layer factors is refused."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad.errors import UserError
from physgrad.jacobians import LayerJacobian, layer_jacobian, plan_layers
from physgrad.nets import apply_mlp, init_mlp
from physgrad.optim.kfac import kfac
from physgrad.optim.spectral import truncated_spectral_direction


def network_problem(sizes=(3, 5, 4, 2), batch=7, seed=0):
    """A tanh MLP followed by a fixed nonlinear 'physics' y = sin(P z): (params, layer J, g = dL/dy,
    dense J)."""
    rng = np.random.default_rng(seed)
    params = init_mlp(jax.random.PRNGKey(seed), sizes, jnp.float64)
    physics = jnp.asarray(rng.normal(size=(sizes[-1], 3)))
    inputs = jnp.asarray(rng.normal(size=(batch, sizes[0])))

    def sample_output(p, x):
        return jnp.sin(apply_mlp(p, x, "tanh") @ physics)

    plan = plan_layers(sample_output, params, inputs[0])
    assert not isinstance(plan, str), plan
    y, jac = layer_jacobian(sample_output, params, inputs, plan)
    g = jnp.asarray(rng.normal(size=y.shape))
    return params, jac, g, jac.dense()


def kronecker_reference(jac: LayerJacobian, g, damping):
    """The K-FAC step from the dense J: per layer, the columns of W_bar = [W; b] in (in + 1) x out
    row-major order, A and G from the factors' definitions, (B A_d (x) G_d)^-1 applied to that block
    of J^T g."""
    dense = np.asarray(jac.dense())
    gradient = dense.T @ np.asarray(g).reshape(-1)
    batch = jac.inputs[0].shape[0]
    sizes = [
        jac.inputs[leaf].shape[1] * jac.cotangents[leaf].shape[2]
        if kind == "w"
        else jac.cotangents[leaf].shape[2]
        for leaf, kind in jac.plan.leaves
    ]
    starts = np.cumsum([0, *sizes])
    step = np.zeros_like(gradient)
    for layer in range(len(jac.inputs)):
        a = np.asarray(jac.inputs[layer])
        a_bar = np.concatenate([a, np.ones((batch, 1))], axis=1)
        delta = np.asarray(jac.cotangents[layer]).reshape(-1, jac.cotangents[layer].shape[2])
        a_factor, g_factor = a_bar.T @ a_bar / batch, delta.T @ delta / batch
        a_damped = a_factor + np.sqrt(damping) * np.trace(a_factor) / len(a_factor) * np.eye(
            len(a_factor)
        )
        g_damped = g_factor + np.sqrt(damping) * np.trace(g_factor) / len(g_factor) * np.eye(
            len(g_factor)
        )
        w = jac.plan.leaves.index((layer, "w"))
        b = jac.plan.leaves.index((layer, "b"))
        fan_in = a.shape[1]
        block = np.concatenate(
            [gradient[starts[w] : starts[w + 1]], gradient[starts[b] : starts[b + 1]]]
        )
        solved = np.linalg.solve(batch * np.kron(a_damped, g_damped), block)
        step[starts[w] : starts[w + 1]] = solved[: fan_in * g_factor.shape[0]]
        step[starts[b] : starts[b + 1]] = solved[fan_in * g_factor.shape[0] :]
    return step


@functools.cache
def compiled_update(learning_rate, damping, plan):
    """The rule's update on J in factors with this plan, compiled as a training step compiles it
    (one program per setting, shared by the calls): called eagerly, each of its small operations
    was compiled one by one (5 s of the first test's 8 s). The same operations, compared at the
    same tolerances."""
    rule = kfac(learning_rate, damping)

    @jax.jit
    def update(flat, state, inputs, cotangents, g):
        factored = LayerJacobian(plan, inputs, cotangents)
        return rule.update(flat, state, flat, jacobian=factored, output_grad=g)

    return rule, update


def kfac_update(rule_damping, jac, g, learning_rate=1.0):
    rule, step = compiled_update(learning_rate, rule_damping, jac.plan)
    flat = jnp.zeros(jac.shape[1])
    update, state = step(flat, rule.init(flat), jac.inputs, jac.cotangents, g)
    return np.asarray(update), state


# one damping in make test, both ends in make test-long
@pytest.mark.parametrize(
    "damping",
    [pytest.param(1e-6, marks=pytest.mark.long), 1e-2, pytest.param(1.0, marks=pytest.mark.long)],
)
def test_the_step_is_the_kronecker_factored_gauss_newton_step(x64, damping):
    _, jac, g, _ = network_problem()
    update, state = kfac_update(damping, jac, g, learning_rate=0.5)
    np.testing.assert_allclose(
        update, -0.5 * kronecker_reference(jac, g, damping), rtol=1e-9, atol=1e-12
    )
    assert int(state.failures) == 0


def test_on_an_exactly_factored_problem_it_is_the_gauss_newton_step(x64):
    """One linear layer and a linear least-squares loss: every cotangent is a unit vector, so sum_k
    delta delta^T = I for every sample, J^T J = B A (x) I exactly, and K-FAC without damping is J^+
    g (m > n: full column rank), which solves the least-squares problem in one step."""
    rng = np.random.default_rng(3)
    batch, fan_in, fan_out = 12, 3, 2
    params = init_mlp(jax.random.PRNGKey(1), (fan_in, fan_out), jnp.float64)
    inputs = jnp.asarray(rng.normal(size=(batch, fan_in)))
    targets = jnp.asarray(rng.normal(size=(batch, fan_out)))
    sample_output = lambda p, x: apply_mlp(p, x, "tanh")  # noqa: E731 - one layer: linear output
    plan = plan_layers(sample_output, params, inputs[0])
    y, jac = layer_jacobian(sample_output, params, inputs, plan)
    g = y - targets  # dL/dy of L = 1/2 |y - t|^2
    update, _ = kfac_update(1e-24, jac, g)
    gauss_newton = truncated_spectral_direction(jac.dense(), g.reshape(-1), 1.0, 1e-12, "svd")
    np.testing.assert_allclose(update, -np.asarray(gauss_newton), rtol=1e-8, atol=1e-12)
    from jax.flatten_util import ravel_pytree

    flat, unravel = ravel_pytree(params)
    solved = unravel(flat + update)
    x_bar = np.concatenate([np.asarray(inputs), np.ones((batch, 1))], axis=1)
    best = np.linalg.lstsq(x_bar, np.asarray(targets), rcond=None)[0]
    np.testing.assert_allclose(np.asarray(solved[0]["w"]), best[:fan_in], rtol=1e-8)
    np.testing.assert_allclose(np.asarray(solved[0]["b"]), best[fan_in], rtol=1e-8)


# make test-long: K-FAC is not Gauss-Newton on a network with a hidden layer; make test keeps
# test_the_step_is_the_kronecker_factored_gauss_newton_step[0.01], whose closed form on such a
# network is not Gauss-Newton's step either
@pytest.mark.long
def test_on_a_deep_network_it_differs_from_gauss_newton(x64):
    """The factorisation is an approximation: on a network with a hidden layer it is not J^+ g (a
    test that would pass for a rule that computed the exact Gauss-Newton step is no test of
    K-FAC)."""
    _, jac, g, dense = network_problem(batch=40)
    update, _ = kfac_update(1e-10, jac, g)
    gauss_newton = -np.asarray(
        truncated_spectral_direction(dense, g.reshape(-1), 1.0, 1e-12, "svd")
    )
    assert np.linalg.norm(update - gauss_newton) > 1e-3 * np.linalg.norm(gauss_newton)
    # but it is a descent direction for the linearised loss: g^T J D < 0
    assert float(np.asarray(g).reshape(-1) @ (np.asarray(dense) @ update)) < 0


def test_large_damping_gives_a_scaled_gradient_step(x64):
    """gamma -> inf: (A + sqrt(gamma) m_A I)^-1 X (G + sqrt(gamma) m_G I)^-1 -> X / (gamma m_A m_G)
    per layer."""
    _, jac, g, dense = network_problem(seed=2)
    gamma = 1e16
    update, _ = kfac_update(gamma, jac, g)
    gradient = np.asarray(dense).T @ np.asarray(g).reshape(-1)
    expected = np.zeros_like(gradient)
    batch = jac.inputs[0].shape[0]
    starts = np.cumsum(
        [
            0,
            *[
                jac.inputs[leaf].shape[1] * jac.cotangents[leaf].shape[2]
                if k == "w"
                else jac.cotangents[leaf].shape[2]
                for leaf, k in jac.plan.leaves
            ],
        ]
    )
    for i, (layer, _) in enumerate(jac.plan.leaves):
        a = np.concatenate([np.asarray(jac.inputs[layer]), np.ones((batch, 1))], axis=1)
        delta = np.asarray(jac.cotangents[layer]).reshape(-1, jac.cotangents[layer].shape[2])
        mean_a = np.sum(a * a) / batch / a.shape[1]
        mean_g = np.sum(delta * delta) / batch / delta.shape[1]
        expected[starts[i] : starts[i + 1]] = -gradient[starts[i] : starts[i + 1]] / (
            batch * gamma * mean_a * mean_g
        )
    np.testing.assert_allclose(update, expected, rtol=1e-5)


def test_the_damping_is_free_of_the_problems_scale(x64):
    """Scaling the physics output by c scales the cotangents and g by c: the step is unchanged (g
    carries one c, G two, and the damping follows G's mean eigenvalue)."""
    _, jac, g, _ = network_problem(seed=4)
    scaled = LayerJacobian(jac.plan, jac.inputs, tuple(10.0 * d for d in jac.cotangents))
    np.testing.assert_allclose(
        kfac_update(1e-3, scaled, 10.0 * g)[0], kfac_update(1e-3, jac, g)[0], rtol=1e-9
    )


def test_a_dense_jacobian_is_refused():
    rule = kfac(1.0)
    flat = jnp.zeros(4)
    with pytest.raises(UserError, match="layer factors"):
        rule.update(flat, rule.init(flat), flat, jacobian=jnp.ones((3, 4)), output_grad=jnp.ones(3))


# a 100-iteration run: make test-long (make test checks the step against its closed form above, and
# runs K-FAC and its refusal through the runner in test_configs.py's pairs)
@pytest.mark.long
def test_kfac_trains_the_toy_and_is_refused_where_the_network_is_not_layer_factorised(tmp_path):
    run = physgrad.run(
        "task=toy",
        "task.scale=1",  # the book's well-conditioned case, with three 20-neuron layers
        "task.hidden=[20,20,20]",
        "optim=kfac",
        "trainer.iterations=100",
        "trainer.eval_every=50",
        "trainer.batch_size=64",
        out_dir=tmp_path / "toy",
    )
    assert run.attrs["status"] == "completed" and run.eval["loss"][-1] < 0.5 * run.eval["loss"][0]
    assert run.attrs["jacobian"] == "layer-factorised"
    with pytest.raises(UserError) as refused:
        physgrad.run(
            "task=multicart",
            "optim=kfac",
            "task.poles=2",
            "unroll=10",
            "trainer.iterations=2",
            out_dir=tmp_path / "multicart",
        )
    reason = str(refused.value)
    assert (
        "optim=kfac" in reason
        and "task=multicart" in reason
        and "layer factors" in reason
        and "\n" not in reason
    )
