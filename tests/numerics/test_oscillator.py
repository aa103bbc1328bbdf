"""Numerics layer of the oscillator: the harmonic chain, RK4's order and energy drift, the
zero-control loss, the unroll against loops and finite differences, the BPTT modes by hand on a
linear system, the combined gradient and the checkpointed rollout."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.gradients import combine_signs
from physgrad.nets import apply_mlp
from physgrad.tasks import build_scene
from physgrad.tasks.oscillator import energy, rk4_step
from physgrad.unroll import MODES, PHYSICS_ONLY, STOPPED, rollout
from tests.helpers import load
from tests.reference import check_gradient, forward_states, loop_states


def integrate(x0, dt, steps, alpha, controls=None):
    controls = jnp.zeros(steps) if controls is None else controls
    final, _ = rollout(
        lambda x, u: rk4_step(x, u, dt, alpha, 3.0), lambda x, k: controls[k], x0, steps
    )
    return final


def harmonic(x0, t):
    q, p = jnp.split(x0, 2)
    return jnp.concatenate([q * jnp.cos(t) + p * jnp.sin(t), -q * jnp.sin(t) + p * jnp.cos(t)])


def test_uncoupled_unforced_chain_is_harmonic(x64):
    x0 = jax.random.uniform(jax.random.PRNGKey(0), (6,))
    numeric = integrate(x0, 0.125, 96, 0.0)
    # RK4 on the linear system x' = A x is exactly x_{n+1} = R(dt A) x_n, R(z) = 1 + z + z^2/2 +
    # z^3/6 + z^4/24
    a = 0.125 * jnp.block([[jnp.zeros((3, 3)), jnp.eye(3)], [-jnp.eye(3), jnp.zeros((3, 3))]])
    r = jnp.eye(6) + a + a @ a / 2 + a @ a @ a / 6 + a @ a @ a @ a / 24
    np.testing.assert_allclose(numeric, jnp.linalg.matrix_power(r, 96) @ x0, rtol=0, atol=1e-13)
    # and close to the exact harmonic motion: RK4's phase error is dt^5/120 per step
    bound = 96 * 0.125**5 / 120 * float(jnp.max(jnp.abs(x0))) * 2
    assert float(jnp.max(jnp.abs(numeric - harmonic(x0, 12.0)))) < bound


def order(dts, errors):
    return np.polyfit(np.log(dts), np.log(errors), 1)[0]


def test_rk4_is_fourth_order(x64):
    x0 = jax.random.uniform(jax.random.PRNGKey(1), (4,))
    dts = np.array([0.2, 0.1, 0.05, 0.025])
    errors = [
        float(jnp.max(jnp.abs(integrate(x0, dt, round(4.0 / dt), 0.0) - harmonic(x0, 4.0))))
        for dt in dts
    ]
    assert 3.8 < order(dts, errors) < 4.2, errors
    # and on the coupled nonlinear chain, against a fine-step solution
    reference = integrate(x0, 0.2 / 64, 64 * 20, 1.0)
    errors = [
        float(jnp.max(jnp.abs(integrate(x0, dt, round(4.0 / dt), 1.0) - reference))) for dt in dts
    ]
    assert 3.7 < order(dts, errors) < 4.3, errors


def test_unforced_energy_drift_is_fourth_order(x64):
    x0 = jax.random.uniform(jax.random.PRNGKey(2), (4,))
    dts = np.array([0.25, 0.125, 0.0625])
    drifts = [
        abs(float(energy(integrate(x0, dt, round(12 / dt), 1.0), 1.0) - energy(x0, 1.0)))
        for dt in dts
    ]
    assert drifts[-1] < 1e-5
    assert 3.5 < order(dts, drifts) < 5.5, drifts


def test_zero_control_loss_is_about_0_80():
    cfg = load("task=oscillator")
    scene = build_scene(cfg.task, jax.random.PRNGKey(0))
    # u = 0 throughout
    zero = jax.tree_util.tree_map(jnp.zeros_like, scene.init_params(jax.random.PRNGKey(1)))
    loss = float(scene.evaluate(zero, scene.test_set)["loss"])
    assert abs(loss - 0.80) < 0.03, loss


def test_unroll_sets_the_time_steps_and_the_open_loop_output_size():
    cfg = load("task=oscillator", "task.train_size=8", "task.test_size=8")
    scene = build_scene(cfg.task, jax.random.PRNGKey(0), 10)
    params = scene.init_params(jax.random.PRNGKey(1))
    assert scene.unroll == 10 and params[-1]["w"].shape == (20, 10) and not scene.closed_loop
    closed = build_scene(
        load("task=oscillator", "task.closed_loop=true").task, jax.random.PRNGKey(0), 10
    )
    assert (
        closed.init_params(jax.random.PRNGKey(1))[-1]["w"].shape == (20, 1) and closed.closed_loop
    )


# the regular gradient of the closed loop in make test; the open loop and the stopped modes M and S
# in make test-long
@pytest.mark.parametrize(
    "mode",
    ["R", pytest.param("M", marks=pytest.mark.long), pytest.param("S", marks=pytest.mark.long)],
)
@pytest.mark.parametrize(
    "closed_loop",
    [pytest.param(False, marks=pytest.mark.long), True],
    ids=["open", "closed"],
)
def test_scan_matches_loop_and_finite_differences(x64, closed_loop, mode):
    steps = 12
    cfg = load(
        "task=oscillator",
        f"task.closed_loop={closed_loop}",
        "task.train_size=4",
        "task.test_size=4",
    )
    scene = build_scene(cfg.task, jax.random.PRNGKey(3), steps)
    params = scene.init_params(jax.random.PRNGKey(4))
    sample = {"x0": jax.random.uniform(jax.random.PRNGKey(5), (4,))}
    x0 = sample["x0"]

    # one compiled RK4 step and controller, called by the plain Python loop step after step (no
    # lax.scan): eagerly, each step's small operations were compiled one by one
    step = jax.jit(lambda x, u: rk4_step(x, u, 0.125, 1.0, 3.0))
    controller = jax.jit(lambda p, x: apply_mlp(p, jnp.concatenate([x, x0]), hidden="relu")[0])

    def policy_of(p):
        if closed_loop:
            return lambda x, k: controller(p, x)
        controls = apply_mlp(p, x0, hidden="relu")
        return lambda x, k: controls[k]

    frozen = forward_states(step, policy_of(params), x0, steps)

    def loop_loss(p):
        return scene.sample_loss(
            loop_states(step, policy_of(p), x0, steps, MODES[mode], frozen)[-1], sample
        )

    def scan_loss(p):
        return scene.sample_loss(scene.backprop_output(MODES[mode])(p, sample), sample)

    check_gradient(loop_loss, scan_loss, params)


def test_modes_on_a_linear_system_by_hand(x64):
    """x_{k+1} = a x_k + b c_k, c_k = theta x_k, L = x_N: the three gradients in closed form."""
    a, b, x0, n = 0.9, 0.5, 1.3, 6

    def final_state(theta, backprop):
        final, _ = rollout(
            lambda x, c: a * x + b * c, lambda x, k: theta * x, jnp.asarray(x0), n, backprop
        )
        return final

    theta = 0.4
    rate = a + b * theta
    states = x0 * rate ** np.arange(n)  # forward states x_0..x_{N-1}, the same in every mode
    expected = {
        "R": n * b * rate ** (n - 1) * x0,  # d/dtheta (a + b theta)^N x0
        "M": sum(
            a ** (n - 1 - k) * b * states[k] for k in range(n)
        ),  # controls move x only via physics
        "S": b * states[n - 1],  # only the last step's own effect
    }
    for mode, value in expected.items():
        np.testing.assert_allclose(jax.grad(final_state)(theta, MODES[mode]), value, rtol=1e-12)
    assert expected["R"] != expected["M"] != expected["S"]


def test_combined_gradient_takes_physics_gradient_where_signs_agree():
    g_m = {"w": jnp.array([1.0, -2.0, 3.0, 0.0, 0.0, -0.5]), "b": jnp.array([4.0])}
    g_r = {"w": jnp.array([5.0, 1.0, 0.1, 2.0, 0.0, -9.0]), "b": jnp.array([-1.0])}
    combined = combine_signs(g_m, g_r)
    np.testing.assert_array_equal(combined["w"], [1.0, 0.0, 3.0, 0.0, 0.0, -0.5])
    np.testing.assert_array_equal(combined["b"], [0.0])
    assert PHYSICS_ONLY == MODES["M"] and STOPPED == MODES["S"]


def test_checkpointed_rollout_gives_the_same_loss_and_gradient(x64):
    small = ["task=oscillator", "task.train_size=8", "task.test_size=8", "task.closed_loop=true"]
    plain = build_scene(load(*small).task, jax.random.PRNGKey(0), 32)
    remat = build_scene(load(*small, "task.checkpoint=true").task, jax.random.PRNGKey(0), 32)
    params = plain.init_params(jax.random.PRNGKey(1))

    def loss_and_grad(scene):
        return jax.value_and_grad(
            lambda p: scene.batch_loss(scene.batch_output(p, scene.test_set), scene.test_set)
        )(params)

    (loss, grads), (loss_remat, grads_remat) = loss_and_grad(plain), loss_and_grad(remat)
    np.testing.assert_allclose(loss_remat, loss, rtol=1e-13)
    for a, b in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(grads_remat)):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-14)
