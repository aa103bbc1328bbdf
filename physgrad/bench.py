"""`make bench`: step time, compile time and peak memory of every scene x variant at its reference
size, with the floors it is measured against, as one markdown table.

Every measurement runs in its own subprocess (a fresh peak-memory counter and no cache shared
between variants); the table gives ratios against baselines measured in the same run, never absolute
targets:
- Jacobian variants (hig, gauss_newton): the step with the form of J physgrad chooses
  (layer-factorised where the network allows it) against the same step with the per-sample Jacobian,
  and against its floor: the fastest float64 eigendecomposition of an m x m symmetric matrix (numpy,
  scipy or jax) plus one bare forward and backward pass (draw, loss, gradient);
- adam: step / a bare jitted loss-and-gradient of the same function (minibatch draw, loss,
  gradient);
- runner overhead: the share of a `physgrad run` training loop's wall time (compilation excluded)
  spent neither in training steps nor in evaluations: row buffering, HDF5 flushes, NaN checks,
  progress bar, at the default logging cadence.

Each subprocess measures through physgrad.bench_measure; physgrad.bench_tables writes the tables.

    python -m physgrad.bench [--out docs/benchmarks.md] [--scenes poisson,oscillator] [--quick]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from physgrad.bench_measure import measure_floors, measure_seeds, measure_variant
from physgrad.bench_tables import OPTIMS, SCENES, machine, page
from physgrad.files import write_text

# variants measured in another precision as well
EXTRA = {
    "poisson": [("hig", ["precision=64"])],
    # the unrolling study's other training modalities and stepper, and its longest unroll
    "ks": [
        ("adam", ["task.training=ONE"]),
        ("adam", ["task.training=NOG"]),
        ("adam", ["task.stepper=predict"]),
        ("adam", ["unroll=16"]),
    ],
}
# temporal scenes whose Jacobian pass would differentiate 128 x 64 outputs per sample: not a
# reference setup
SKIP = {
    ("quantum_control", "hig"),
    ("quantum_control", "gauss_newton"),
    ("quantum_control", "gd"),
    ("quantum_control", "levenberg_marquardt"),
}


SEED_CASES = (
    ("oscillator", "adam"),
    ("oscillator", "hig"),
    ("quantum", "adam"),
    ("multicart", "bptt"),
    ("multicart", "stable_bptt"),
    ("quantum_control", "stable_bptt"),
)
# the configurations as a run takes them (the Jacobian rules' float64 retry batches over seeds)
SEED_OVERRIDES: dict[str, list[str]] = {}


def run_seeds(
    scenes: Iterable[str],
    count: int,
    repeats: int,
    min_seconds: float,
    timeout: float,
    on_row: Callable[[list[dict]], object] = lambda rows: None,
) -> list[dict]:
    rows: list[dict] = []
    for task, optim in SEED_CASES:
        if task not in scenes:
            continue
        overrides = [f"task={task}", f"optim={optim}", *SEED_OVERRIDES.get(optim, [])]
        print(f"bench: {' '.join(overrides)} seeds={count}", file=sys.stderr, flush=True)
        result = _subprocess(
            "seeds",
            {
                "overrides": overrides,
                "count": count,
                "repeats": repeats,
                "min_seconds": min_seconds,
            },
            timeout,
        )
        rows.append({"task": task, "variant": optim, **result})
        on_row(rows)
    return rows


def _subprocess(kind: str, payload: dict, timeout: float) -> dict:
    command = [sys.executable, "-m", "physgrad.bench", f"--{kind}", json.dumps(payload)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"no result within {timeout:.0f} s"}
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["?"])[-1]
        return {"error": f"exit {done.returncode}: {last}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_bench(
    scenes: Iterable[str],
    repeats: int,
    min_seconds: float,
    timeout: float,
    on_row: Callable[[list[dict]], object] = lambda rows: None,
    optims: Iterable[str] = OPTIMS,
) -> list[dict]:
    """Every scene x variant (of optims) measured in its own subprocess; a variant the scene refuses
    at its reference size is a row with the reason; on_row(rows so far) after each."""
    rows: list[dict] = []
    optims = tuple(optims)
    for task in scenes:
        jobs = [
            (optim, [f"task={task}", f"optim={optim}"])
            for optim in optims
            if (task, optim) not in SKIP
        ]
        jobs += [
            (optim, [f"task={task}", f"optim={optim}", *extra])
            for optim, extra in EXTRA.get(task, [])
            if optim in optims
        ]
        for optim, overrides in jobs:
            print(f"bench: {' '.join(overrides)}", file=sys.stderr, flush=True)
            result = _subprocess(
                "variant",
                {"overrides": overrides, "repeats": repeats, "min_seconds": min_seconds},
                timeout,
            )
            if "refused" in result:
                rows.append({"task": task, "variant": optim, "refused": result["refused"]})
                on_row(rows)
                continue
            precision = 64 if "precision=64" in overrides else 32
            if "jac_shape" in result:
                size = result["jac_shape"][0]
                floors = next((r["floors"] for r in rows if r.get("floor_size") == size), None)
                if floors is None:
                    floors = _subprocess("floors", {"size": size, "repeats": repeats}, timeout)
                result.update(floor_size=size, floors=floors)
            settings = [o.removeprefix("task.") for o in overrides[2:] if o != "precision=64"]
            variant = (
                optim
                + ("" if precision == 32 else " f64")
                + (f" ({', '.join(settings)})" if settings else "")
            )
            rows.append({"task": task, "variant": variant, "precision": precision, **result})
            on_row(rows)
    return rows


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m physgrad.bench", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--out", default="outputs/bench/benchmarks.md", help="markdown table (and a .json beside)"
    )
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated tasks")
    parser.add_argument(
        "--optims", default=",".join(OPTIMS), help="comma-separated update rules (conf/optim)"
    )
    parser.add_argument(
        "--repeats", type=int, default=5, help="timed steps at least (median), after a warm-up"
    )
    parser.add_argument(
        "--min-seconds", type=float, default=3.0, help="and at least this long per measurement"
    )
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per subprocess")
    parser.add_argument("--variant", help=argparse.SUPPRESS)
    parser.add_argument("--floors", help=argparse.SUPPRESS)
    parser.add_argument("--seeds", help=argparse.SUPPRESS)
    parser.add_argument(
        "--vectorised-seeds",
        type=int,
        default=8,
        help="N of the seeds=N throughput table (0: no such table)",
    )
    return parser


def _measurement(options: argparse.Namespace) -> dict | None:
    """What a subprocess was asked to measure (--seeds, --variant or --floors with its payload as
    JSON); None in the parent process."""
    if options.seeds:
        payload = json.loads(options.seeds)
        return measure_seeds(
            payload["overrides"], payload["count"], payload["repeats"], payload["min_seconds"]
        )
    if options.variant:
        payload = json.loads(options.variant)
        return measure_variant(payload["overrides"], payload["repeats"], payload["min_seconds"])
    if options.floors:
        payload = json.loads(options.floors)
        return measure_floors(payload["size"], payload["repeats"])
    return None


def main(argv: list[str] | None = None) -> int:
    options = _parser().parse_args(argv)
    measured = _measurement(options)
    if measured is not None:  # a subprocess: its result as one line of JSON
        print(json.dumps(measured))
        return 0
    scenes = [s for s in options.scenes.split(",") if s]
    optims = [o for o in options.optims.split(",") if o]
    for kind, asked, known in (("scene", scenes, SCENES), ("optim", optims, OPTIMS)):
        unknown = sorted(set(asked) - set(known))
        if unknown:
            print(
                f"physgrad bench: error: unknown {kind} {', '.join(unknown)}: choose from "
                f"{', '.join(known)}",
                file=sys.stderr,
            )
            return 2
    start = time.perf_counter()
    out = Path(options.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    described = machine()

    def write(rows: list[dict], seed_rows: list[dict]) -> str:
        """The page as measured so far: a bench cut short keeps every row it finished."""
        text = page(
            rows,
            seed_rows,
            described,
            options.repeats,
            options.min_seconds,
            time.perf_counter() - start,
            options.vectorised_seeds,
        )
        write_text(out, text)
        write_text(
            out.with_suffix(".json"),
            json.dumps({"variants": rows, "seeds": seed_rows}, indent=1, default=str),
        )
        return text

    rows = run_bench(
        scenes,
        options.repeats,
        options.min_seconds,
        options.timeout,
        on_row=lambda so_far: write(so_far, []),
        optims=optims,
    )
    seed_rows = (
        run_seeds(
            scenes,
            options.vectorised_seeds,
            options.repeats,
            options.min_seconds,
            options.timeout,
            on_row=lambda so_far: write(rows, so_far),
        )
        if options.vectorised_seeds > 0
        else []
    )
    text = write(rows, seed_rows)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
