"""The Kuramoto-Sivashinsky scene's solver and data (physgrad.tasks.ks builds the scene on them;
its docstring gives the equations and the ETD schemes).

Solver: ETD1 and ETD2RK steps of u_t + u u_x + u_xx + u_xxxx = 0 on a periodic grid. Data: the
study's initial states, their ground-truth trajectories (ETD2RK in float64) cached on disk, and the
training and held-out sets drawn from them.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from physgrad.files import cache_dir, replace_file

# bump when the generated data would change for the same settings
DATA_VERSION = 2  # 2: a validation set beside the test set
# numpy seeds of the held-out states: TEST_SEED + the test size's index
TEST_SEED, VALIDATION_SEED = (
    1000,
    2000,
)


# --------------------------------------------------------------------------------------------------
# solver


def _series_or_exact(
    x: jax.Array, exact: Callable[[jax.Array], jax.Array], coefficients: list[float]
) -> jax.Array:
    """exact(x) where |x| >= 0.1, else the Taylor series sum_k coefficients[k] x^k (exact would
    cancel)."""
    small = jnp.abs(x) < 0.1
    safe = jnp.where(small, 1.0, x)
    series = sum(c * x**k for k, c in enumerate(coefficients))
    return jnp.where(small, series, exact(safe))


def phi1(x: jax.Array) -> jax.Array:
    """(e^x - 1) / x, to round-off also near x = 0."""
    return _series_or_exact(
        x, lambda z: jnp.expm1(z) / z, [1 / math.factorial(k + 1) for k in range(9)]
    )


def phi2(x: jax.Array) -> jax.Array:
    """(e^x - 1 - x) / x^2, to round-off also near x = 0."""
    return _series_or_exact(
        x, lambda z: (jnp.expm1(z) - z) / z**2, [1 / math.factorial(k + 2) for k in range(9)]
    )


def wavenumbers(points: int, length: float | jax.Array) -> jax.Array:
    """kappa_n = 2 pi n / L for the rfft modes n = 0 .. points/2."""
    return 2 * jnp.pi * jnp.arange(points // 2 + 1) / length


def nonlinear(u: jax.Array, kappa: jax.Array) -> jax.Array:
    """N(u) = -(i kappa / 2) FFT(u^2), the transform of -u u_x."""
    return -0.5j * kappa * jnp.fft.rfft(u * u)


def etd_step(u: jax.Array, length: float | jax.Array, h: float, order: int) -> jax.Array:
    """One ETD1 (order 1) or ETD2RK (order 2) step of size h; u real on the grid, length L (may be
    traced)."""
    points = u.shape[-1]
    kappa = wavenumbers(points, length)
    x = (kappa**2 - kappa**4) * h
    u_hat, n_u = jnp.fft.rfft(u), nonlinear(u, kappa)
    a_hat = jnp.exp(x) * u_hat + h * phi1(x) * n_u
    if order == 1:
        return jnp.fft.irfft(a_hat, points)
    a = jnp.fft.irfft(a_hat, points)
    return jnp.fft.irfft(a_hat + h * phi2(x) * (nonlinear(a, kappa) - n_u), points)


def solver_step(
    u: jax.Array, length: float | jax.Array, h: float, substeps: int, order: int
) -> jax.Array:
    """One model step: `substeps` ETD steps of size h."""
    for _ in range(substeps):
        u = etd_step(u, length, h, order)
    return u


def domain_length(base_domain: float, size: float | jax.Array) -> float | jax.Array:
    return 2 * jnp.pi * base_domain * size


# --------------------------------------------------------------------------------------------------
# data


def train_initial_states(points: int, base_domain: float, size: float) -> np.ndarray:
    """The study's six training initial states on x_j = D j / points with D = base_domain * size:
    cos(2 pi x) + a cos(2 pi x / D) (1 + b sin(2 pi x / D)) for (a, b) in (0.1, +-0.1), (-0.2,
    +-0.3), (0.3, +-0.5)."""
    d = base_domain * size
    x = d * np.arange(points) / points
    return np.stack(
        [
            np.cos(2 * np.pi * x)
            + a * np.cos(2 * np.pi * x / d) * (1 + b * np.sin(2 * np.pi * x / d))
            for a in (0.1, -0.2, 0.3)
            for b in ({0.1: (0.1, -0.1), -0.2: (0.3, -0.3), 0.3: (0.5, -0.5)}[a])
        ]
    )


def test_initial_states(
    points: int, base_domain: float, size: float, count: int, seed: int
) -> np.ndarray:
    """The study's test family: cos(pi x) + c cos(2 pi x / D) (1 - s sin(2 pi x / D)), c ~ U(-0.1,
    0.1), s ~ U(-2, 2), drawn from a fixed seed per test size."""
    d = base_domain * size
    x = d * np.arange(points) / points
    rng = np.random.default_rng(seed)
    c, s = rng.uniform(-0.1, 0.1, count), rng.uniform(-2.0, 2.0, count)
    return np.cos(np.pi * x) + c[:, None] * np.cos(2 * np.pi * x / d) * (
        1 - s[:, None] * np.sin(2 * np.pi * x / d)
    )


def trajectories(
    initial: np.ndarray, lengths: np.ndarray, steps: int, h: float, substeps: int
) -> np.ndarray:
    """Ground truth in float64 (whatever the run's precision): initial (n, points), one domain
    length per row -> (n, steps + 1, points), ETD2RK model steps."""
    with jax.enable_x64(True):

        def advance(u: jax.Array, _: None) -> tuple[jax.Array, jax.Array]:
            u = jax.vmap(lambda v, length: solver_step(v, length, h, substeps, 2))(u, lengths)
            return u, u

        _, states = jax.jit(lambda u0: jax.lax.scan(advance, u0, None, length=steps))(
            jnp.asarray(initial)
        )
        return np.concatenate([initial[:, None], np.asarray(states).transpose(1, 0, 2)], axis=1)


def generate(
    settings: dict, initial_by_size: list, sizes: list, warmup: int, steps: int
) -> np.ndarray:
    """Ground truth from each size's initial states: `warmup` model steps dropped, then `steps` kept
    -> (len(sizes), initial states per size, steps + 1, points)."""
    initial = np.concatenate(initial_by_size)
    lengths = np.repeat(
        [float(domain_length(settings["base_domain"], size)) for size in sizes],
        [len(i) for i in initial_by_size],
    )
    warm = trajectories(initial, lengths, warmup, settings["dt"], settings["substeps"])[:, -1]
    states = trajectories(warm, lengths, steps, settings["dt"], settings["substeps"])
    return states.reshape(len(sizes), -1, *states.shape[1:])


def dataset(settings: dict) -> dict:
    """The training and test trajectories for ``settings``, generated on first use and cached in
    cache_dir()/ks-<hash of the settings>.npz (a change of any setting names another file).

    train: (sizes, 6, train_steps + 1, points) after `warmup` steps; test: (test sizes, test_count,
    test_steps + 1, points) after 2 * warmup steps (the study starts its test rollouts 200 steps
    into trajectories cropped after 200); validation: as test, from other seeds of the same
    family."""
    key = json.dumps({**settings, "version": DATA_VERSION}, sort_keys=True)
    path = cache_dir() / f"ks-{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if path.exists():
        try:
            with np.load(path) as stored:
                if str(stored["settings"]) == key:
                    return {part: stored[part] for part in ("train", "test", "validation")}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            pass  # damaged or foreign: generate again
    s = settings
    initial = [
        train_initial_states(s["points"], s["base_domain"], size) for size in s["train_sizes"]
    ]
    data = {"train": generate(s, initial, s["train_sizes"], s["warmup"], s["train_steps"])}
    # test and validation: the test family from a fixed seed per test size (first seed + its index);
    # validation from other seeds, for tuning (physgrad compare), so that no choice is made on the
    # test states
    for part, first_seed in (("test", TEST_SEED), ("validation", VALIDATION_SEED)):
        initial = [
            test_initial_states(
                s["points"], s["base_domain"], size, s["test_count"], first_seed + index
            )
            for index, size in enumerate(s["test_sizes"])
        ]
        data[part] = generate(s, initial, s["test_sizes"], 2 * s["warmup"], s["test_steps"])
    path.parent.mkdir(parents=True, exist_ok=True)
    content = io.BytesIO()
    np.savez(content, **data, settings=np.array(key))
    replace_file(path, content.getvalue())  # a concurrent job of a sweep reads a whole file or none
    return data


def training_set(train: np.ndarray, sizes: list[float], dtype: DTypeLike) -> dict:
    """train (sizes, initial states, frames, points) as flat frames, each with its size factor."""
    train = jnp.asarray(train, dtype)
    return {
        "frames": train.reshape(-1, train.shape[-1]),
        "size": jnp.repeat(jnp.asarray(sizes, dtype), train.shape[1] * train.shape[2]),
    }


def draw_windows(
    training: str,
    unroll: int,
    trajectories_count: int,
    frames_count: int,
    key: jax.Array,
    batch_size: int,
    frames_set: dict,
) -> dict:
    """B windows of m + 1 consecutive frames (trajectory and start uniform) from the flat frames of
    `trajectories_count` trajectories of `frames_count` frames; for ONE, B x m independent one-step
    pairs, m per sample."""
    pairs = batch_size * unroll if training == "ONE" else batch_size
    span = 1 if training == "ONE" else unroll
    k_trajectory, k_start = jax.random.split(key)
    trajectory = jax.random.randint(k_trajectory, (pairs,), 0, trajectories_count)
    first = trajectory * frames_count + jax.random.randint(
        k_start, (pairs,), 0, frames_count - span
    )
    # (pairs, span + 1, points)
    frames = frames_set["frames"][first[:, None] + jnp.arange(span + 1)]
    size = frames_set["size"][first]
    if training == "ONE":
        frames = frames.reshape(batch_size, unroll, 2, frames.shape[-1])
        size = size.reshape(batch_size, unroll)
        return {
            "inputs": frames[:, :, 0],
            "target": frames[:, :, 1],
            "sizes": size,
            "state": frames[:, 0, 0],
            "size": size[:, 0],
        }
    return {"state": frames[:, 0], "target": frames[:, 1:], "size": size}


def held_out_set(frames: np.ndarray, sizes: list[float], horizon: int, dtype: DTypeLike) -> dict:
    """Rollout samples from held-out trajectories (test sizes, count, frames, points)."""
    frames = jnp.asarray(frames, dtype)
    states = frames[:, :, 0].reshape(-1, frames.shape[-1])
    targets = frames[:, :, 1:].reshape(-1, frames.shape[2] - 1, frames.shape[-1])
    return {
        "state": states,
        "target": targets,
        "size": jnp.repeat(jnp.asarray(sizes, dtype), frames.shape[1]),
        # the study's normaliser: the largest u*^2 over frames 0..horizon, the state itself included
        "scale": jnp.maximum(
            jnp.max(states**2, axis=1), jnp.max(targets[:, :horizon] ** 2, axis=(1, 2))
        ),
    }
