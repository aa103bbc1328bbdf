"""Quantum dipole control (HIG and StableBPTT papers): steer a particle in a box with a field u(t)
x.

i dpsi/dt = (-d^2/dx^2 + u(t) x) psi on (0, 2), psi = 0 at both walls (hbar = 1, m = 1/2), on the
interior points x_j = j dx, j = 1..N, dx = 2 / (N + 1). H = -D2 + u diag(x) with D2 the 3-point
Laplacian / dx^2. Crank-Nicolson, a tridiagonal solve per sample and step:
    (I + i dt/2 H) psi_{n+1} = (I - i dt/2 H) psi_n.
Discrete eigenstates phi_n(j) = sin(pi n j / (N + 1)) (normalised), energies (4/dx^2) sin^2(pi n /
(2(N + 1))).

Two presets share this module (conf/task/quantum.yaml, conf/task/quantum_control.yaml):
- HIG: start in phi_1, reach a random real mix of phi_2 and phi_3; loss 1 - |<target|psi(T)>|^2;
  open loop.
- StableBPTT: start in a random complex mix of phi_1 and phi_2, reach phi_n; loss sum_t (1 -
  |<phi_n|psi_t>|^2); closed loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike

from physgrad.errors import UserError
from physgrad.nets import apply_control_cnn, apply_mlp, init_control_cnn, init_mlp
from physgrad.tasks import Scene
from physgrad.tridiagonal import Solve, library_solve, solve_for
from physgrad.unroll import Dynamics
from physgrad.validate import choice, flag, layer_widths, number

Params = Any  # a pytree of network parameters
# a closed-loop controller: (params, psi, target) -> u
Control = Callable[[Params, jax.Array, jax.Array], jax.Array]
# the controller of one sample: (psi_k, k) -> u_k
Policy = Callable[[jax.Array, jax.Array], jax.Array]


def grid(points: int, dtype: DTypeLike = jnp.float32) -> jax.Array:
    """x_j = j * dx, j = 1..N, built from integers."""
    return jnp.arange(1, points + 1, dtype=dtype) * (2.0 / (points + 1))


def eigenstate(level: int, points: int, dtype: DTypeLike = jnp.float32) -> jax.Array:
    j = jnp.arange(1, points + 1, dtype=dtype)
    phi = jnp.sin(jnp.pi * level * j / (points + 1))
    return phi / jnp.linalg.norm(phi)


def eigenenergy(level: int, points: int) -> float:
    dx = 2.0 / (points + 1)
    return 4.0 / dx**2 * float(jnp.sin(jnp.pi * level / (2 * (points + 1)))) ** 2


def apply_hamiltonian(psi: jax.Array, u: float | jax.Array, x: jax.Array) -> jax.Array:
    """H psi = -(psi_{j+1} - 2 psi_j + psi_{j-1}) / dx^2 + u x_j psi_j with psi = 0 beyond the
    walls."""
    dx = x[0]
    padded = jnp.pad(psi, 1)
    return -(padded[2:] - 2.0 * psi + padded[:-2]) / dx**2 + u * x * psi


def crank_nicolson_step(
    psi: jax.Array,
    u: float | jax.Array,
    x: jax.Array,
    dt: float,
    solve: Solve = library_solve,
) -> jax.Array:
    """Solve (I + i dt/2 H) psi_next = (I - i dt/2 H) psi, a tridiagonal system (O(N) per sample),
    by `solve` (physgrad.tridiagonal: the scene takes the device's fastest path)."""
    dx = x[0]
    half = 0.5j * dt
    rhs = psi - half * apply_hamiltonian(psi, u, x)
    diagonal = 1.0 + half * (2.0 / dx**2 + u * x)
    off = jnp.full_like(psi, -half / dx**2)
    return solve(off.at[0].set(0.0), diagonal, off.at[-1].set(0.0), rhs)


def fidelity(target: jax.Array, psi: jax.Array) -> jax.Array:
    """|<target|psi>|^2."""
    return jnp.abs(jnp.vdot(target, psi)) ** 2


def realify(psi: jax.Array) -> jax.Array:
    return jnp.concatenate([psi.real, psi.imag])


def eigenstates(points: int, levels: int, dtype: DTypeLike) -> list[jax.Array]:
    """phi_1..phi_levels as complex vectors (complex of the precision of ``dtype``)."""
    cplx = jnp.result_type(dtype, jnp.complex64)
    return [eigenstate(n, points, dtype).astype(cplx) for n in range(1, levels + 1)]


def start_states(
    k_start: jax.Array,
    k_phase: jax.Array,
    count: int,
    start: str,
    phi: list[jax.Array],
    dtype: DTypeLike,
) -> jax.Array:
    """psi_0: phi_1 ("ground"), or ("mix12") (m_1 phi_1 + m_2 phi_2) / |m| with m_i = c_i exp(i
    a_i), c_i ~ N(0, 1), a_i ~ U[0, 2 pi)."""
    if start == "ground":
        return jnp.broadcast_to(phi[0], (count, phi[0].shape[0]))
    c = jax.random.normal(k_start, (count, 2), dtype)
    a = jax.random.uniform(k_phase, (count, 2), dtype, 0.0, 2.0 * jnp.pi)
    mix = c * jnp.exp(1j * a)
    return (mix[:, :1] * phi[0] + mix[:, 1:] * phi[1]) / jnp.linalg.norm(mix, axis=1, keepdims=True)


def target_states(
    k_target: jax.Array, count: int, target: str, level: int, phi: list[jax.Array], dtype: DTypeLike
) -> jax.Array:
    """The target: ("mix23") (c_2 phi_2 + c_3 phi_3) / |c| with c_i ~ N(0, 1), real; or ("level")
    phi_level."""
    if target == "mix23":
        c = jax.random.normal(k_target, (count, 2), dtype)
        return (c[:, :1] * phi[1] + c[:, 1:] * phi[2]) / jnp.linalg.norm(c, axis=1, keepdims=True)
    return jnp.broadcast_to(phi[level - 1], (count, phi[0].shape[0]))


def make_samples(
    key: jax.Array,
    count: int,
    *,
    points: int,
    start: str,
    target: str,
    level: int,
    dtype: DTypeLike,
) -> dict:
    """``count`` samples {"psi0": start state, "target": target state}, both complex."""
    cplx = jnp.result_type(dtype, jnp.complex64)
    phi = eigenstates(points, max(3, level), dtype)
    k_start, k_target, k_phase = jax.random.split(key, 3)
    psi0 = start_states(k_start, k_phase, count, start, phi, dtype)
    targets = target_states(k_target, count, target, level, phi, dtype)
    return {"psi0": psi0.astype(cplx), "target": targets.astype(cplx)}


def initial_state(sample: dict) -> jax.Array:
    """x_0 = psi_0."""
    return sample["psi0"]


def init_network(
    key: jax.Array,
    *,
    points: int,
    network: str,
    closed_loop: bool,
    hidden: list[int],
    unroll: int,
    dtype: DTypeLike,
) -> Params:
    """closed loop: the control CNN on psi ("cnn") or an MLP from (psi, target) as real numbers to u
    ("dense"); open loop: an MLP from the target as real numbers to the controls of all unroll
    steps."""
    if closed_loop and network == "cnn":
        return init_control_cnn(key, points, dtype)
    if closed_loop:
        return init_mlp(key, [4 * points, *hidden, 1], dtype)
    return init_mlp(key, [2 * points, *hidden, unroll], dtype)


def cnn_control(params: Params, psi: jax.Array, target: jax.Array) -> jax.Array:
    """u = CNN(psi as an (N, 2) image of (Re, Im)); the target is not an input."""
    return apply_control_cnn(params, jnp.stack([psi.real, psi.imag], axis=1))


def dense_control(params: Params, psi: jax.Array, target: jax.Array) -> jax.Array:
    """u = MLP([Re psi, Im psi, Re target, Im target]) with tanh hidden layers."""
    return apply_mlp(params, jnp.concatenate([realify(psi), realify(target)]), hidden="tanh")[0]


def feedback(
    control: Control, params: Params, target: jax.Array, psi: jax.Array, k: jax.Array
) -> jax.Array:
    """u_k = control(params, psi_k, target)."""
    return control(params, psi, target)


def scheduled(controls: jax.Array, psi: jax.Array, k: jax.Array) -> jax.Array:
    """u_k = controls[k], whatever the state."""
    return controls[k]


def closed_loop_policy(params: Params, sample: dict, *, control: Control) -> Policy:
    """The controller of one sample: (psi, k) -> control(params, psi, target)."""
    return partial(feedback, control, params, sample["target"])


def open_loop_policy(params: Params, sample: dict) -> Policy:
    """The controller of one sample: all unroll controls u = MLP([Re target, Im target]) at once,
    indexed by k."""
    return partial(scheduled, apply_mlp(params, realify(sample["target"]), hidden="tanh"))


def policy_for(closed_loop: bool, network: str) -> Callable[..., Policy]:
    """(params, sample) -> the sample's controller: the network sees psi_t every step (closed loop)
    or gives every control at once from the target (open loop)."""
    if not closed_loop:
        return open_loop_policy
    return partial(closed_loop_policy, control=cnn_control if network == "cnn" else dense_control)


def step_fidelity(psi: jax.Array, u: jax.Array, sample: dict) -> jax.Array:
    """Observed per step: |<target|psi_{k+1}>|^2."""
    return fidelity(sample["target"], psi)


@dataclass(frozen=True)
class Objective:
    """every_step: y = the fidelity F_t of every step, L = sum_t (1 - F_t); otherwise y = psi(T) as
    real numbers [Re, Im] and L = 1 - |<target|psi(T)>|^2. The metric is the final fidelity either
    way."""

    every_step: bool
    points: int

    def readout(self, final: jax.Array, fidelities: jax.Array | None, sample: dict) -> jax.Array:
        return fidelities if self.every_step else realify(final)

    def final_fidelity(self, y: jax.Array, sample: dict) -> jax.Array:
        if self.every_step:
            return y[-1]
        return fidelity(sample["target"], y[: self.points] + 1j * y[self.points :])

    def sample_loss(self, y: jax.Array, sample: dict) -> jax.Array:
        return jnp.sum(1.0 - y) if self.every_step else 1.0 - self.final_fidelity(y, sample)

    def sample_metrics(self, params: Params, sample: dict, y: jax.Array) -> dict:
        return {"fidelity": self.final_fidelity(y, sample)}


def build(
    key: jax.Array,
    *,
    points: int,
    dt: float,
    unroll: int,
    start: str,
    target: str,
    target_level: int,
    loss: str,
    closed_loop: bool,
    network: str,
    hidden: list[int],
    checkpoint: bool,
    train_size: int,
    test_size: int,
) -> Scene:
    """The scene, either preset: every difference between them is one of these settings
    (docs/decisions.md)."""
    points = number("task.points", points, 3, integer=True)
    dt = number("task.dt", dt, 0, open_low=True)
    start = choice("task.start", start, ("ground", "mix12"))
    target = choice("task.target", target, ("mix23", "level"))
    level = number("task.target_level", target_level, 1, integer=True)
    if target == "level" and level > points:
        raise UserError(
            f"task.target_level={level} is not allowed: the grid has {points} levels (task.points)"
        )
    every_step = choice("task.loss", loss, ("final", "every_step")) == "every_step"
    network = choice("task.network", network, ("dense", "cnn"))
    closed_loop = flag("task.closed_loop", closed_loop)
    if network == "cnn" and not closed_loop:
        raise UserError(
            "task.network=cnn is the closed-loop controller: use task.closed_loop=true or "
            "task.network=dense"
        )
    train_size = number("task.train_size", train_size, 1, integer=True)
    test_size = number("task.test_size", test_size, 1, integer=True)
    hidden = layer_widths("task.hidden", hidden)
    checkpoint = flag("task.checkpoint", checkpoint)

    real = jnp.zeros(()).dtype
    samples = partial(
        make_samples, points=points, start=start, target=target, level=level, dtype=real
    )
    policy = policy_for(closed_loop, network)
    objective = Objective(every_step, points)
    train_key, test_key = jax.random.split(key)
    return Scene(
        init_params=partial(
            init_network,
            points=points,
            network=network,
            closed_loop=closed_loop,
            hidden=hidden,
            unroll=unroll,
            dtype=real,
        ),
        train_set=samples(train_key, train_size),
        test_set=samples(test_key, test_size),
        dynamics=Dynamics(
            step=partial(
                crank_nicolson_step,
                x=grid(points, real),
                dt=dt,
                solve=solve_for(jax.default_backend()),
            ),
            policy=policy,
            initial=initial_state,
            unroll=unroll,
            closed_loop=closed_loop,
            readout=objective.readout,
            checkpoint=checkpoint,
            observe=step_fidelity if every_step else None,
        ),
        sample_loss=objective.sample_loss,
        sample_metrics=objective.sample_metrics,
    )
