"""Multicart physics against an independent numpy evaluation and its equilibria; BPTT gradients
against plain loops and finite differences of correspondingly stopped functions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import apply_mlp
from physgrad.tasks import build_scene
from physgrad.tasks.multicart import euler_step
from physgrad.unroll import MODES, rollout
from tests.helpers import load
from tests.reference import check_gradient, forward_states, loop_states


def numpy_step(state, force, dt=0.01, g=9.8, m=0.1, big_m=1.1, half_length=0.5):
    """The paper's equations written out pole by pole in numpy, independently of physgrad."""
    n = (len(state) - 2) // 2
    x, theta, x_dot, theta_dot = state[0], state[1 : 1 + n], state[1 + n], state[2 + n :]
    theta_ddot = np.empty(n)
    coupling = 0.0
    for i in range(n):
        a_i = (force + m * half_length * theta_dot[i] ** 2 * np.sin(theta[i])) / big_m
        theta_ddot[i] = (g * np.sin(theta[i]) - np.cos(theta[i]) * a_i) / (
            half_length * (4.0 / 3.0 - m * np.cos(theta[i]) ** 2 / big_m)
        )
        coupling += theta_dot[i] ** 2 * np.sin(theta[i]) - theta_ddot[i] * np.cos(theta[i])
    x_ddot = (force + m * half_length * coupling) / big_m
    x_dot_new, theta_dot_new = x_dot + dt * x_ddot, theta_dot + dt * theta_ddot
    return np.concatenate(
        [[x + dt * x_dot_new], theta + dt * theta_dot_new, [x_dot_new], theta_dot_new]
    )


# make test-long: one and two poles; make test keeps four (every pole coupled through the cart)
@pytest.mark.parametrize(
    "poles", [pytest.param(1, marks=pytest.mark.long), pytest.param(2, marks=pytest.mark.long), 4]
)
def test_step_matches_independent_numpy(x64, poles):
    rng = np.random.default_rng(poles)
    for _ in range(5):
        state = rng.uniform(-3, 3, 2 * (1 + poles))
        force = rng.uniform(-5, 5)
        np.testing.assert_allclose(
            euler_step(jnp.asarray(state), force, 0.01, 0.5),
            numpy_step(state, force),
            rtol=1e-13,
            atol=1e-13,
        )


@pytest.mark.parametrize("theta", [np.pi, 0.0])
def test_unforced_hanging_and_upright_states_stay_put(x64, theta):
    poles = 3
    state = jnp.concatenate([jnp.array([0.7]), jnp.full(poles, theta), jnp.zeros(1 + poles)])
    final, _ = rollout(lambda s, f: euler_step(s, f, 0.01, 0.5), lambda s, k: 0.0, state, 100)
    np.testing.assert_allclose(final, state, atol=1e-12)


def test_reference_network_starts_with_zero_force():
    scene = build_scene(load("task=multicart", "task.poles=2").task, jax.random.PRNGKey(0))
    params = scene.init_params(jax.random.PRNGKey(1))
    assert (
        sum(leaf.size for leaf in jax.tree_util.tree_leaves(params))
        == 6 * 100 + 100 + 100 * 100 + 100 + 101
    )
    states = scene.test_set["state"]
    assert states.shape == (256, 6)
    theta = states[:, 1:3]
    assert (
        float(jnp.min(theta)) >= np.pi - np.pi / 6 - 1e-6
        and float(jnp.max(theta)) <= np.pi + np.pi / 6 + 1e-6
    )
    forces = jax.vmap(lambda s: apply_mlp(params, s, hidden="tanh")[0])(states)
    assert jnp.all(forces == 0.0)
    # hanging start: the loss of the untrained controller is close to its maximum of 2
    assert 1.7 < float(scene.evaluate(params, scene.test_set)["loss"]) <= 2.0


# the regular gradient in make test, the stopped modes M and S in make test-long
@pytest.mark.parametrize(
    "mode",
    ["R", pytest.param("M", marks=pytest.mark.long), pytest.param("S", marks=pytest.mark.long)],
)
def test_bptt_gradients_match_finite_differences_of_stopped_functions(x64, mode):
    steps, poles = 30, 2
    scene = build_scene(
        load("task=multicart", f"task.poles={poles}", "task.test_size=4").task,
        jax.random.PRNGKey(2),
        steps,
    )
    # a non-zero last layer, so that every parameter influences the force
    # (drawn by NumPy: JAX's sampler would compile once per leaf shape)
    params = jax.tree_util.tree_map(
        lambda a: a + 0.1 * np.random.default_rng(a.size).normal(size=a.shape),
        scene.init_params(jax.random.PRNGKey(3)),
    )
    sample = {"state": scene.test_set["state"][0]}

    # one compiled Euler step, called by the plain Python loop step after step (no lax.scan):
    # eagerly, each step's dozens of small operations were compiled one by one
    @jax.jit
    def step(s, f):
        return euler_step(s, f, 0.01, 0.5)

    controller = jax.jit(lambda p, s: apply_mlp(p, s, hidden="tanh")[0])

    def policy_of(p):
        return lambda s, k: controller(p, s)

    frozen = forward_states(step, policy_of(params), sample["state"], steps)

    def loop_loss(p):
        final = loop_states(step, policy_of(p), sample["state"], steps, MODES[mode], frozen)[-1]
        return 1.0 - jnp.mean(jnp.cos(final[1 : 1 + poles]))

    def scan_loss(p):
        return scene.sample_loss(scene.backprop_output(MODES[mode])(p, sample), sample)

    check_gradient(loop_loss, scan_loss, params)


# make test-long: the modes' gradients differ on the multicart; make test keeps the three modes'
# gradients in closed form, each different, in
# tests/numerics/test_oscillator.py::test_modes_on_a_linear_system_by_hand
@pytest.mark.long
def test_modes_give_different_gradients():
    scene = build_scene(
        load("task=multicart", "task.poles=2", "task.test_size=4").task, jax.random.PRNGKey(2)
    )
    params = jax.tree_util.tree_map(lambda a: a + 0.1, scene.init_params(jax.random.PRNGKey(3)))

    def grad(mode):
        output = scene.backprop_output(MODES[mode])
        return jax.flatten_util.ravel_pytree(
            jax.grad(
                lambda p: scene.batch_loss(
                    jax.vmap(output, (None, 0))(p, scene.test_set), scene.test_set
                )
            )(params)
        )[0]

    g = {mode: grad(mode) for mode in "RMS"}
    assert not jnp.allclose(g["R"], g["M"]) and not jnp.allclose(g["M"], g["S"])
