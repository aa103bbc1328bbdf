"""Closed-loop heater control of the 2D heat equation: a network reads the temperature field every
step and sets the power of four heaters so that the plate ends at a target profile.

The plate is the unit square on an n x n grid with cold edges (T = 0 outside it). Explicit Euler:

    T_{k+1} = T_k + dt * (alpha * Laplace(T_k) + sum_j p_j(T_k) * B_j),

with the five-point Laplacian (spacing h = 1 / (n + 1)), stable for alpha * dt / h^2 <= 1/4 (checked
at build time), and B_j a Gaussian footprint of heater j at the plate's quarter points. The
controller sees the field averaged over 4 x 4 blocks and outputs each heater's power, bounded in
[0, max_power] by a sigmoid. Start: a smooth random field (a sum of three random Gaussian bumps).
The output y is the final field as 16 x 16 sensors read it (averaged over 2 x 2 blocks), the
per-sample loss its mean squared distance to the target read the same way: a raised plateau in the
middle of the plate. (The sensors keep the Jacobian rules' Jacobian at 256 rows a sample, not
1,024.)
"""

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics
from physgrad.validate import number


def build(key, *, grid, alpha, dt, unroll, max_power, hidden, train_size, test_size):
    """physgrad calls this with the keys of conf/task/heat.yaml and a PRNG key for the data."""
    dt = number("task.dt", dt, 0, open_low=True)
    h = 1.0 / (grid + 1)
    if alpha * dt / h**2 > 0.25:
        raise ValueError(
            f"task.dt={dt:g}: explicit Euler is unstable above alpha * dt / h^2 = 1/4; "
            f"use task.dt={0.25 * h**2 / alpha:.3g} or less"
        )
    if grid % 4:
        raise ValueError(
            f"task.grid={grid}: the controller averages 4 x 4 blocks; use a multiple of 4"
        )
    dtype = jnp.zeros(()).dtype
    x = (jnp.arange(grid, dtype=dtype) + 1) * h
    xx, yy = jnp.meshgrid(x, x, indexing="ij")
    corners = [(cx, cy) for cx in (0.3, 0.7) for cy in (0.3, 0.7)]
    heaters = jnp.stack([jnp.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 0.02) for cx, cy in corners])
    target = 0.5 * jnp.exp(-((((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.08) ** 2))

    def laplace(t):
        padded = jnp.pad(t, 1)  # the cold edges
        neighbours = padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]
        return (neighbours - 4 * t) / h**2

    def step(t, power):
        return t + dt * (alpha * laplace(t) + jnp.tensordot(power, heaters, 1))

    def blocks(t, size):
        return t.reshape(grid // size, size, grid // size, size).mean(axis=(1, 3))

    def observe(t):
        return blocks(t, 4).ravel()

    sensed_target = blocks(target, 2)

    def policy(params, sample):  # closed loop: the network reads the field at every step
        return lambda t, k: max_power * jax.nn.sigmoid(apply_mlp(params, observe(t), hidden="tanh"))

    def starts(k, count):
        kc, ka = jax.random.split(k)
        centres = jax.random.uniform(kc, (count, 3, 2), dtype, 0.2, 0.8)
        heights = jax.random.uniform(ka, (count, 3), dtype, 0.0, 0.6)
        bumps = jnp.exp(
            -((xx - centres[..., 0, None, None]) ** 2 + (yy - centres[..., 1, None, None]) ** 2)
            / 0.03
        )
        return {"field": jnp.einsum("sb,sbij->sij", heights, bumps)}

    train_key, test_key = jax.random.split(key)
    inputs = (grid // 4) ** 2
    return Scene(
        init_params=lambda k: init_mlp(k, [inputs, *hidden, len(heaters)], dtype),
        train_set=starts(train_key, train_size),
        test_set=starts(test_key, test_size),
        dynamics=Dynamics(
            step=step,
            policy=policy,
            initial=lambda sample: sample["field"],
            unroll=unroll,
            closed_loop=True,
            readout=lambda final, observed, sample: blocks(final, 2),
        ),
        sample_loss=lambda y, sample: jnp.mean((y - sensed_target) ** 2),
        sample_metrics=lambda params, sample, y: {
            "peak_error": jnp.max(jnp.abs(y - sensed_target))
        },
    )
