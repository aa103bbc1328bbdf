"""`physgrad check` (`make check-stability`): stiff and extreme cases, and what the tool does with
them.

Two kinds of case: training runs through `run_experiment` (results in outputs/check/<case>/, so
every curve can be inspected) and probes that measure one numerical property directly (norm drift of
the Schroedinger solver, growth of the BPTT gradient with the unroll length, the spectral kernel on
rank-deficient Jacobians). Each gives a row: case, variant, precision, outcome, final loss, detail.
Outcomes of runs:
  converged  completed with the final test loss below half the initial one;
  stalled    completed without halving it;
  grew       completed with the final test loss above the initial one;
  diverged   with the quantity that went non-finite first and the iteration;
  refused    with the reason; failed with the error (a bug in physgrad: please report it).
`--small` is the form that runs in CI (about two minutes); the default is the full suite.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from physgrad.files import write_text

if TYPE_CHECKING:
    from physgrad.nets import Params


@dataclass(frozen=True)
class RunCase:
    case: str
    overrides: tuple[str, ...]

    @property
    def slug(self) -> str:
        return "".join(c if c.isalnum() or c in "=-." else "_" for c in "_".join(self.overrides))


def run_cases(small: bool) -> list[RunCase]:
    """The training-run cases; --small keeps one or two variants per case with short runs."""
    its = (
        (lambda n: f"trainer.iterations={max(5, n // 15)}")
        if small
        else (lambda n: f"trainer.iterations={n}")
    )
    oscillator = ("task=oscillator", "trainer.eval_every=50") + (
        ("task.train_size=512", "task.test_size=256") if small else ()
    )
    cases = _stiff_oscillator_cases(small, its, oscillator)
    if not small:
        cases += _long_unroll_cases(its, oscillator)
    cases += _guidance_cases(small, its)
    toy = ("task=toy", "trainer.eval_every=100")
    cases += [
        RunCase("badly scaled toy (lambda 0.01)", (*toy, f"optim={o}", its(3000)))
        for o in ("adam", "gauss_newton", "hig", "levenberg_marquardt", "kfac", "lbfgs", "muon")
    ]
    return cases + _too_large_cases(small, its, oscillator)


def _stiff_oscillator_cases(
    small: bool, its: Callable[[int], str], oscillator: tuple[str, ...]
) -> list[RunCase]:
    """The oscillator with a stiff coupling and with a large time step."""
    jacobian = (
        ("adam", "hig") if small else ("adam", "gauss_newton", "hig", "levenberg_marquardt", "kfac")
    )
    cases = []
    for alpha in (100,) if small else (10, 100):
        cases += [
            RunCase(
                f"oscillator stiff coupling alpha={alpha}",
                (*oscillator, f"optim={o}", f"task.alpha={alpha}", its(300)),
            )
            for o in jacobian
        ]
    cases += [
        RunCase(
            "oscillator large step dt=0.5", (*oscillator, f"optim={o}", "task.dt=0.5", its(300))
        )
        for o in (("hig",) if small else jacobian)
    ]
    return cases


def _long_unroll_cases(its: Callable[[int], str], oscillator: tuple[str, ...]) -> list[RunCase]:
    """Long rollouts (the full suite only): oscillator, quantum and the 4-pole cart."""
    cases = [
        RunCase(
            "oscillator long unroll, 1024 steps",
            (*oscillator, f"optim={o}", "unroll=1024", its(100)),
        )
        for o in ("adam", "hig")
    ]
    cases += [
        RunCase(
            "quantum long unroll, 4096 steps",
            (
                "task=quantum",
                f"optim={o}",
                "unroll=4096",
                "task.test_size=128",
                "trainer.eval_every=5",
                its(10),
            ),
        )
        for o in ("adam", "hig")
    ]
    cases += [
        RunCase(
            "multicart 4 poles, 400 steps",
            ("task=multicart", f"optim={o}", "task.poles=4", "unroll=400", its(300)),
        )
        for o in ("bptt", "stable_bptt")
    ]
    return cases


def _guidance_cases(small: bool, its: Callable[[int], str]) -> list[RunCase]:
    """Agents that pass close to each other."""
    # softening 0.001 lets agents that pass close feel forces up to repulsion / 0.001^2 = 1.5e7
    # (10^4 times the reference's 1.5e3 at d = 0.1): stiff for explicit Euler at dt = 1/15, with
    # spikes in the BPTT gradient
    return [
        RunCase(
            "guidance near contact (softening 0.001)",
            (
                "task=guidance",
                f"optim={o}",
                "task.softening=0.001",
                "trainer.eval_every=100",
                its(300),
                *(["task.test_size=16"] if small else []),
            ),
        )
        for o in (("bptt",) if small else ("bptt", "stable_bptt"))
    ]


def _too_large_cases(
    small: bool, its: Callable[[int], str], oscillator: tuple[str, ...]
) -> list[RunCase]:
    """A learning rate of 1e6 on every kind of update rule."""
    too_large = (
        [("oscillator", "gd"), ("oscillator", "hig"), ("multicart", "bptt")]
        if small
        else [
            ("oscillator", o)
            for o in ("adam", "gd", "gauss_newton", "hig", "levenberg_marquardt", "kfac", "lbfgs")
        ]
        + [
            ("multicart", "bptt"),
            ("multicart", "stable_bptt"),
            ("poisson", "adam"),
            ("poisson", "gd"),
            ("quantum", "adam"),
        ]
    )
    cases = []
    for task, optim in too_large:
        extra = tuple(oscillator[1:]) if task == "oscillator" else ("task.test_size=64",)
        cases.append(
            RunCase(
                f"{task}: learning rate 1e6 (far too large)",
                (f"task={task}", f"optim={optim}", "optim.learning_rate=1e6", *extra, its(50)),
            )
        )
    return cases


def run_row(case: RunCase, out_dir: Path) -> dict:
    from physgrad.configs import compose
    from physgrad.experiment import run_experiment
    from physgrad.members import variant_label
    from physgrad.results import read_run

    # no per-case figures: the table is the output (the curves stay in the results files)
    cfg = compose([*case.overrides, "overwrite=true", "figures=false"])
    try:
        outcome, path = run_experiment(cfg, out_dir / case.slug)
    except Exception as error:  # noqa: BLE001 - a failure is a row of the table, not the end of the suite
        return {
            "case": case.case,
            "variant": variant_label(cfg.optim),
            "precision": str(cfg.precision),
            "outcome": "failed",
            "final loss": math.nan,
            "detail": f"{type(error).__name__}: {error}"[:200],
        }
    run = read_run(path)
    test = run.eval.get("loss", np.empty(0))
    final = float(test[-1]) if test.size else math.nan
    if outcome.status == "completed":
        initial = float(test[0]) if test.size else math.nan
        label = "converged" if final < 0.5 * initial else ("grew" if final > initial else "stalled")
        detail = f"test loss {float(test[0]):.3g} -> {final:.3g} in {outcome.iterations} iterations"
    else:
        label = outcome.status
        train_loss = run.train.get("loss", np.empty(0))
        finite = train_loss[np.isfinite(train_loss)]
        final = float(finite[-1]) if finite.size else final  # the last finite minibatch loss
        detail = outcome.reason or ""
    return {
        "case": case.case,
        "variant": variant_label(cfg.optim),
        "precision": str(cfg.precision),
        "outcome": label,
        "final loss": final,
        "detail": detail,
    }


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
                + f"; x{growth:.3g} per doubling",
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


PROBES = (quantum_norm_drift, bptt_gradient_growth, rank_deficient_kernels)
COLUMNS = ("case", "variant", "precision", "outcome", "final loss", "detail")


def markdown(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        cells = [
            f"{row[c]:.4g}"
            if isinstance(row[c], float) and math.isfinite(row[c])
            else ("" if isinstance(row[c], float) else str(row[c]).replace("|", "/"))
            for c in COLUMNS
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_check(small: bool, out_dir: Path) -> list[dict]:
    rows = []
    for probe in PROBES:
        print(f"check: {probe.__name__}", file=sys.stderr, flush=True)
        rows += probe(small)
    for case in run_cases(small):
        print(f"check: {case.case}: {' '.join(case.overrides)}", file=sys.stderr, flush=True)
        rows.append(run_row(case, out_dir))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="physgrad check", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--small", action="store_true", help="the short form that CI runs (about 2 minutes)"
    )
    parser.add_argument("--out", default="outputs/check", help="folder for the runs and check.md")
    parser.add_argument(
        "-cd",
        "--config-dir",
        action="append",
        default=[],
        help="a folder of your own configs (task/NAME.yaml), as for physgrad run",
    )
    parser.add_argument(
        "overrides",
        nargs="*",
        help="task=NAME [key=value ...]: check that scene (gradients against "
        "finite differences, the rollout against a loop, J against jvp/vjp; physgrad.scene_check)",
    )
    options = parser.parse_args(argv)
    import logging

    logging.getLogger("jax").setLevel(logging.WARNING)
    if options.overrides or options.config_dir:
        from physgrad.scene_check import check_one_scene

        return check_one_scene(options.overrides, options.config_dir)
    out = Path(options.out)
    start = time.perf_counter()
    rows = run_check(options.small, out)
    text = (
        f"# physgrad check ({'small' if options.small else 'full'})\n\n{len(rows)} cases in "
        f"{time.perf_counter() - start:.0f} s; runs in {out}/.\n\n" + markdown(rows)
    )
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "check.md", text)
    print(text, end="")
    return 1 if any(row["outcome"] == "failed" for row in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
