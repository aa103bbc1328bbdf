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

    python -m physgrad.bench [--out docs/benchmarks.md] [--scenes poisson,oscillator] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from physgrad.configs import compose
from physgrad.timing import compiled_step, interleaved_times

SCENES = ("oscillator", "quantum", "poisson", "multicart", "quantum_control", "guidance", "ks")
OPTIMS = (
    "adam",
    "gd",
    "gauss_newton",
    "hig",
    "levenberg_marquardt",
    "kfac",
    "lbfgs",
    "muon",
    "bptt",
    "stable_bptt",
)
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


def _median_times(
    fns: list, repeats: int, min_seconds: float, warmup: bool = True, max_seconds: float = 120.0
) -> list[tuple[float, int]]:
    """Median wall time of each fn() (which must block until its results are ready), timed in turn
    (interleaved_times). Returns (median seconds, calls timed) per fn."""
    return [
        (statistics.median(fn_times), len(fn_times))
        for fn_times in interleaved_times(fns, repeats, min_seconds, warmup, max_seconds)
    ]


def _median_time(
    fn, repeats: int, min_seconds: float, warmup: bool = True, max_seconds: float = 120.0
) -> tuple[float, int]:
    return _median_times([fn], repeats, min_seconds, warmup, max_seconds)[0]


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux


def measure_variant(overrides: list[str], repeats: int, min_seconds: float) -> dict:
    """Compile and time the training step of one configuration (the runner's own compiled step) in
    turn with its baselines: the bare loss-and-gradient (adam and the Jacobian variants), the
    runner's overhead (adam), and for a factorised Jacobian variant the same step with the
    per-sample Jacobian."""
    import dataclasses

    import jax
    import numpy as np

    from physgrad.errors import UserError
    from physgrad.nets import count_params
    from physgrad.optim.spectral import resolve_route
    from physgrad.runner import compile_training

    cfg = compose(overrides)
    try:
        settings, scene, rule, seeds, compiled, compile_s, one_step = compiled_step(cfg, [cfg.seed])
    except UserError as error:
        return {"refused": str(error)}
    result = {"compile_s": compile_s}
    one_step()  # the first call reaches the step's peak memory, before any baseline is built
    result["peak_rss_gb"] = _peak_rss_gb()

    # the baselines: the scene's own functions on its own parameter pytree, as a user would write
    # them; timed in turn with the step (one call each per round), so that drift of the machine
    # cancels in the ratios
    timed = {"step_s": one_step}
    params = seeds.network()
    train_key = seeds.train_keys[0]
    if rule.uses_jacobian:
        batch = scene.sample_train(jax.random.fold_in(train_key, 0), settings.batch_size)
        shape = (jax.eval_shape(scene.batch_output, params, batch).size, count_params(params))
        result.update(
            jac_shape=list(shape),
            jacobian=rule.gradient.name,
            route=resolve_route(cfg.optim.route, float(cfg.optim.tau), shape),
        )
        if rule.gradient.plan is not None:
            per_sample = compile_training(
                scene,
                rule._replace(gradient=dataclasses.replace(rule.gradient, plan=None)),
                seeds,
                settings.batch_size,
            )
            state = [per_sample.params, per_sample.opt_state]

            def per_sample_step():
                state[0], state[1], _ = per_sample.step(
                    state[0], state[1], np.int32(0), seeds.train_keys, seeds.train_sets
                )
                jax.block_until_ready(state[0])

            per_sample_step()
            result["per_sample_peak_rss_gb"] = _peak_rss_gb()  # the larger of the two
            timed["per_sample_step_s"] = per_sample_step
        timed["eigh_s"] = _eigh_timer(shape[0])
    if cfg.optim.name == "adam" or rule.uses_jacobian:
        # the same function as the step's: draw the minibatch (as every step does), loss, gradient
        def loss_and_grad(p, key):
            batch = scene.sample_train(key, settings.batch_size)
            return jax.value_and_grad(
                lambda q: scene.batch_loss(scene.batch_output(q, batch), batch)
            )(p)

        bare = jax.jit(loss_and_grad).lower(params, train_key).compile()
        timed["loss_grad_s"] = lambda: jax.block_until_ready(bare(params, train_key))
    medians = _median_times(list(timed.values()), repeats, min_seconds)
    result.update({name: seconds for name, (seconds, _) in zip(timed, medians)})
    result["steps_timed"] = medians[0][1]
    if cfg.optim.name == "adam":
        eval_s, _ = _median_time(
            lambda: jax.block_until_ready(compiled.evaluate(compiled.params, seeds.test_sets)), 3, 0
        )
        result.update(runner_overhead(settings, scene, rule, seeds, result["step_s"], eval_s))
    return result


def _random_gram(size: int):
    import numpy as np

    factor = np.random.default_rng(0).standard_normal((size, size))
    return factor @ factor.T


def _eigh_timer(size: int):
    """eigh() -> the step's own eigendecomposition (jax, float64) of a random m x m Gram matrix,
    blocking."""
    import jax
    import jax.numpy as jnp

    with jax.enable_x64(True):
        matrix = jnp.asarray(_random_gram(size))
        eigh = jax.jit(jnp.linalg.eigh).lower(matrix).compile()
    return lambda: jax.block_until_ready(eigh(matrix))


def runner_overhead(settings, scene, rule, seeds, step_s: float, eval_s: float) -> dict:
    """Run `train` as `physgrad run` does (default eval_every and flush cadence) for ~10 s and split
    its wall time: the timed training steps (train_seconds, which include fetching the logged
    scalars), the evaluations (count x eval_s, their median time), and the rest, which is the
    runner's own work (row buffering, HDF5 flushes, NaN checks, progress bar). Measured within one
    run, so the machine's drift between runs does not enter."""
    import dataclasses

    import h5py

    from physgrad.results import ResultsWriter
    from physgrad.runner import train

    iterations = max(200, min(20_000, int(10.0 / step_s)))
    settings = dataclasses.replace(
        settings, iterations=iterations, time_budget=None, eval_seconds=None
    )
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "results.h5"
        start = time.perf_counter()
        (outcome,) = train(scene, rule, seeds, [ResultsWriter(path, {})], settings)
        total = time.perf_counter() - start
        with h5py.File(path) as f:
            start_up = float(f.attrs["compile_seconds"]) + float(
                f.attrs.get("first_step_overhead_seconds", 0.0)
            )
            evaluations = f["eval/iteration"].shape[0]
    loop = total - start_up
    rest = loop - outcome.train_seconds - evaluations * eval_s
    return {
        "overhead_iterations": iterations,
        "eval_share": evaluations * eval_s / loop,
        "runner_overhead": rest / loop,
    }


def measure_seeds(overrides: list[str], count: int, repeats: int, min_seconds: float) -> dict:
    """Seconds per iteration of one seed and of `count` seeds in one vectorised step (what
    seeds=<count> runs), timed in turn in one process."""
    cfg = compose(overrides)
    *_, single = compiled_step(cfg, [cfg.seed])
    *_, many = compiled_step(cfg, [cfg.seed + i for i in range(count)])
    (single_s, _), (many_s, _) = _median_times([single, many], repeats, min_seconds)
    return {
        "seeds": count,
        "single_step_s": single_s,
        "step_s": many_s,
        "peak_rss_gb": _peak_rss_gb(),
    }


def measure_floors(size: int, repeats: int) -> dict:
    """The float64 eigendecomposition (eigenvalues and vectors) of a random symmetric positive
    semi-definite size x size matrix, with each library that offers one: numpy (LAPACK syevd), scipy
    (syevr and syevd) and jax (compiled ahead)."""
    import numpy as np
    import scipy.linalg

    matrix = _random_gram(size)
    timed = {
        "eigh_numpy_s": lambda: np.linalg.eigh(matrix),
        "eigh_scipy_evr_s": lambda: scipy.linalg.eigh(matrix, driver="evr"),
        "eigh_scipy_evd_s": lambda: scipy.linalg.eigh(matrix, driver="evd"),
        "eigh_jax_s": _eigh_timer(size),
    }
    medians = _median_times(list(timed.values()), repeats, 0, max_seconds=60)
    return {name: seconds for name, (seconds, _) in zip(timed, medians)}


# where vectorising over seeds is measured: cheap steps, where one seed leaves the cores idle
SEED_CASES = (
    ("oscillator", "adam"),
    ("oscillator", "hig"),
    ("quantum", "adam"),
    ("multicart", "bptt"),
    ("multicart", "stable_bptt"),
    ("quantum_control", "stable_bptt"),
)
# seeds > 1 needs the float64 retry off (docs/decisions.md); the single seed is measured the same
# way
SEED_OVERRIDES = {
    "hig": ["optim.retry_float64=false"],
    "gauss_newton": ["optim.retry_float64=false"],
}


def run_seeds(scenes, count: int, repeats: int, min_seconds: float, timeout: float) -> list[dict]:
    rows = []
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
    return rows


def seeds_table(rows: list[dict]) -> str:
    lines = [
        "| scene | variant | s/iter, 1 seed | s/iter, N seeds vectorised | throughput gain (N x "
        "t1 / tN) "
        "| peak RSS (both in one process) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['task']} | {row['variant']} | {row['error']} |  |  |  |")
            continue
        gain = row["seeds"] * row["single_step_s"] / row["step_s"]
        lines.append(
            f"| {row['task']} | {row['variant']} | {_fmt(row['single_step_s'])} | "
            f"{_fmt(row['step_s'])} "
            f"(N = {row['seeds']}) | {gain:.2f}x | {row['peak_rss_gb']:.2f} GB |"
        )
    return "\n".join(lines) + "\n"


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


def _fmt(seconds: float | None) -> str:
    if seconds is None:
        return ""
    return f"{seconds * 1e3:.3g} ms" if seconds < 1 else f"{seconds:.3g} s"


def run_bench(scenes, repeats: int, min_seconds: float, timeout: float) -> list[dict]:
    rows = []
    for task in scenes:
        jobs = [
            (optim, [f"task={task}", f"optim={optim}"])
            for optim in OPTIMS
            if (task, optim) not in SKIP
        ]
        jobs += [
            (optim, [f"task={task}", f"optim={optim}", *extra])
            for optim, extra in EXTRA.get(task, [])
        ]
        for optim, overrides in jobs:
            print(f"bench: {' '.join(overrides)}", file=sys.stderr, flush=True)
            result = _subprocess(
                "variant",
                {"overrides": overrides, "repeats": repeats, "min_seconds": min_seconds},
                timeout,
            )
            if "refused" in result:
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
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | variant | s/iter | compile | peak RSS | step / bare draw+loss+grad | runner "
        "overhead |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['task']} | {row['variant']} | {row['error']} |  |  |  |  |")
            continue
        ratio_bare = f"{row['step_s'] / row['loss_grad_s']:.2f}" if "loss_grad_s" in row else ""
        overhead = ""
        if "runner_overhead" in row:
            overhead = (
                f"{100 * row['runner_overhead']:.1f}% ({row['overhead_iterations']} it; "
                "evaluations "
                f"{100 * row['eval_share']:.0f}%)"
            )
        lines.append(
            f"| {row['task']} | {row['variant']} | {_fmt(row['step_s'])} | "
            f"{_fmt(row['compile_s'])} | "
            f"{row['peak_rss_gb']:.2f} GB | {ratio_bare} | {overhead} |"
        )
    return "\n".join(lines) + "\n"


def floor_seconds(row: dict) -> float:
    """The floor of a Jacobian step: the fastest library's float64 eigendecomposition of an m x m
    matrix plus one bare forward and backward pass. The jax eigendecomposition is timed in turn with
    the step; the libraries are compared in a separate measurement, whose fastest-to-jax ratio
    scales it."""
    floors = row["floors"]
    fastest = min(value for name, value in floors.items() if name.startswith("eigh_"))
    return row["eigh_s"] * fastest / floors["eigh_jax_s"] + row["loss_grad_s"]


def jacobian_table(rows: list[dict]) -> str:
    """The Jacobian variants: the step with the chosen form of J against the per-sample form and the
    floor."""
    lines = [
        "| scene | variant | J (m x n), route | form of J | step | step, per-sample J | speed-up | "
        "eigh, in turn with the step | eigh numpy / scipy evr / scipy evd / jax | bare fwd+bwd | "
        "step / (fastest eigh + fwd+bwd) | "
        "peak RSS (per-sample J) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "jac_shape" not in row:
            continue
        floors = row["floors"]
        per_sample = row.get("per_sample_step_s")
        speed_up = f"{per_sample / row['step_s']:.2f}x" if per_sample else ""
        if "error" in floors:
            eigh, ratio = floors["error"], ""
        else:
            eigh = " / ".join(
                _fmt(floors[name])
                for name in ("eigh_numpy_s", "eigh_scipy_evr_s", "eigh_scipy_evd_s", "eigh_jax_s")
            )
            ratio = f"{row['step_s'] / floor_seconds(row):.2f}"
        peak = f"{row['peak_rss_gb']:.2f} GB" + (
            f" ({row['per_sample_peak_rss_gb']:.2f} GB)" if per_sample else ""
        )
        form = row["jacobian"].replace("per-sample: ", "per-sample (") + (
            ")" if ":" in row["jacobian"] else ""
        )
        lines.append(
            f"| {row['task']} | {row['variant']} | {row['jac_shape'][0]} x {row['jac_shape'][1]}, "
            f"{row['route']} | {form} | {_fmt(row['step_s'])} | {_fmt(per_sample)} | {speed_up} | "
            f"{_fmt(row['eigh_s'])} | {eigh} | "
            f"{_fmt(row['loss_grad_s'])} | {ratio} | {peak} |"
        )
    return "\n".join(lines) + "\n"


def machine() -> str:
    import platform

    import jax

    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax "
        f"{jax.__version__} on "
        f"{jax.devices()[0].device_kind}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m physgrad.bench", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--out", default="outputs/bench/benchmarks.md", help="markdown table (and a .json beside)"
    )
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated tasks")
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
        "--vectorised-seeds", type=int, default=8, help="N of the seeds=N throughput table"
    )
    options = parser.parse_args(argv)
    if options.seeds:
        payload = json.loads(options.seeds)
        print(
            json.dumps(
                measure_seeds(
                    payload["overrides"],
                    payload["count"],
                    payload["repeats"],
                    payload["min_seconds"],
                )
            )
        )
        return 0
    if options.variant:
        payload = json.loads(options.variant)
        print(
            json.dumps(
                measure_variant(payload["overrides"], payload["repeats"], payload["min_seconds"])
            )
        )
        return 0
    if options.floors:
        payload = json.loads(options.floors)
        print(json.dumps(measure_floors(payload["size"], payload["repeats"])))
        return 0
    scenes = [s for s in options.scenes.split(",") if s]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        print(
            f"physgrad bench: error: unknown scene {', '.join(unknown)}: choose from "
            f"{', '.join(SCENES)}",
            file=sys.stderr,
        )
        return 2
    start = time.perf_counter()
    rows = run_bench(scenes, options.repeats, options.min_seconds, options.timeout)
    seed_rows = run_seeds(
        scenes, options.vectorised_seeds, options.repeats, options.min_seconds, options.timeout
    )
    header = (
        f"# physgrad benchmark\n\nMachine: {machine()}. Reference sizes, float32 unless marked "
        "f64, "
        f"median of >= {options.repeats} steps and >= {options.min_seconds:g} s after "
        "compilation, each step "
        "timed in turn with its baselines (bare loss and gradient, the per-sample Jacobian, the "
        "eigh floor); "
        "compile: the step and the evaluation, ahead of time; peak RSS: after the step's first "
        "call; "
        f"{time.perf_counter() - start:.0f} s in all.\n\n"
    )
    out = Path(options.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    seeds_text = (
        (
            f"\nSeeds in one process (`seeds={options.vectorised_seeds}`, one vmapped step):\n\n"
            + seeds_table(seed_rows)
        )
        if seed_rows
        else ""
    )
    text = (
        header
        + table(rows)
        + "\nJacobian variants (the step above against the per-sample Jacobian and the "
        "floor):\n\n" + jacobian_table(rows) + seeds_text
    )
    out.write_text(text)
    out.with_suffix(".json").write_text(
        json.dumps({"variants": rows, "seeds": seed_rows}, indent=1, default=str)
    )
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
