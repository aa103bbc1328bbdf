"""The PBDL book's figure of the badly scaled toy, from the runs of
conf/experiment/toy_scaling.yaml: toy_book.png, one row per lambda, three panels each (the book's):
- the held-out loss against training wall-clock (median over seeds, log scale);
- the hidden neurons' activations over a grid of inputs: their mean magnitude and the share of
  them saturated (beyond 0.99 in magnitude), against training time (the calibrated clock where the
  runs had it, as a study's budget; seeds trained together share one measured clock);
- the physical output (y1, lambda y2) at the probe input x = 0.3 in y-space, its path over training
  from the initial network (light grey) to the end, and the target yhat (black).
and toy_book.md: each variant's final loss, spread and share of saturated neurons per lambda.

Usage: python experiments/toy_figure.py RUNS_FOLDER [OUT_FOLDER]
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from physgrad.files import write_figure, write_text
from physgrad.readout import config_row, fmt
from physgrad.results import Run, find_results, read_run

PROBE = 0.3  # physgrad.tasks.toy.PROBE, repeated so that this script reads results without JAX
COLOURS = {"adam": "tab:blue", "gauss_newton": "tab:red", "hig": "tab:green"}


def collect(folders: list[Path]) -> dict[float, dict[str, list[Run]]]:
    """{lambda: {variant: [runs]}} of the toy's completed or diverged runs that hold the
    activation metrics."""
    table: dict[float, dict[str, list[Run]]] = defaultdict(lambda: defaultdict(list))
    for path in find_results(folders):
        run = read_run(path)
        if run.attrs.get("task") != "toy" or "hidden_spread" not in run.eval:
            continue
        if run.attrs.get("status") not in ("completed", "diverged"):
            continue
        table[float(config_row(run)["task.scale"])][run.variant].append(run)
    return table


def clock_of(runs: list[Run]) -> str:
    """The time axis every run has: the calibrated clock where all ran on it (a study's budget:
    seeds trained together share the measured clock, so it counts their job, not a run), else
    the measured one."""
    return "calibrated_time" if all("calibrated_time" in r.eval for r in runs) else "wall_time"


CLOCK_LABELS = {
    "calibrated_time": "training time, calibrated clock (s)",
    "wall_time": "training wall-clock (s)",
}


def on_grid(runs: list[Run], values, grid: np.ndarray, clock: str = "wall_time") -> np.ndarray:
    """The median over runs of values(run), each interpolated onto a common time grid on the
    clock (NaN past a run's end)."""
    rows = [
        np.interp(grid, run.eval[clock], values(run), right=np.nan)
        for run in runs
        if run.eval[clock].size
    ]
    return np.nanmedian(rows, axis=0) if rows else np.full(grid.shape, np.nan)


def plot(table: dict, path: Path, note: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = sorted(table, reverse=True)
    figure, axes = plt.subplots(len(scales), 3, figsize=(13, 3.6 * len(scales)), squeeze=False)
    target = np.array([np.sin(6 * PROBE), np.cos(9 * PROBE)])
    for row, scale in zip(axes, scales):
        clock = clock_of([r for runs in table[scale].values() for r in runs])
        end = max(r.eval[clock][-1] for runs in table[scale].values() for r in runs)
        grid = np.linspace(0.0, end, 200)
        for variant, runs in sorted(table[scale].items()):
            colour = COLOURS.get(variant)
            loss = on_grid(runs, lambda r: r.eval["loss"], grid, clock)
            diverged = sum(r.attrs.get("status") == "diverged" for r in runs)
            label = f"{variant} ({len(runs)} seeds" + (
                f", {diverged} diverged)" if diverged else ")"
            )
            row[0].plot(grid, loss, color=colour, label=label)
            mean = on_grid(runs, lambda r: r.eval["hidden_magnitude"], grid, clock)
            saturated = on_grid(runs, lambda r: r.eval["hidden_saturated"], grid, clock)
            row[1].plot(grid, mean, color=colour, label=variant)
            row[1].plot(grid, saturated, "--", color=colour)
            first = min(runs, key=lambda r: int(r.attrs.get("seed", 0)))
            row[2].plot(
                first.eval["probe_y1"], first.eval["probe_y2"], ".-", color=colour, ms=3, lw=0.8
            )
            row[2].plot(first.eval["probe_y1"][0], first.eval["probe_y2"][0], "o", color="0.8")
        row[0].set_yscale("log")
        row[0].set(xlabel=CLOCK_LABELS[clock], ylabel="held-out loss")
        row[0].set_title(f"lambda = {scale:g}: loss (median over seeds)")
        row[0].legend(fontsize=8)
        row[1].set(xlabel=CLOCK_LABELS[clock], ylabel="hidden activations", ylim=(-0.05, 1.05))
        row[1].set_title("mean |h| (solid), share saturated, |h| > 0.99 (dashed)")
        row[2].plot(*target, "ko", ms=8, label="target")
        # a window around the target: a step that jumps far out shows as a line leaving it
        row[2].set(
            xlabel="y1",
            ylabel="lambda y2",
            xlim=(target[0] - 1.5, target[0] + 1.5),
            ylim=(target[1] - 1.5, target[1] + 1.5),
        )
        row[2].set_title(f"output at x = {PROBE} (seed {first.attrs.get('seed')})")
        row[2].legend(fontsize=8)
    if note:
        figure.suptitle(note, fontsize=9)
    figure.tight_layout()
    write_figure(figure, path, dpi=110)
    plt.close(figure)


def summary(table: dict) -> str:
    """Per lambda and variant: the diverged runs, and medians over seeds of the last held-out loss,
    spread of the activations and share of saturated values (a diverged run's last evaluation)."""
    lines = [
        "| lambda | variant | seeds | diverged | held-out loss | activation spread | saturated |",
        "|---|---|---|---|---|---|---|",
    ]
    for scale in sorted(table, reverse=True):
        for variant, runs in sorted(table[scale].items()):
            final = [
                (
                    r.final("eval"),
                    r.final("eval", "hidden_spread"),
                    r.final("eval", "hidden_saturated"),
                )
                for r in runs
            ]
            loss, width, saturated = np.median(np.array(final), axis=0)
            diverged = sum(r.attrs.get("status") == "diverged" for r in runs)
            lines.append(
                f"| {scale:g} | {variant} | {len(runs)} | {diverged} | {fmt(loss)} | {width:.2f} | "
                f"{saturated:.0%} |"
            )
    return "\n".join(lines) + "\n"


def write(folders: list[Path], out: Path, note: str = "") -> tuple[list[str], str]:
    """Draw toy_book.png and write toy_book.md into out from the runs under the folders; returns
    (figure names, the table)."""
    table = collect(folders)
    out.mkdir(parents=True, exist_ok=True)
    if not table:
        return [], "no completed runs of the book's toy\n"
    plot(table, out / "toy_book.png", note)
    text = summary(table)
    write_text(
        out / "toy_book.md",
        "# The badly scaled toy, as the PBDL book shows it\n\n"
        + (f"{note}\n\n" if note else "")
        + text,
    )
    return ["toy_book.png"], text


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        print(__doc__.split("\n\n")[-1], file=sys.stderr)
        sys.exit(2)
    folder = Path(sys.argv[1])
    images, text = write([folder], Path(sys.argv[2]) if len(sys.argv) == 3 else folder)
    print(text)
