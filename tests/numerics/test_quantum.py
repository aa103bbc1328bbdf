"""Quantum dipole scene: closed forms of the discrete Hamiltonian, unitarity of Crank-Nicolson,
parity, gradients through the tridiagonal solver against loops and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import apply_control_cnn, apply_mlp, count_params
from physgrad.tasks import build_scene
from physgrad.tasks.quantum import (
    apply_hamiltonian,
    crank_nicolson_step,
    eigenenergy,
    eigenstate,
    fidelity,
    grid,
    realify,
)
from physgrad.unroll import MODES, rollout
from tests.helpers import load
from tests.reference import check_gradient, forward_states, loop_states


# make test-long: the larger grid; make test keeps the scenes' 14 points
@pytest.mark.parametrize("points", [14, pytest.param(32, marks=pytest.mark.long)])
def test_eigenstates_and_energies_match_closed_forms(x64, points):
    x = grid(points, jnp.float64)
    assert x[0] == 2.0 / (points + 1) and abs(float(x[-1]) - 2.0 * points / (points + 1)) < 1e-15
    hamiltonian = jax.vmap(lambda e: apply_hamiltonian(e, 0.0, x))(jnp.eye(points)).T
    energies, vectors = np.linalg.eigh(np.asarray(hamiltonian))
    np.testing.assert_allclose(
        energies, [eigenenergy(n, points) for n in range(1, points + 1)], rtol=1e-12
    )
    for n in (1, 2, 3, 5):
        overlap = abs(float(vectors[:, n - 1] @ eigenstate(n, points, jnp.float64)))
        assert abs(overlap - 1.0) < 1e-12


def test_free_eigenstate_gains_only_the_crank_nicolson_phase(x64):
    points, dt, steps = 14, 0.05, 384
    x = grid(points, jnp.float64)
    for n in (1, 3):
        phi = eigenstate(n, points, jnp.float64).astype(jnp.complex128)
        final, _ = rollout(
            lambda psi, u: crank_nicolson_step(psi, u, x, dt), lambda psi, k: 0.0, phi, steps
        )
        energy = eigenenergy(n, points)
        factor = (1 - 0.5j * dt * energy) / (1 + 0.5j * dt * energy)
        np.testing.assert_allclose(final, factor**steps * phi, atol=1e-12)


# make test-long: the other precision of each grid; make test keeps both grids and both precisions,
# one pair each ([14-0.05-384-64-1e-12], [32-0.0625-128-32-2e-05])
@pytest.mark.parametrize(
    "points, dt, steps, precision, tolerance",
    [
        pytest.param(14, 0.05, 384, 32, 2e-5, marks=pytest.mark.long),
        (14, 0.05, 384, 64, 1e-12),
        (32, 0.0625, 128, 32, 2e-5),
        pytest.param(32, 0.0625, 128, 64, 1e-12, marks=pytest.mark.long),
    ],
)
def test_norm_stays_one_for_bounded_random_controls(points, dt, steps, precision, tolerance):
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", precision == 64)
    try:
        real = jnp.float64 if precision == 64 else jnp.float32
        x = grid(points, real)
        controls = jax.random.uniform(jax.random.PRNGKey(0), (steps,), real, -10.0, 10.0)
        psi0 = eigenstate(1, points, real).astype(jnp.result_type(real, jnp.complex64))
        _, norms = rollout(
            lambda psi, u: crank_nicolson_step(psi, u, x, dt),
            lambda psi, k: controls[k],
            psi0,
            steps,
            observe=lambda psi, u: jnp.linalg.norm(psi),
        )
        assert norms.dtype == real
        drift = float(jnp.max(jnp.abs(norms - 1.0)))
        assert drift < tolerance, drift
    finally:
        jax.config.update("jax_enable_x64", previous)


def test_parity_forbids_a_direct_step_from_phi1_to_phi3(x64):
    points, dt = 14, 0.05
    x = grid(points, jnp.float64)
    phi = [eigenstate(n, points, jnp.float64).astype(jnp.complex128) for n in (1, 2, 3)]

    def overlaps(field):
        psi = crank_nicolson_step(phi[0], field, x, dt)
        return abs(complex(jnp.vdot(phi[1], psi))), abs(complex(jnp.vdot(phi[2], psi)))

    (to2_big, to3_big), (to2_small, to3_small) = overlaps(1e-2), overlaps(1e-3)
    np.testing.assert_allclose(to2_big / to2_small, 10.0, rtol=1e-3)  # first order in the field
    # second order: zero at first order
    np.testing.assert_allclose(to3_big / to3_small, 100.0, rtol=1e-3)
    assert to3_small < 1e-3 * to2_small


def test_hig_preset_network_sizes_and_zero_control():
    scene = build_scene(load("task=quantum", "task.test_size=32").task, jax.random.PRNGKey(0))
    params = scene.init_params(jax.random.PRNGKey(1))
    assert count_params(params) == 9484 and scene.unroll == 384
    zero = jax.tree_util.tree_map(jnp.zeros_like, params)
    # u = 0: psi stays phi_1, orthogonal to every target
    metrics = scene.evaluate(zero, scene.test_set)
    np.testing.assert_allclose(metrics["loss"], 1.0, atol=1e-5)
    np.testing.assert_allclose(metrics["fidelity"], 0.0, atol=1e-5)


def test_control_preset_network_and_loss_over_every_step():
    scene = build_scene(
        load("task=quantum_control", "task.test_size=16").task, jax.random.PRNGKey(0)
    )
    params = scene.init_params(jax.random.PRNGKey(1))
    assert count_params(params) == 11701 and scene.closed_loop
    y = scene.batch_output(params, scene.test_set)
    assert y.shape == (16, 128)  # the fidelity of every step
    loss = scene.batch_loss(y, scene.test_set)
    assert 0.0 <= float(loss) <= 128.0
    norms = jnp.linalg.norm(scene.test_set["psi0"], axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-6)


@pytest.mark.parametrize("mode", ["R", "M", "S"])
@pytest.mark.parametrize("preset", ["quantum", "quantum_control"])
@pytest.mark.long
def test_gradients_through_the_solver(x64, preset, mode):
    steps = 10
    scene = build_scene(
        load(f"task={preset}", "task.train_size=4", "task.test_size=4").task,
        jax.random.PRNGKey(2),
        steps,
    )
    cfg = load(f"task={preset}").task
    params = scene.init_params(jax.random.PRNGKey(3))
    sample = jax.tree_util.tree_map(lambda a: a[1], scene.test_set)
    x = grid(cfg.points, jnp.float64)

    def step(psi, u):
        return crank_nicolson_step(psi, u, x, cfg.dt)

    def policy_of(p):
        if cfg.network == "cnn":
            return lambda psi, k: apply_control_cnn(p, jnp.stack([psi.real, psi.imag], axis=1))
        controls = apply_mlp(p, realify(sample["target"]), hidden="tanh")
        return lambda psi, k: controls[k]

    frozen = forward_states(step, policy_of(params), sample["psi0"], steps)

    def loop_loss(p):
        states = loop_states(step, policy_of(p), sample["psi0"], steps, MODES[mode], frozen)
        if cfg.loss == "every_step":
            return sum(1.0 - fidelity(sample["target"], psi) for psi in states)
        return 1.0 - fidelity(sample["target"], states[-1])

    def scan_loss(p):
        return scene.sample_loss(scene.backprop_output(MODES[mode])(p, sample), sample)

    grads = check_gradient(loop_loss, scan_loss, params)
    assert all(jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))
