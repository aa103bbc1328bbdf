"""The probes of `physgrad check`: each measures one numerical property directly, without a training
run, and gives rows of the suite's table (case, variant, precision, outcome, final loss, detail):
the Schroedinger solver's norm drift under random fields, the growth of the BPTT gradient with the
unroll length, and the spectral kernel on rank-deficient Jacobians."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from physgrad.readout import fmt

if TYPE_CHECKING:
    from physgrad.nets import Params


def quantum_norm_drift(small: bool) -> list[dict]:
    """max_t | |psi_t| - 1 | under random fields of amplitude A, from phi_1, in float32 and float64:
    CN is
    unitary, so only round-off may move the norm."""
    import jax
    import jax.numpy as jnp

    from physgrad.members import set_precision
    from physgrad.tasks.quantum import crank_nicolson_step, eigenstate, grid

    unroll = 1024 if small else 4096
    rows = []
    for bits in (32, 64):
        set_precision(bits)
        real = jnp.float64 if bits == 64 else jnp.float32
        x = grid(14, real)
        for amplitude in (10.0, 1000.0):
            fields = amplitude * jax.random.uniform(
                jax.random.PRNGKey(0), (unroll,), real, -1.0, 1.0
            )

            def body(psi: jax.Array, u: jax.Array) -> tuple[jax.Array, jax.Array]:
                psi = crank_nicolson_step(psi, u, x, 0.05)
                return psi, jnp.abs(jnp.linalg.norm(psi) - 1.0)

            psi0 = eigenstate(1, 14, real).astype(jnp.complex128 if bits == 64 else jnp.complex64)
            final, drift = jax.jit(lambda p: jax.lax.scan(body, p, fields))(psi0)
            worst = float(jnp.max(drift))
            rows.append(
                {
                    "case": f"quantum norm, random fields up to {amplitude:g}, {unroll} steps",
                    "variant": "-",
                    "precision": str(bits),
                    "outcome": "finite" if np.isfinite(worst) else "non-finite",
                    "final loss": math.nan,
                    "detail": f"largest deviation of the norm from 1: {worst:.2e}",
                }
            )
    set_precision(32)
    return rows


def bptt_gradient_growth(small: bool) -> list[dict]:
    """The gradient norm on the 4-pole cart against the unroll length, regular (R) and physics-only
    (M) backpropagation, float64; the growth per doubling of the unroll length is the detail. The
    network is the initial one with a random output layer instead of the zero one (with a zero
    output layer the force is 0 and no gradient reaches the network's input, so R and M would
    coincide)."""
    import jax
    import optax

    from physgrad.configs import compose
    from physgrad.members import set_precision
    from physgrad.tasks import build_scene
    from physgrad.unroll import MODES

    set_precision(64)
    unrolls = (25, 50, 100) if small else (25, 50, 100, 200, 400)
    rows = []
    cfg = compose(["task=multicart", "task.poles=4", "precision=64"])
    data_key, init_key, batch_key = jax.random.split(jax.random.PRNGKey(0), 3)
    for mode in ("R", "M"):
        norms = []
        for unroll in unrolls:
            scene = build_scene(cfg.task, data_key, unroll)
            params = scene.init_params(init_key)
            last = params[-1]["w"]
            params[-1] = {
                **params[-1],
                "w": 0.1
                * jax.random.normal(jax.random.fold_in(init_key, 1), last.shape, last.dtype),
            }
            batch = scene.sample_train(batch_key, 8)
            output = scene.backprop_output(MODES[mode])

            def loss(p: Params) -> jax.Array:
                return scene.batch_loss(jax.vmap(output, in_axes=(None, 0))(p, batch), batch)

            norms.append(float(optax.tree.norm(jax.jit(jax.grad(loss))(params))))
        growth = (
            (norms[-1] / norms[0]) ** (1.0 / math.log2(unrolls[-1] / unrolls[0]))
            if norms[0] > 0
            else math.nan
        )
        rows.append(
            {
                "case": "multicart 4 poles: gradient norm against unroll",
                "variant": f"bptt backprop={mode}",
                "precision": "64",
                "outcome": "finite" if all(map(math.isfinite, norms)) else "non-finite",
                "final loss": math.nan,
                "detail": ", ".join(f"{h}: {n:.2e}" for h, n in zip(unrolls, norms))
                + f"; x{fmt(float(growth))} per doubling",
            }
        )
    set_precision(32)
    return rows


def rank_deficient_kernels(small: bool) -> list[dict]:
    """The spectral kernel (HIG: kappa 1/2, Gauss-Newton: kappa 1) on Jacobians with duplicated
    samples, dead ReLUs (zero columns) and all zeros, for tau 1e-12 .. 1e-2, both routes, float32
    and float64; the detail is the worst relative error against a numpy float64 SVD of the same
    matrix with the same truncation."""
    import jax.numpy as jnp

    from physgrad.members import set_precision
    from physgrad.optim.spectral import truncated_spectral_direction

    rng = np.random.default_rng(0)
    m, n = (48, 120) if small else (256, 1024)
    base = rng.standard_normal((m // 2, n)) * np.logspace(0, -3, m // 2)[:, None]
    dead = rng.standard_normal((m, n))
    dead[:, rng.random(n) < 0.5] = 0.0
    matrices = {
        "duplicated samples": np.concatenate([base, base]),
        "dead ReLUs (half the columns zero)": dead,
        "all-zero J": np.zeros((m, n)),
    }
    g = rng.standard_normal(m)
    taus = (1e-12, 1e-8, 1e-6, 1e-4, 1e-2)
    rows = []
    for bits in (32, 64):
        set_precision(bits)
        dtype = np.float64 if bits == 64 else np.float32
        for name, jac in matrices.items():
            for variant, kappa in (("gauss_newton", 1.0), ("hig", 0.5)):
                errors, finite = [], True
                given = jac.astype(dtype)
                u, s, vt = np.linalg.svd(given.astype(np.float64), full_matrices=False)
                for tau in taus:
                    keep = s > tau * s.max() if s.max() > 0 else np.zeros_like(s, bool)
                    expected = vt[keep].T @ (s[keep] ** -kappa * (u[:, keep].T @ g))
                    for route in ("svd", "gram"):
                        got = np.asarray(
                            truncated_spectral_direction(
                                jnp.asarray(given), jnp.asarray(g, dtype), kappa, tau, route
                            ),
                            np.float64,
                        )
                        finite &= bool(np.isfinite(got).all())
                        scale = np.linalg.norm(expected)
                        errors.append(
                            (np.linalg.norm(got - expected) / scale)
                            if scale > 0
                            else float(np.abs(got).max())
                        )
                by_tau = np.array(errors).reshape(len(taus), 2).max(axis=1)
                rows.append(
                    {
                        "case": f"rank-deficient J: {name}",
                        "variant": variant,
                        "precision": str(bits),
                        "outcome": "finite" if finite else "non-finite",
                        "final loss": math.nan,
                        "detail": "worst rel. error (svd, gram) at tau "
                        + ", ".join(f"{t:.0e}: {e:.1e}" for t, e in zip(taus, by_tau)),
                    }
                )
    set_precision(32)
    return rows
