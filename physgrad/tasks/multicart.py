"""Multi-pole cart-pole swing-up (StableBPTT paper): n poles on one cart, one shared force F.

theta = 0 is upright. With g = 9.8, pole mass m = 0.1, total mass M = 1.1 (not scaled with n), half
length l:
    A_i = (F + m l thetadot_i^2 sin theta_i) / M
    thetaddot_i = (g sin theta_i - cos theta_i A_i) / (l (4/3 - m cos^2 theta_i / M))
    xddot = (F + m l sum_i (thetadot_i^2 sin theta_i - thetaddot_i cos theta_i)) / M
Semi-implicit Euler: velocities first, then positions with the new velocities.
State: [x, theta_1..theta_n, xdot, thetadot_1..thetadot_n]. Loss: 1 - mean_i cos theta_i at the
final step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics
from physgrad.validate import flag, layer_widths, number

if TYPE_CHECKING:
    from physgrad.nets import Params

GRAVITY, POLE_MASS, TOTAL_MASS = 9.8, 0.1, 1.1


def accelerations(
    theta: jax.Array, theta_dot: jax.Array, force: jax.Array, half_length: float
) -> tuple[jax.Array, jax.Array]:
    """(xddot, thetaddot) of the equations above."""
    sin, cos = jnp.sin(theta), jnp.cos(theta)
    a = (force + POLE_MASS * half_length * theta_dot**2 * sin) / TOTAL_MASS
    theta_ddot = (GRAVITY * sin - cos * a) / (
        half_length * (4.0 / 3.0 - POLE_MASS * cos**2 / TOTAL_MASS)
    )
    x_ddot = (
        force + POLE_MASS * half_length * jnp.sum(theta_dot**2 * sin - theta_ddot * cos)
    ) / TOTAL_MASS
    return x_ddot, theta_ddot


def euler_step(state: jax.Array, force: jax.Array, dt: float, half_length: float) -> jax.Array:
    """Semi-implicit Euler: v_{k+1} = v_k + dt a(q_k, v_k), q_{k+1} = q_k + dt v_{k+1}."""
    half = state.shape[0] // 2
    positions, velocities = state[:half], state[half:]
    x_ddot, theta_ddot = accelerations(positions[1:], velocities[1:], force, half_length)
    velocities = velocities + dt * jnp.concatenate([x_ddot[None], theta_ddot])
    return jnp.concatenate([positions + dt * velocities, velocities])


def build(
    key: jax.Array,
    *,
    poles: int,
    dt: float,
    unroll: int,
    half_length: float,
    hidden: Sequence[int],
    checkpoint: bool,
    train_size: int,
    test_size: int,
) -> Scene:
    """The scene: a closed-loop controller state -> hidden tanh layers -> force, last layer
    zero-initialised."""
    poles = number("task.poles", poles, 1, integer=True)
    dt = number("task.dt", dt, 0, open_low=True)
    half_length = number("task.half_length", half_length, 0, open_low=True)
    train_size = number("task.train_size", train_size, 1, integer=True)
    test_size = number("task.test_size", test_size, 1, integer=True)
    dtype = jnp.zeros(()).dtype
    sizes = [2 * (1 + poles), *layer_widths("task.hidden", hidden), 1]
    checkpoint = flag("task.checkpoint", checkpoint)

    def make_states(k: jax.Array, count: int) -> dict[str, jax.Array]:
        """Hanging: theta_i = pi + U[-1, 1] pi/6; x, xdot and thetadot_i ~ U[-1, 1]."""
        k_theta, k_rest = jax.random.split(k)
        theta = jnp.pi + jax.random.uniform(k_theta, (count, poles), dtype, -1.0, 1.0) * jnp.pi / 6
        rest = jax.random.uniform(k_rest, (count, 2 + poles), dtype, -1.0, 1.0)
        return {"state": jnp.concatenate([rest[:, :1], theta, rest[:, 1:]], axis=1)}

    def step(state: jax.Array, force: jax.Array) -> jax.Array:
        return euler_step(state, force, dt, half_length)

    def policy(
        params: Params, sample: dict[str, jax.Array]
    ) -> Callable[[jax.Array, jax.Array], jax.Array]:
        return lambda state, k: apply_mlp(params, state, hidden="tanh")[0]

    def cos_poles(final: jax.Array, observed: None, sample: dict[str, jax.Array]) -> jax.Array:
        return jnp.cos(final[1 : 1 + poles])  # y: cos(theta_i) of every pole at the end

    train_key, test_key = jax.random.split(key)

    return Scene(
        init_params=lambda k: init_mlp(
            k, sizes, dtype, zero_last=True
        ),  # the initial force is exactly 0
        train_set=make_states(train_key, train_size),
        test_set=make_states(test_key, test_size),
        dynamics=Dynamics(
            step=step,
            policy=policy,
            initial=lambda sample: sample["state"],
            unroll=unroll,
            closed_loop=True,
            readout=cos_poles,
            checkpoint=checkpoint,
        ),
        sample_loss=lambda y, sample: 1.0 - jnp.mean(y),
        sample_metrics=lambda params, sample, y: {"upright": jnp.mean(y > 0.9)},
    )
