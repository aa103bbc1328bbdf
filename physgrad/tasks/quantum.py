"""Quantum dipole control (HIG and StableBPTT papers): steer a particle in a box with a field u(t) x.

i dpsi/dt = (-d^2/dx^2 + u(t) x) psi on (0, 2), psi = 0 at both walls (hbar = 1, m = 1/2), on the interior
points x_j = j dx, j = 1..N, dx = 2 / (N + 1). H = -D2 + u diag(x) with D2 the 3-point Laplacian / dx^2.
Crank-Nicolson, a tridiagonal solve per sample and step:
    (I + i dt/2 H) psi_{n+1} = (I - i dt/2 H) psi_n.
Discrete eigenstates phi_n(j) = sin(pi n j / (N + 1)) (normalised), energies (4/dx^2) sin^2(pi n / (2(N + 1))).

Two presets share this module (conf/task/quantum.yaml, conf/task/quantum_control.yaml):
- HIG: start in phi_1, reach a random real mix of phi_2 and phi_3; loss 1 - |<target|psi(T)>|^2; open loop.
- StableBPTT: start in a random complex mix of phi_1 and phi_2, reach phi_n; loss sum_t (1 - |<phi_n|psi_t>|^2);
  closed loop.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.lax.linalg import tridiagonal_solve

from physgrad.errors import UserError
from physgrad.nets import apply_control_cnn, apply_mlp, init_control_cnn, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics
from physgrad.validate import choice, flag, layer_widths, number


def grid(points: int, dtype=jnp.float32) -> jax.Array:
    """x_j = j * dx, j = 1..N, built from integers."""
    return jnp.arange(1, points + 1, dtype=dtype) * (2.0 / (points + 1))


def eigenstate(level: int, points: int, dtype=jnp.float32) -> jax.Array:
    j = jnp.arange(1, points + 1, dtype=dtype)
    phi = jnp.sin(jnp.pi * level * j / (points + 1))
    return phi / jnp.linalg.norm(phi)


def eigenenergy(level: int, points: int) -> float:
    dx = 2.0 / (points + 1)
    return 4.0 / dx ** 2 * float(jnp.sin(jnp.pi * level / (2 * (points + 1)))) ** 2


def apply_hamiltonian(psi, u, x):
    """H psi = -(psi_{j+1} - 2 psi_j + psi_{j-1}) / dx^2 + u x_j psi_j with psi = 0 beyond the walls."""
    dx = x[0]
    padded = jnp.pad(psi, 1)
    return -(padded[2:] - 2.0 * psi + padded[:-2]) / dx ** 2 + u * x * psi


def crank_nicolson_step(psi, u, x, dt):
    """Solve (I + i dt/2 H) psi_next = (I - i dt/2 H) psi with a tridiagonal solver (O(N) per sample)."""
    dx = x[0]
    half = 0.5j * dt
    rhs = psi - half * apply_hamiltonian(psi, u, x)
    diagonal = 1.0 + half * (2.0 / dx ** 2 + u * x)
    off = jnp.full_like(psi, -half / dx ** 2)
    lower, upper = off.at[0].set(0.0), off.at[-1].set(0.0)
    return tridiagonal_solve(lower, diagonal, upper, rhs[:, None])[:, 0]


def fidelity(target, psi):
    """|<target|psi>|^2."""
    return jnp.abs(jnp.vdot(target, psi)) ** 2


def realify(psi):
    return jnp.concatenate([psi.real, psi.imag])


def build(key, *, points, dt, unroll, start, target, target_level, loss, closed_loop, network, hidden,
          checkpoint, train_size, test_size) -> Scene:
    """The scene, either preset: every difference between them is one of these settings (docs/decisions.md)."""
    points = number("task.points", points, 3, integer=True)
    dt = number("task.dt", dt, 0, open_low=True)
    start = choice("task.start", start, ("ground", "mix12"))
    target_kind = choice("task.target", target, ("mix23", "level"))
    level = number("task.target_level", target_level, 1, integer=True)
    if target_kind == "level" and level > points:
        raise UserError(f"task.target_level={level} is not allowed: the grid has {points} levels (task.points)")
    every_step = choice("task.loss", loss, ("final", "every_step")) == "every_step"
    network = choice("task.network", network, ("dense", "cnn"))
    closed_loop = flag("task.closed_loop", closed_loop)
    if network == "cnn" and not closed_loop:
        raise UserError("task.network=cnn is the closed-loop controller: use task.closed_loop=true or "
                        "task.network=dense")
    train_size = number("task.train_size", train_size, 1, integer=True)
    test_size = number("task.test_size", test_size, 1, integer=True)

    real = jnp.zeros(()).dtype
    cplx = jnp.result_type(real, jnp.complex64)
    x = grid(points, real)
    phi = [eigenstate(n, points, real).astype(cplx) for n in range(1, max(3, level) + 1)]

    def make_samples(k, count):
        k_start, k_target, k_phase = jax.random.split(k, 3)
        if start == "ground":
            psi0 = jnp.broadcast_to(phi[0], (count, points))
        else:
            c = jax.random.normal(k_start, (count, 2), real)
            a = jax.random.uniform(k_phase, (count, 2), real, 0.0, 2.0 * jnp.pi)
            mix = c * jnp.exp(1j * a)
            psi0 = (mix[:, :1] * phi[0] + mix[:, 1:] * phi[1]) / jnp.linalg.norm(mix, axis=1, keepdims=True)
        if target_kind == "mix23":
            c = jax.random.normal(k_target, (count, 2), real)
            target = (c[:, :1] * phi[1] + c[:, 1:] * phi[2]) / jnp.linalg.norm(c, axis=1, keepdims=True)
        else:
            target = jnp.broadcast_to(phi[level - 1], (count, points))
        return {"psi0": psi0.astype(cplx), "target": target.astype(cplx)}

    hidden = layer_widths("task.hidden", hidden)
    checkpoint = flag("task.checkpoint", checkpoint)
    if closed_loop and network == "cnn":
        init = lambda k: init_control_cnn(k, points, real)  # noqa: E731

        def control(params, psi, target):
            return apply_control_cnn(params, jnp.stack([psi.real, psi.imag], axis=1))
    elif closed_loop:
        init = lambda k: init_mlp(k, [4 * points, *hidden, 1], real)  # noqa: E731

        def control(params, psi, target):
            return apply_mlp(params, jnp.concatenate([realify(psi), realify(target)]), hidden="tanh")[0]
    else:
        init = lambda k: init_mlp(k, [2 * points, *hidden, unroll], real)  # noqa: E731

    def step(psi, u):
        return crank_nicolson_step(psi, u, x, dt)

    def policy(params, sample):
        target = sample["target"]
        if closed_loop:
            return lambda psi, k: control(params, psi, target)
        controls = apply_mlp(params, realify(target), hidden="tanh")
        return lambda psi, k: controls[k]

    def readout(final, fidelities, sample):
        # y: the fidelity of every step (loss over all steps), or the final state as real numbers
        return fidelities if every_step else realify(final)

    def final_fidelity(y, sample):
        if every_step:
            return y[-1]
        return fidelity(sample["target"], y[:points] + 1j * y[points:])

    def sample_loss(y, sample):
        return jnp.sum(1.0 - y) if every_step else 1.0 - final_fidelity(y, sample)

    train_key, test_key = jax.random.split(key)

    return Scene(
        init_params=init,
        train_set=make_samples(train_key, train_size),
        test_set=make_samples(test_key, test_size),
        dynamics=Dynamics(step=step, policy=policy, initial=lambda sample: sample["psi0"], unroll=unroll,
                          closed_loop=closed_loop, readout=readout, checkpoint=checkpoint,
                          observe=(lambda psi, u, sample: fidelity(sample["target"], psi)) if every_step else None),
        sample_loss=sample_loss,
        sample_metrics=lambda params, sample, y: {"fidelity": final_fidelity(y, sample)},
    )
