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
from physgrad.readout import fmt
from physgrad.stability_probes import (
    bptt_gradient_growth,
    quantum_norm_drift,
    rank_deficient_kernels,
)

if TYPE_CHECKING:
    pass


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
        detail = (
            f"test loss {fmt(float(test[0]))} -> {fmt(final)} in {outcome.iterations} iterations"
        )
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
