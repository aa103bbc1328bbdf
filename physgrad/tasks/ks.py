"""Kuramoto-Sivashinsky neural simulator (the unrolling study, List, Chen, Bali, Thuerey, CMAME
2025): a network learns a time stepper from trajectories and is trained over m unrolled steps.

    u_t + u u_x + u_xx + u_xxxx = 0,  periodic, `points` grid points, length L = 2 pi * base_domain
    * size.

In Fourier space u_t = lin u + N(u) with lin(kappa) = kappa^2 - kappa^4, N(u) = -(i kappa / 2)
FFT(u^2) and kappa = 2 pi n / L. Exponential time differencing with step h, x = lin h, phi1 = (e^x -
1)/x, phi2 = (e^x - 1 - x)/x^2 (phi1(0) = 1, phi2(0) = 1/2):
    ETD1:    u' = e^x u + h phi1 N(u)
    ETD2RK:  a = ETD1(u),  u' = a + h phi2 (N(a) - N(u))       (Cox and Matthews' second-order
    scheme)
One model step is `substeps` solver steps (2 x 0.5 in the study). Ground truth: ETD2RK, generated in
float64; the coarse solver P of the correction stepper: ETD1 with the same h.

Steppers (task.stepper): predict s' = f(s) (the network alone); correct s' = P(s) + dt f(s) (dt = h,
as the study scales the correction). The network sees the state and a constant channel holding the
size factor.

Training modalities (task.training): WIG unrolls m steps with gradients through time; NOG unrolls m
steps with the state detached before every step (no gradient through time); ONE trains on one-step
pairs: each sample is m independent ground-truth pairs, so a batch of B holds B*m pairs and costs
what B unrolled windows cost, with the same number of updates (the study's compute matching: batch
and epochs times m). Loss: the mean squared error over the m predicted states and the grid. Held-out
loss: the study's relative error over `horizon` steps of an autoregressive rollout from each test
state, mean_k mean_x (u_k - u*_k)^2 / max_{k,x} u*_k^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from physgrad.errors import UserError
from physgrad.files import write_figure
from physgrad.nets import apply_resnet, init_resnet
from physgrad.tasks import Scene
from physgrad.tasks.ks_solver import (
    dataset,
    domain_length,
    draw_windows,
    held_out_set,
    solver_step,
    training_set,
)
from physgrad.unroll import Dynamics
from physgrad.validate import choice, flag, number

Params = Any  # a pytree of network parameters
State = tuple[jax.Array, jax.Array]  # the rollout state (u, size)

STEPPERS = ("predict", "correct")
TRAININGS = ("WIG", "NOG", "ONE")
# rollouts that leave [-DIVERGED_FACTOR, DIVERGED_FACTOR] x the ground truth's largest |u| count as
# unstable
DIVERGED_FACTOR = 3.0
# the study's clamp of a relative error per step (a rollout that blows up counts this much per step)
ERROR_CAP = 30.0
# the long rollout's accuracy horizon: steps before the correlation with the ground truth first
# drops below this
DECORRELATION = 0.5


# --------------------------------------------------------------------------------------------------
# model


@dataclass(frozen=True)
class Stepper:
    """The learned stepper: s' = f(s) (kind "predict") or P(s) + h f(s) (kind "correct"), f the
    ResNet of physgrad.nets and P `substeps` ETD1 steps of size h on the domain 2 pi * base_domain *
    size."""

    kind: str
    base_domain: float
    h: float
    substeps: int

    def coarse(self, u: jax.Array, size: float | jax.Array) -> jax.Array:
        """P: the first-order solver over one model step."""
        return solver_step(u, domain_length(self.base_domain, size), self.h, self.substeps, 1)

    def stepped(self, u: jax.Array, size: float | jax.Array, correction: jax.Array) -> jax.Array:
        """The next state from the network's output f(s)."""
        return correction if self.kind == "predict" else self.coarse(u, size) + self.h * correction

    def advance(self, params: Params, u: jax.Array, size: float | jax.Array) -> jax.Array:
        return self.stepped(u, size, apply_resnet(params, u, size))

    def autoregressive(
        self, params: Params, u: jax.Array, size: float | jax.Array, steps: int
    ) -> jax.Array:
        """The learned stepper's states 1..steps from u: (steps, points)."""
        return jax.lax.scan(
            lambda v, _: (self.advance(params, v, size),) * 2, u, None, length=steps
        )[1]


def detach(state: State, training: str) -> State:
    """NOG: the state detached before every step, wherever it goes; WIG: the state itself."""
    return jax.lax.stop_gradient(state) if training == "NOG" else state


def rollout_step(stepper: Stepper, training: str, state: State, output: jax.Array) -> State:
    """x_{k+1}: for ONE the policy's output itself; else the stepper's step from the (for NOG
    detached) state."""
    if training == "ONE":
        return output, state[1]
    u, size = detach(state, training)
    return stepper.stepped(u, size, output), size


def rollout_policy(
    stepper: Stepper, training: str, params: Params, sample: dict
) -> Callable[[State, jax.Array], jax.Array]:
    """ONE: the learned stepper from the sample's k-th ground-truth state; else the network on the
    state."""
    if training == "ONE":
        return lambda state, k: stepper.advance(params, sample["inputs"][k], sample["sizes"][k])
    return lambda state, k: apply_resnet(params, *detach(state, training))


def dynamics(stepper: Stepper, training: str, unroll: int) -> Dynamics:
    """The rollout of m steps of the training modality; y = the m predicted states. The rollout
    state is (u, size); the network is the policy and the solver the physics, so that the modes M
    and S of physgrad.unroll stop what they stop in the control scenes."""
    return Dynamics(
        step=partial(rollout_step, stepper, training),
        policy=partial(rollout_policy, stepper, training),
        initial=lambda sample: (sample["state"], sample["size"]),
        unroll=unroll,
        closed_loop=True,
        readout=lambda final, observed, sample: observed.reshape(-1),
        observe=lambda state, control, sample: state[0],
    )


def sample_loss(y: jax.Array, sample: dict) -> jax.Array:
    """Training samples: the MSE over the predicted steps and the grid. Test samples: the study's
    relative error, mean_k min(mean_x (u_k - u*_k)^2 / scale, ERROR_CAP) with scale = max u*^2 over
    frames 0..horizon (a non-finite step counts ERROR_CAP, so that a model blowing up has a finite,
    comparable error)."""
    target = sample["target"]
    predicted = y.reshape(-1, target.shape[-1])
    squared = (predicted - target[: predicted.shape[0]]) ** 2
    if "scale" not in sample:
        return jnp.mean(squared)
    per_step = jnp.mean(squared, axis=1) / sample["scale"]
    return jnp.mean(jnp.where(jnp.isfinite(per_step), jnp.minimum(per_step, ERROR_CAP), ERROR_CAP))


def held_out_output(stepper: Stepper, horizon: int, params: Params, sample: dict) -> jax.Array:
    """The held-out loss's output: `horizon` steps of the learned stepper, whatever the training
    unroll."""
    return stepper.autoregressive(params, sample["state"], sample["size"], horizon).reshape(-1)


def stability_metrics(
    stepper: Stepper,
    long_horizon: int,
    dtype: DTypeLike,
    params: Params,
    sample: dict,
    y: jax.Array,
) -> dict:
    """unstable_fraction: the long rollout leaves DIVERGED_FACTOR x the ground truth's largest |u|
    or is not finite; decorrelation_steps: steps before its correlation with the ground truth first
    drops below DECORRELATION (long_horizon if never)."""
    states = stepper.autoregressive(params, sample["state"], sample["size"], long_horizon)
    truth = sample["target"][:long_horizon]
    finite = jnp.isfinite(states)
    states = jnp.where(finite, states, 0.0)
    unstable = ~jnp.all(finite) | (
        jnp.max(jnp.abs(states)) > DIVERGED_FACTOR * jnp.max(jnp.abs(truth))
    )
    below = jax.vmap(pearson)(states, truth) < DECORRELATION
    steps = jnp.where(jnp.any(below), jnp.argmax(below), long_horizon)
    return {"unstable_fraction": unstable.astype(dtype), "decorrelation_steps": steps.astype(dtype)}


# --------------------------------------------------------------------------------------------------
# scene


def sizes(name: str, value: Any) -> list[float]:
    """A non-empty list of positive size factors."""
    listed = list(value) if isinstance(value, (list, tuple)) else None
    if not listed:
        raise UserError(
            f"{name}={value!r} is not allowed: use a list of positive size factors, e.g. [0.9, 1.0]"
        )
    return [number(f"{name}[{i}]", v, 0, open_low=True) for i, v in enumerate(listed)]


def pearson(a: jax.Array, b: jax.Array) -> jax.Array:
    """The correlation of two fields over the grid (0 where either is constant)."""
    a, b = a - jnp.mean(a), b - jnp.mean(b)
    norms = jnp.sqrt(jnp.sum(a * a) * jnp.sum(b * b))
    return jnp.where(norms > 0, jnp.sum(a * b) / jnp.where(norms > 0, norms, 1.0), 0.0)


def data_settings(
    unroll: int,
    points: int,
    base_domain: float,
    train_sizes: list[float],
    test_sizes: list[float],
    dt: float,
    substeps: int,
    warmup: int,
    train_steps: int,
    test_count: int,
    test_steps: int,
) -> dict:
    """The checked settings the data depend on (the key of dataset's cache)."""
    points = number("task.points", points, 4, integer=True)
    if points % 2:
        raise UserError(f"task.points={points} is not allowed: use an even number of grid points")
    return {
        "points": points,
        "base_domain": number("task.base_domain", base_domain, 0, open_low=True),
        "train_sizes": sizes("task.train_sizes", train_sizes),
        "test_sizes": sizes("task.test_sizes", test_sizes),
        "dt": number("task.dt", dt, 0, open_low=True),
        "substeps": number("task.substeps", substeps, 1, integer=True),
        "warmup": number("task.warmup", warmup, 0, integer=True),
        "train_steps": number("task.train_steps", train_steps, unroll + 1, integer=True),
        "test_count": number("task.test_count", test_count, 1, integer=True),
        "test_steps": number("task.test_steps", test_steps, 1, integer=True),
    }


def build(
    key: jax.Array,
    *,
    stepper: str,
    training: str,
    unroll: int,
    points: int,
    base_domain: float,
    train_sizes: list[float],
    test_sizes: list[float],
    dt: float,
    substeps: int,
    warmup: int,
    train_steps: int,
    test_count: int,
    test_steps: int,
    horizon: int,
    long_horizon: int,
    channels: int,
    blocks: int,
    zero_output: bool,
) -> Scene:
    """The scene; see the module docstring for the equations, steppers and training modalities. The
    data do not depend on ``key`` (the study's fixed initial states): seeds differ in network and
    minibatches."""
    stepper = choice("task.stepper", stepper, STEPPERS)
    training = choice("task.training", training, TRAININGS)
    unroll = number("task.unroll", unroll, 1, integer=True)
    settings = data_settings(
        unroll,
        points,
        base_domain,
        train_sizes,
        test_sizes,
        dt,
        substeps,
        warmup,
        train_steps,
        test_count,
        test_steps,
    )
    horizon = number("task.horizon", horizon, 1, settings["test_steps"] + 1, integer=True)
    long_horizon = number(
        "task.long_horizon", long_horizon, horizon, settings["test_steps"] + 1, integer=True
    )
    channels = number("task.channels", channels, 1, integer=True)
    blocks = number("task.blocks", blocks, 0, integer=True)
    zero_output = flag("task.zero_output", zero_output)
    dtype = jnp.zeros(()).dtype
    data = dataset(settings)
    model = Stepper(stepper, settings["base_domain"], settings["dt"], settings["substeps"])
    train_shape = data["train"].shape  # (sizes, initial states, frames, points)
    return Scene(
        init_params=partial(
            init_resnet, channels=channels, blocks=blocks, dtype=dtype, zero_output=zero_output
        ),
        train_set=training_set(data["train"], settings["train_sizes"], dtype),
        draw_batch=partial(
            draw_windows, training, unroll, train_shape[0] * train_shape[1], train_shape[2]
        ),
        test_set=held_out_set(data["test"], settings["test_sizes"], horizon, dtype),
        validation_set=held_out_set(data["validation"], settings["test_sizes"], horizon, dtype),
        test_output=partial(held_out_output, model, horizon),
        dynamics=dynamics(model, training, unroll),
        sample_loss=sample_loss,
        sample_metrics=partial(stability_metrics, model, long_horizon, dtype),
        figure=partial(
            draw_rollouts,
            stepper=model,
            variant=f"{stepper}, {training}, m = {unroll}",
            horizon=horizon,
            long_horizon=long_horizon,
        ),
    )


def rollout_errors(
    params: Params, test_set: dict, stepper: Stepper, horizon: int, steps: int
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """draw_rollouts' data: the network's rollouts and the ground truth over ``steps`` steps (test
    states, steps, points), and the relative error per test state and step of the network and of the
    coarse solver alone, capped as the held-out loss caps it."""
    model = np.asarray(
        jax.jit(jax.vmap(lambda u, s: stepper.autoregressive(params, u, s, steps)))(
            test_set["state"], test_set["size"]
        )
    )
    truth = np.asarray(test_set["target"][:, :steps])

    def solver_alone(u: jax.Array, size: jax.Array) -> jax.Array:
        return jax.lax.scan(lambda v, _: (stepper.coarse(v, size),) * 2, u, None, length=steps)[1]

    baseline = np.asarray(jax.jit(jax.vmap(solver_alone))(test_set["state"], test_set["size"]))
    scale = np.max(truth[:, :horizon] ** 2, axis=(1, 2))[:, None]
    with np.errstate(all="ignore"):  # capped as the held-out loss caps it
        errors = {
            label: np.where(np.isfinite(e), np.minimum(e, ERROR_CAP), ERROR_CAP)
            for label, e in (
                ("network", np.mean((model - truth) ** 2, axis=2) / scale),
                ("coarse solver P alone", np.mean((baseline - truth) ** 2, axis=2) / scale),
            )
        }
    return model, truth, errors


def draw_rollouts(
    params: Params,
    test_set: dict,
    path: str | Path,
    stepper: Stepper,
    variant: str,
    horizon: int,
    long_horizon: int,
) -> None:
    """scene.png: a test rollout against the ground truth as space-time images (truth, model,
    difference), and the relative error per rollout step (median over the test states, with the
    coarse solver alone for reference)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = long_horizon
    model, truth, errors = rollout_errors(params, test_set, stepper, horizon, steps)
    sizes = np.asarray(test_set["size"])
    index = int(np.argmin(np.abs(sizes - np.median(sizes))))  # an interpolating size
    shown = min(steps, 200)
    fig = plt.figure(figsize=(13, 6.2))
    grid = fig.add_gridspec(2, 3, height_ratios=[1.0, 0.9])
    limit = float(np.max(np.abs(truth[index, :shown])))
    panels = (
        ("ground truth (ETD2RK)", truth[index]),
        ("network rollout", model[index]),
        ("network - truth", model[index] - truth[index]),
    )
    for column, (title, field) in enumerate(panels):
        ax = fig.add_subplot(grid[0, column])
        image = ax.imshow(
            np.clip(field[:shown].T, -2 * limit, 2 * limit),
            aspect="auto",
            origin="lower",
            cmap="RdBu_r",
            vmin=-limit,
            vmax=limit,
            extent=(1, shown, 0, field.shape[1]),
        )
        ax.set_title(f"{title}, size {sizes[index]:.3g}", fontsize=9)
        ax.set_xlabel("rollout step")
        ax.set_ylabel("grid point")
    fig.colorbar(image, ax=fig.axes, shrink=0.6, pad=0.01, label="u")
    ax = fig.add_subplot(grid[1, :])
    for label, error in errors.items():
        ax.semilogy(
            np.arange(1, steps + 1),
            np.median(error, axis=0),
            label=f"{label}: median over {len(error)} test states",
        )
    ax.axhline(ERROR_CAP, color="k", lw=0.8, ls="--", label=f"cap ({ERROR_CAP:g}: blown up)")
    ax.axvline(horizon, color="gray", ls=":", lw=1, label=f"the study's horizon ({horizon} steps)")
    ax.set_xlabel("rollout step")
    ax.set_ylabel("mean_x (u - u*)^2 / max u*^2")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(
        f"Kuramoto-Sivashinsky: learned stepper ({variant}) on held-out test states", fontsize=10
    )
    write_figure(fig, path, dpi=100, bbox_inches="tight")
    plt.close(fig)
