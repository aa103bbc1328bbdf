"""Guidance by repulsion against an independent numpy evaluation (agent by agent), hand-computed
forces of simple configurations, the zero-control loss, and BPTT gradients against plain loops and
finite differences of correspondingly stopped functions (float64)."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import apply_mlp
from physgrad.tasks import build_scene
from physgrad.tasks.guidance import euler_step
from physgrad.unroll import MODES
from tests.helpers import load
from tests.reference import check_gradient, forward_states

PHYSICS = {
    "softening": 0.1,
    "repulsion": 15.0,
    "evader_friction": 4.0,
    "flocking": 0.2,
    "flock_distance": 0.5,
    "driver_friction": 1.0,
    "spreading": 0.2,
}

DT = 1.0 / 15.0


def numpy_step(state, gains, drivers, dt=DT, p=PHYSICS):
    """The paper's equations written out agent by agent in numpy, independently of physgrad."""
    state = np.asarray(state, np.float64)
    x, v = state[:, 0], state[:, 1]
    agents = len(x)

    def distance(r):
        return p["softening"] + math.sqrt(r[0] ** 2 + r[1] ** 2)

    a = np.zeros((agents, 2))
    evader_sum = sum(x[j] for j in range(drivers, agents))
    for k in range(drivers):
        towards = x[k] - evader_sum
        a[k] += gains[k][0] * towards + gains[k][1] * np.array([-towards[1], towards[0]])
        a[k] -= p["driver_friction"] * v[k]
        for i in range(drivers):
            if i != k:
                r = x[k] - x[i]
                a[k] += p["spreading"] * r / distance(r) ** 2
    for j in range(drivers, agents):
        for k in range(drivers):
            r = x[j] - x[k]
            a[j] += p["repulsion"] * r / distance(r) ** 2
        a[j] -= p["evader_friction"] * v[j]
        for i in range(drivers, agents):
            if i != j:
                r = x[i] - x[j]
                d = distance(r)
                a[j] += p["flocking"] * (p["flock_distance"] / d - 1.0) / d * r
    return np.stack([x + dt * v, v + dt * a], axis=1)


@functools.cache
def compiled_step(drivers):
    """euler_step with the paper's physics, compiled as the scene's rollout compiles it (once per
    number of drivers and of agents): called eagerly, each of the step's dozens of small operations
    was compiled one by one, most of these tests' time. The same operations, compared at the same
    tolerances."""
    return jax.jit(lambda state, gains: euler_step(state, gains, DT, drivers, PHYSICS))


def test_step_matches_independent_numpy(x64):
    rng = np.random.default_rng(0)
    for drivers, evaders in ((2, 4), (1, 1), (3, 2)):
        for _ in range(4):
            state = rng.uniform(-3, 3, (drivers + evaders, 2, 2))
            gains = rng.uniform(-2, 2, (drivers, 2))
            np.testing.assert_allclose(
                compiled_step(drivers)(jnp.asarray(state), jnp.asarray(gains)),
                numpy_step(state, gains, drivers),
                rtol=1e-13,
                atol=1e-13,
            )


def at_rest(*positions):
    positions = np.asarray(positions, np.float64)
    return jnp.asarray(np.stack([positions, np.zeros_like(positions)], axis=1))


def test_agents_at_rest_move_as_the_forces_say(x64):
    """Zero control, everything at rest: positions stay for one step and velocities become dt times
    the forces, computed by hand for configurations with simple numbers."""
    # one driver at the origin, one evader at (1, 0): repelled along +x with 15 / d^2, d = 0.1 + 1
    moved = compiled_step(1)(at_rest([0.0, 0.0], [1.0, 0.0]), jnp.zeros((1, 2)))
    np.testing.assert_allclose(moved[:, 0], [[0.0, 0.0], [1.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(
        moved[:, 1], DT * np.array([[0.0, 0.0], [15.0 / 1.1**2, 0.0]]), rtol=1e-14
    )
    # two drivers at (+-1, 0) spread apart with 0.2 * 2 / 2.1^2; the evader at (0, 10) between them
    # feels the repulsion of both, whose x parts cancel
    moved = compiled_step(2)(at_rest([1.0, 0.0], [-1.0, 0.0], [0.0, 10.0]), jnp.zeros((2, 2)))
    d = 0.1 + math.sqrt(101.0)
    np.testing.assert_allclose(
        moved[:2, 1], DT * np.array([[0.4 / 2.1**2, 0.0], [-0.4 / 2.1**2, 0.0]]), rtol=1e-14
    )
    np.testing.assert_allclose(
        moved[2, 1], DT * np.array([0.0, 15.0 * 2 * 10.0 / d**2]), rtol=1e-14, atol=1e-15
    )
    # two evaders far from the driver: at d = flock_distance (|r| = 0.4) flocking vanishes; closer
    # they attract (p > 0 below flock_distance, as the equations are written), farther they repel
    far = [1e6, 0.0]
    for gap, sign in ((0.4, 0.0), (0.15, 1.0), (1.0, -1.0)):
        moved = compiled_step(1)(at_rest(far, [0.0, 0.0], [gap, 0.0]), jnp.zeros((1, 2)))
        d = 0.1 + gap
        flock = 0.2 * (0.5 / d - 1.0) / d * gap  # on the first evader, towards the second (+x)
        repelled = 15.0 / (1e6 + 0.1) ** 2 * 1e6
        np.testing.assert_allclose(
            moved[1, 1, 0], DT * (flock - repelled * (1e6 / 1e6)), rtol=1e-10, atol=1e-18
        )
        assert np.sign(flock) == sign


def test_reference_network_data_and_zero_control_loss(x64):
    """The network starts with zero gains (zero output layer), so the first loss is the physics
    alone: the evaders' mean squared distance over 60 steps, checked against the numpy
    evaluation."""
    scene = build_scene(load("task=guidance", "task.test_size=8").task, jax.random.PRNGKey(0))
    params = scene.init_params(jax.random.PRNGKey(1))
    assert sum(leaf.size for leaf in jax.tree_util.tree_leaves(params)) == 13_004
    states = np.asarray(scene.test_set["state"])
    assert states.shape == (8, 6, 2, 2) and np.all(states[:, :, 1] == 0)
    radius = np.linalg.norm(states[:, :2, 0], axis=-1)
    assert np.all((radius >= 3) & (radius <= 4))
    offsets = states[:, 2:, 0] - states[:, 2:, 0].mean(axis=1, keepdims=True)
    assert np.all(np.abs(offsets) <= 1.0)  # U[-0.5, 0.5] offsets around one shared centre
    evaluation = scene.evaluate(params, scene.test_set)
    expected = []
    for state in states:
        squared = []
        for _ in range(60):
            state = numpy_step(state, np.zeros((2, 2)), 2)
            squared.append(np.mean(state[2:, 0] ** 2))
        expected.append(np.mean(squared))
    np.testing.assert_allclose(evaluation["loss"], np.mean(expected), rtol=1e-12)
    np.testing.assert_allclose(evaluation["physics_loss"], evaluation["loss"], rtol=0)


@pytest.mark.parametrize("mode", ["R", "M", "S"])
@pytest.mark.long
def test_scan_matches_loop_and_finite_differences(x64, mode):
    """Loss over every step plus the control cost, with a random (non-zero) output layer so that the
    modes differ; the stopped inputs are the forward states of the regular rollout."""
    unroll, cost = 8, 0.1
    scene = build_scene(
        load(
            "task=guidance",
            f"task.control_cost={cost}",
            "task.train_size=4",
            "task.test_size=4",
            "task.hidden=[16,16]",
        ).task,
        jax.random.PRNGKey(3),
        unroll,
    )
    params = scene.init_params(jax.random.PRNGKey(4))
    params[-1] = {
        **params[-1],
        "w": 0.1 * jax.random.normal(jax.random.PRNGKey(5), params[-1]["w"].shape),
    }
    sample = jax.tree_util.tree_map(lambda leaf: leaf[0], scene.test_set)
    x0 = sample["state"]

    def step(x, c):
        return euler_step(x, c, DT, 2, PHYSICS)

    def policy_of(p):
        return lambda x, k: apply_mlp(p, x.reshape(-1), hidden="tanh").reshape(2, 2)

    frozen = forward_states(step, policy_of(params), x0, unroll)
    backprop = MODES[mode]

    def loop_loss(p):
        x, evader_terms, control_terms = x0, [], []
        for k in range(unroll):
            c = policy_of(p)(frozen[k] if backprop.stop_policy_input else x, k)
            x = step(frozen[k] if backprop.stop_physics_input else x, c)
            evader_terms.append(jnp.mean(x[2:, 0] ** 2))
            control_terms.append(jnp.mean(c**2))
        return jnp.mean(jnp.stack(evader_terms)) + cost * jnp.mean(jnp.stack(control_terms))

    def scan_loss(p):
        return scene.sample_loss(scene.backprop_output(backprop)(p, sample), sample)

    check_gradient(loop_loss, scan_loss, params)


def test_agents_on_top_of_each_other_give_finite_gradients(x64):
    """|r| is not differentiable at r = 0: the softened distance keeps an agent's distance to itself
    (and to an agent at the same spot) out of the gradient's way."""
    state = at_rest([3.0, 0.0], [3.0, 0.0], [0.5, 0.5], [0.5, 0.5])

    def loss(gains):
        return jnp.sum(
            euler_step(euler_step(state, gains, DT, 2, PHYSICS), gains, DT, 2, PHYSICS) ** 2
        )

    # compiled, as a training step is: eagerly, every operation of the two steps and of their
    # gradient was compiled one by one; the gradient is the same
    gradient = jax.jit(jax.grad(loss))(jnp.ones((2, 2)))
    assert np.isfinite(np.asarray(gradient)).all() and np.abs(np.asarray(gradient)).max() > 0
