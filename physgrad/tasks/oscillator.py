"""Coupled nonlinear oscillators (HIG paper): bring a chain of oscillators back to where it started.

State x = [q_1..q_n, p_1..p_n];  dq_i/dt = p_i,
    dp_i/dt = -q_i + alpha [(q_{i+1} - q_i)^3 + (q_{i-1} - q_i)^3] + gain * u(t) * [i == n]
(free ends: a missing neighbour contributes 0), the Hamiltonian system of
    H = sum_i (q_i^2 + p_i^2) / 2 + alpha sum_i (q_i - q_{i+1})^4 / 4
plus the control on the last oscillator. Classic RK4 with u held over each step.
Per-sample loss: sum_j (x_j(T) - x0_j)^2, with x0 ~ U[0,1)^(2n) the start and the target.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics
from physgrad.validate import array_size, flag, layer_widths, number

if TYPE_CHECKING:
    from physgrad.nets import Params


def vector_field(x: jax.Array, u: jax.Array, alpha: float, gain: float) -> jax.Array:
    """dx/dt for one state x = [q, p] and a scalar control u."""
    q, p = jnp.split(x, 2)
    zero = jnp.zeros_like(q[:1])
    to_right = jnp.concatenate([q[1:] - q[:-1], zero])  # q_{i+1} - q_i
    to_left = jnp.concatenate([zero, q[:-1] - q[1:]])  # q_{i-1} - q_i
    drive = jnp.zeros_like(q).at[-1].set(gain * u)
    return jnp.concatenate([p, -q + alpha * (to_right**3 + to_left**3) + drive])


def energy(x: jax.Array, alpha: float) -> jax.Array:
    """H(q, p) without the control term."""
    q, p = jnp.split(x, 2)
    return 0.5 * jnp.sum(q**2 + p**2) + 0.25 * alpha * jnp.sum((q[:-1] - q[1:]) ** 4)


def rk4_step(x: jax.Array, u: jax.Array, dt: float, alpha: float, gain: float) -> jax.Array:
    """One classic Runge-Kutta step of size dt with u constant over the step."""
    k1 = vector_field(x, u, alpha, gain)
    k2 = vector_field(x + 0.5 * dt * k1, u, alpha, gain)
    k3 = vector_field(x + 0.5 * dt * k2, u, alpha, gain)
    k4 = vector_field(x + dt * k3, u, alpha, gain)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def build(
    key: jax.Array,
    *,
    oscillators: int,
    alpha: float,
    gain: float,
    dt: float,
    unroll: int,
    closed_loop: bool,
    hidden: Sequence[int],
    checkpoint: bool,
    train_size: int,
    test_size: int,
) -> Scene:
    """The scene; closed_loop: the network sees (state, target) and gives this step's control, else
    (open loop, the paper's) it maps the target to every control at once."""
    n = number("task.oscillators", oscillators, 1, integer=True)
    dt = number("task.dt", dt, 0, open_low=True)
    alpha, gain = number("task.alpha", alpha), number("task.gain", gain)
    train_size = number("task.train_size", train_size, 1, integer=True)
    test_size = number("task.test_size", test_size, 1, integer=True)
    closed_loop = flag("task.closed_loop", closed_loop)
    hidden = layer_widths("task.hidden", hidden)
    checkpoint = flag("task.checkpoint", checkpoint)
    dtype = jnp.zeros(()).dtype
    sizes = [4 * n, *hidden, 1] if closed_loop else [2 * n, *hidden, unroll]
    array_size("the training set", (train_size, 2 * n), "task.oscillators or task.train_size")
    array_size("the test set", (test_size, 2 * n), "task.oscillators or task.test_size")
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        array_size("a layer of the network", (fan_in, fan_out), "task.oscillators or task.hidden")

    def step(x: jax.Array, u: jax.Array) -> jax.Array:
        return rk4_step(x, u, dt, alpha, gain)

    def policy(
        params: Params, sample: dict[str, jax.Array]
    ) -> Callable[[jax.Array, jax.Array], jax.Array]:
        target = sample["x0"]
        if closed_loop:
            return lambda x, k: apply_mlp(params, jnp.concatenate([x, target]), hidden="relu")[0]
        controls = apply_mlp(params, target, hidden="relu")
        return lambda x, k: controls[k]

    train_key, test_key = jax.random.split(key)
    train_x0 = jax.random.uniform(train_key, (train_size, 2 * n), dtype)
    test_x0 = jax.random.uniform(test_key, (test_size, 2 * n), dtype)

    return Scene(
        init_params=lambda k: init_mlp(k, sizes, dtype),
        train_set={"x0": train_x0},
        test_set={"x0": test_x0},
        dynamics=Dynamics(
            step=step,
            policy=policy,
            initial=lambda sample: sample["x0"],
            unroll=unroll,
            closed_loop=closed_loop,
            checkpoint=checkpoint,
        ),
        sample_loss=lambda y, sample: jnp.sum((y - sample["x0"]) ** 2),
    )
