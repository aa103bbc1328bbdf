"""`make bench`'s page: the measurements of physgrad.bench as markdown tables (ratios against the
baselines measured in the same run, never absolute targets) with the machine they ran on."""

from __future__ import annotations

import os

from physgrad.readout import fmt

# the benchmark's scenes and rules (make bench), here where a page can read them without JAX
SCENES = ("oscillator", "quantum", "poisson", "multicart", "quantum_control", "guidance", "ks")
OPTIMS = (
    "adam",
    "gd",
    "gauss_newton",
    "hig",
    "levenberg_marquardt",
    "kfac",
    "lbfgs",
    "ssbfgs",
    "ssbroyden",
    "muon",
    "soap",
    "psgd_kron",
    "bptt",
    "stable_bptt",
)


def duration(seconds: float | None) -> str:
    """Milliseconds below a second, else seconds, to three figures; "" for None."""
    if seconds is None:
        return ""
    return f"{fmt(seconds * 1e3)} ms" if seconds < 1 else f"{fmt(seconds)} s"


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | variant | s/iter | compile | peak RSS | step / bare draw+loss+grad | runner "
        "overhead |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "refused" in row:  # refused_table
            continue
        if "error" in row:
            lines.append(f"| {row['task']} | {row['variant']} | {row['error']} |  |  |  |  |")
            continue
        ratio_bare = f"{row['step_s'] / row['loss_grad_s']:.2f}" if "loss_grad_s" in row else ""
        overhead = ""
        if "runner_overhead" in row:
            overhead = (
                f"{100 * row['runner_overhead']:.1f}% ({row['overhead_iterations']} it; "
                f"evaluations {100 * row['eval_share']:.0f}%)"
            )
        lines.append(
            f"| {row['task']} | {row['variant']} | {duration(row['step_s'])} | "
            f"{duration(row['compile_s'])} | "
            f"{row['peak_rss_gb']:.2f} GB | {ratio_bare} | {overhead} |"
        )
    return "\n".join(lines) + "\n"


def refused_table(rows: list[dict]) -> str:
    """The variants a scene refuses at its reference size, with the reason each gave ("" if
    none)."""
    refused = [row for row in rows if "refused" in row]
    if not refused:
        return ""
    lines = ["| scene | variant | why |", "|---|---|---|"]
    lines += [
        f"| {row['task']} | {row['variant']} | {row['refused'].replace('|', '/')} |"
        for row in refused
    ]
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
        "step / (fastest eigh + fwd+bwd) | peak RSS (per-sample J) |",
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
                duration(floors[name])
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
            f"{row['route']} | {form} | {duration(row['step_s'])} | {duration(per_sample)} | "
            f"{speed_up} | {duration(row['eigh_s'])} | {eigh} | "
            f"{duration(row['loss_grad_s'])} | {ratio} | {peak} |"
        )
    return "\n".join(lines) + "\n"


def machine() -> str:
    import platform

    import jax

    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax "
        f"{jax.__version__} on {jax.devices()[0].device_kind}"
    )


def seeds_table(rows: list[dict]) -> str:
    lines = [
        "| scene | variant | s/iter, 1 seed | s/iter, N seeds vectorised | throughput gain (N x "
        "t1 / tN) | peak RSS (both in one process) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['task']} | {row['variant']} | {row['error']} |  |  |  |")
            continue
        gain = row["seeds"] * row["single_step_s"] / row["step_s"]
        lines.append(
            f"| {row['task']} | {row['variant']} | {duration(row['single_step_s'])} | "
            f"{duration(row['step_s'])} "
            f"(N = {row['seeds']}) | {gain:.2f}x | {row['peak_rss_gb']:.2f} GB |"
        )
    return "\n".join(lines) + "\n"


def page(
    rows: list[dict],
    seed_rows: list[dict],
    described: str,
    repeats: int,
    min_seconds: float,
    seconds: float,
    vectorised_seeds: int,
) -> str:
    """The whole page: what was measured and how (on the machine `described`, in `seconds` in
    all), the variants' table, the Jacobian variants' table and, where measured, the seeds'."""
    header = (
        f"# physgrad benchmark\n\nMachine: {described}. Reference sizes, float32 unless marked "
        f"f64, median of >= {repeats} steps and >= {min_seconds:g} s after compilation, each step "
        "timed in turn with its baselines (bare loss and gradient, the per-sample Jacobian, the "
        "eigh floor); "
        "compile: the step and the evaluation, ahead of time; peak RSS: after the step's first "
        f"call; {seconds:.0f} s in all.\n\n"
    )
    seeds_text = (
        (
            f"\nSeeds in one process (`seeds={vectorised_seeds}`, one vmapped step):\n\n"
            + seeds_table(seed_rows)
        )
        if seed_rows
        else ""
    )
    refused = refused_table(rows)
    return (
        header
        + table(rows)
        + "\nJacobian variants (the step above against the per-sample Jacobian and the "
        "floor):\n\n"
        + jacobian_table(rows)
        + (f"\nRefused at the reference sizes:\n\n{refused}" if refused else "")
        + seeds_text
    )
