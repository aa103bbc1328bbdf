"""Guidance by repulsion (StableBPTT paper): drivers, steered by the network, herd evaders to the
origin.

Agents move in the plane; the state holds every agent's position and velocity, drivers first:
shape (drivers + evaders, 2, 2) = (agent, [position, velocity], [x, y]); all velocities start at 0.
With the softened distance d(r) = softening + |r|, v_k = x_driver,k - sum_j x_evader,j (a sum over
the evaders, not their centroid) and orth(v) = (-v_y, v_x), the network's gains c_k = (c_k0, c_k1)
give the accelerations
    driver k:  c_k0 v_k + c_k1 orth(v_k) - driver_friction v_driver,k + spreading sum_{i != k} (x_k
    - x_i) / d_ki^2 evader j:  repulsion sum_k (x_j - x_driver,k) / d_kj^2 - evader_friction
      v_evader,j
               + flocking sum_{i != j} p(d_ij) (x_i - x_j),   p(d) = (flock_distance / d - 1) / d
(the sums over i run over agents of the same kind). As written, p > 0 pulls evaders together closer
than flock_distance and pushes them apart beyond it. Explicit Euler: x' = x + dt v, v' = v + dt a(x,
v). Per-sample loss: the mean over steps 1..unroll, evaders and coordinates of x_evader^2, plus
control_cost times the mean of c^2 over steps, drivers and both gains.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from os import PathLike
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from physgrad.files import write_figure
from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics, rollout
from physgrad.validate import layer_widths, number

if TYPE_CHECKING:
    from jax.typing import DTypeLike
    from matplotlib.axes import Axes

    from physgrad.nets import Params


def safe_norm(r: jax.Array) -> jax.Array:
    """|r| over the last axis, with a zero gradient (not NaN) where r = 0: an agent's distance to
    itself."""
    squared = jnp.sum(r**2, axis=-1)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


def pairwise(
    x_to: jax.Array,
    x_from: jax.Array,
    softening: float,
    weight: Callable[[jax.Array], jax.Array],
) -> jax.Array:
    """sum_i weight(d_ai) (x_to,a - x_from,i) for every a: (A, 2) and (B, 2) -> (A, 2), d =
    softening + |r|. A pair at distance 0 (an agent and itself) contributes exactly 0."""
    r = x_to[:, None, :] - x_from[None, :, :]
    return jnp.sum(weight(softening + safe_norm(r))[..., None] * r, axis=1)


def accelerations(state: jax.Array, gains: jax.Array, drivers: int, physics: dict) -> jax.Array:
    """d(velocity)/dt of every agent, shape (agents, 2); gains: (drivers, 2)."""
    positions, velocities = state[:, 0], state[:, 1]
    x_drivers, x_evaders = positions[:drivers], positions[drivers:]
    eps = physics["softening"]
    towards = x_drivers - jnp.sum(x_evaders, axis=0)
    orthogonal = jnp.stack([-towards[:, 1], towards[:, 0]], axis=-1)
    control = gains[:, :1] * towards + gains[:, 1:] * orthogonal
    spread = pairwise(x_drivers, x_drivers, eps, lambda d: d**-2)
    driver = (
        control - physics["driver_friction"] * velocities[:drivers] + physics["spreading"] * spread
    )
    repel = pairwise(x_evaders, x_drivers, eps, lambda d: d**-2)
    distance = physics["flock_distance"]
    # (x_i - x_j) p(d_ij)
    flock = -pairwise(x_evaders, x_evaders, eps, lambda d: (distance / d - 1.0) / d)
    evader = (
        physics["repulsion"] * repel
        - physics["evader_friction"] * velocities[drivers:]
        + physics["flocking"] * flock
    )
    return jnp.concatenate([driver, evader])


def euler_step(
    state: jax.Array, gains: jax.Array, dt: float, drivers: int, physics: dict
) -> jax.Array:
    """Explicit Euler on positions and velocities, both from the current state."""
    positions, velocities = state[:, 0], state[:, 1]
    acceleration = accelerations(state, gains, drivers, physics)
    return jnp.stack([positions + dt * velocities, velocities + dt * acceleration], axis=1)


def initial_states(
    key: jax.Array, count: int, drivers: int, evaders: int, dtype: DTypeLike
) -> jax.Array:
    """Drivers on the annulus 3 <= r <= 4 (uniform radius and angle, each driver on its own);
    evaders around one shared centre on the annulus 1 <= r <= 2, each offset by U[-0.5, 0.5]^2;
    every velocity 0."""
    k_driver, k_centre, k_offset = jax.random.split(key, 3)

    def annulus(k: jax.Array, shape: tuple[int, ...], low: float, high: float) -> jax.Array:
        k_angle, k_radius = jax.random.split(k)
        angle = jax.random.uniform(k_angle, shape, dtype, 0.0, 2.0 * math.pi)
        radius = jax.random.uniform(k_radius, shape, dtype, low, high)
        return jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], axis=-1)

    x_drivers = annulus(k_driver, (count, drivers), 3.0, 4.0)
    centre = annulus(k_centre, (count, 1), 1.0, 2.0)
    x_evaders = centre + jax.random.uniform(k_offset, (count, evaders, 2), dtype, -0.5, 0.5)
    positions = jnp.concatenate([x_drivers, x_evaders], axis=1)
    return jnp.stack([positions, jnp.zeros_like(positions)], axis=2)


def initial_state(sample: dict[str, jax.Array]) -> jax.Array:
    """x_0 = the sample's state."""
    return sample["state"]


def init_network(
    key: jax.Array, *, agents: int, drivers: int, hidden: Sequence[int], dtype: DTypeLike
) -> Params:
    """An MLP from the flattened state (4 numbers per agent) to two gains per driver, its output
    layer zero (the gains start at exactly 0)."""
    return init_mlp(key, [4 * agents, *hidden, 2 * drivers], dtype, zero_last=True)


def gains(params: Params, state: jax.Array, k: jax.Array, *, drivers: int) -> jax.Array:
    """c = MLP(state flattened) with tanh hidden layers, shape (drivers, 2); the same at every step
    k."""
    return apply_mlp(params, state.reshape(-1), hidden="tanh").reshape(drivers, 2)


def controller(
    params: Params, sample: dict[str, jax.Array], *, drivers: int
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """The closed-loop controller of one sample: (state, k) -> gains."""
    return partial(gains, params, drivers=drivers)


def observe(
    state: jax.Array, gains: jax.Array, sample: dict[str, jax.Array], *, drivers: int
) -> jax.Array:
    """Per step: the mean of x_evader^2 (over evaders and coordinates) and of c^2 (over drivers,
    gains)."""
    return jnp.stack([jnp.mean(state[drivers:, 0] ** 2), jnp.mean(gains**2)])


def readout(final: jax.Array, observed: jax.Array, sample: dict[str, jax.Array]) -> jax.Array:
    """y = both per-step terms of the loss: (evader term at steps 1..unroll, control term at each
    step)."""
    return observed.T.reshape(-1)


@dataclass(frozen=True)
class Loss:
    """L = mean(evader term over steps) + control_cost mean(control term over steps), y as given by
    readout."""

    unroll: int
    control_cost: float

    def physics_loss(self, y: jax.Array) -> jax.Array:
        return jnp.mean(y[: self.unroll])

    def sample_loss(self, y: jax.Array, sample: dict[str, jax.Array]) -> jax.Array:
        return self.physics_loss(y) + self.control_cost * jnp.mean(y[self.unroll :])

    def sample_metrics(self, params: Params, sample: dict[str, jax.Array], y: jax.Array) -> dict:
        return {"physics_loss": self.physics_loss(y)}


def agent_paths(
    params: Params,
    states: jax.Array,
    *,
    step: Callable[[jax.Array, jax.Array], jax.Array],
    policy: Callable[[Params, dict[str, jax.Array]], Callable[[jax.Array, jax.Array], jax.Array]],
    unroll: int,
) -> np.ndarray:
    """Positions of every agent at steps 0..unroll under the network, shape (samples, unroll + 1,
    agents, 2)."""

    def positions(state: jax.Array) -> jax.Array:
        _, visited = rollout(
            step, policy(params, {"state": state}), state, unroll, observe=lambda x, c: x[:, 0]
        )
        return jnp.concatenate([state[None, :, 0], visited])  # (unroll + 1, agents, 2)

    return np.asarray(jax.jit(jax.vmap(positions))(states))


def plot_paths(ax: Axes, trajectory: np.ndarray, index: int, drivers: int) -> None:
    """One test state's paths: drivers red, evaders blue, start hollow, end filled, the origin a
    cross. The view holds the start and the evaders' paths; a driver that leaves it is drawn to its
    edge."""
    for agent in range(trajectory.shape[1]):
        colour = "tab:red" if agent < drivers else "tab:blue"
        ax.plot(trajectory[:, agent, 0], trajectory[:, agent, 1], color=colour, lw=1.2)
        ax.plot(*trajectory[0, agent], "o", color=colour, ms=4, mfc="white")
        ax.plot(*trajectory[-1, agent], "o", color=colour, ms=4)
    ax.plot(0, 0, "k+", ms=10)
    extent = 1.15 * max(np.abs(trajectory[0]).max(), np.abs(trajectory[:, drivers:]).max())
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    spread = float(np.mean(trajectory[-1, drivers:] ** 2))
    ax.set_title(f"test state {index}: final mean x_e^2 {spread:.3g}", fontsize=9)
    ax.grid(True, alpha=0.3)


def draw_paths(
    params: Params,
    test_set: dict[str, jax.Array],
    path: str | PathLike[str],
    count: int = 4,
    *,
    step: Callable[[jax.Array, jax.Array], jax.Array],
    policy: Callable[[Params, dict[str, jax.Array]], Callable[[jax.Array, jax.Array], jax.Array]],
    unroll: int,
    dt: float,
    drivers: int,
) -> None:
    """Agent paths of the trained network for the first ``count`` test states, side by side, saved
    to path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = min(count, test_set["state"].shape[0])
    paths = agent_paths(params, test_set["state"][:count], step=step, policy=policy, unroll=unroll)
    fig, axes = plt.subplots(1, count, figsize=(3.6 * count, 3.9), squeeze=False)
    for index, (ax, trajectory) in enumerate(zip(axes[0], paths)):
        plot_paths(ax, trajectory, index, drivers)
    handles = [
        plt.Line2D([], [], color="tab:red", label="drivers"),
        plt.Line2D([], [], color="tab:blue", label="evaders"),
        plt.Line2D([], [], ls="", marker="o", mfc="white", color="gray", label="start"),
        plt.Line2D([], [], ls="", marker="o", color="gray", label=f"end (t = {unroll * dt:.3g})"),
        plt.Line2D([], [], ls="", marker="+", color="k", label="target (origin)"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.suptitle("guidance: agent paths under the trained controller", fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 0.94))
    write_figure(fig, path, dpi=110)
    plt.close(fig)


def build(
    key: jax.Array,
    *,
    drivers: int,
    evaders: int,
    dt: float,
    unroll: int,
    control_cost: float,
    softening: float,
    repulsion: float,
    evader_friction: float,
    flocking: float,
    flock_distance: float,
    driver_friction: float,
    spreading: float,
    hidden: Sequence[int],
    train_size: int,
    test_size: int,
) -> Scene:
    """The scene: the network sees the whole state (agents x [position, velocity] x [x, y],
    flattened) and gives two gains per driver; y holds the per-step terms of the loss (see
    ``readout``)."""
    drivers = number("task.drivers", drivers, 1, integer=True)
    evaders = number("task.evaders", evaders, 1, integer=True)
    dt = number("task.dt", dt, 0, open_low=True)
    control_cost = number("task.control_cost", control_cost, 0)
    physics = {
        "softening": number("task.softening", softening, 0, open_low=True),
        "repulsion": number("task.repulsion", repulsion),
        "evader_friction": number("task.evader_friction", evader_friction),
        "flocking": number("task.flocking", flocking),
        "flock_distance": number("task.flock_distance", flock_distance),
        "driver_friction": number("task.driver_friction", driver_friction),
        "spreading": number("task.spreading", spreading),
    }
    hidden = layer_widths("task.hidden", hidden)
    train_size = number("task.train_size", train_size, 1, integer=True)
    test_size = number("task.test_size", test_size, 1, integer=True)
    dtype = jnp.zeros(()).dtype

    step = partial(euler_step, dt=dt, drivers=drivers, physics=physics)
    policy = partial(controller, drivers=drivers)
    loss = Loss(unroll, control_cost)
    train_key, test_key = jax.random.split(key)
    return Scene(
        init_params=partial(
            init_network, agents=drivers + evaders, drivers=drivers, hidden=hidden, dtype=dtype
        ),
        train_set={"state": initial_states(train_key, train_size, drivers, evaders, dtype)},
        test_set={"state": initial_states(test_key, test_size, drivers, evaders, dtype)},
        dynamics=Dynamics(
            step=step,
            policy=policy,
            initial=initial_state,
            unroll=unroll,
            closed_loop=True,
            readout=readout,
            observe=partial(observe, drivers=drivers),
        ),
        sample_loss=loss.sample_loss,
        sample_metrics=loss.sample_metrics,
        figure=partial(draw_paths, step=step, policy=policy, unroll=unroll, dt=dt, drivers=drivers),
    )
