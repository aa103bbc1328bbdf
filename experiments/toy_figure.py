"""The PBDL book's figure of the badly scaled toy, from the runs of
conf/experiment/toy_scaling.yaml: toy_book.png, one row per lambda, three panels each (the book's):
- the held-out loss against training wall-clock (median over seeds, log scale);
- the hidden neurons' activations over a grid of inputs: their mean magnitude and the share of
  them saturated (beyond 0.99 in magnitude), against training time (the calibrated clock where the
  runs had it, as a study's budget; seeds trained together share one measured clock);
- the physical output (y1, lambda y2) at the probe input x = 0.3 in y-space, its path over training
  from the initial network (light grey) to the end, and the target yhat (black).
and toy_book.md: each variant's final loss, spread and share of saturated neurons per lambda.
What the figure and the table show is one small table (`panels`: the median curves on a grid, the
probe seed's path, the medians at the end), kept as evidence (docs/evidence/toy_book.csv) so that
the figure regenerates without the runs.

Usage: python experiments/toy_figure.py RUNS_FOLDER [OUT_FOLDER] [--keep CSV]
       python experiments/toy_figure.py --evidence CSV FIGURE (the figure from the kept table)
"""

from __future__ import annotations

import io
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd

from physgrad.errors import UserError
from physgrad.files import read_own_file, replace_file, write_figure, write_text
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
    if not rows:
        return np.full(grid.shape, np.nan)
    with warnings.catch_warnings():  # past every run's end the median is NaN, as meant
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(rows, axis=0)


GRID = 80  # points of a median curve, and of the probe's path, on the clock


def panels(table: dict) -> pd.DataFrame:
    """What the figure and the table show, per lambda and variant: kind "curve", the medians over
    seeds on a grid of the clock (loss, mean |h|, share saturated); kind "path", the probe output
    (y1, lambda y2) of the lowest seed at each evaluation; kind "final", the medians over seeds of
    the last evaluation (loss, spread, saturated; a diverged run's last)."""
    rows = []
    for scale in sorted(table, reverse=True):
        clock = clock_of([r for runs in table[scale].values() for r in runs])
        end = max(r.eval[clock][-1] for runs in table[scale].values() for r in runs)
        grid = np.linspace(0.0, end, GRID)
        for variant, runs in sorted(table[scale].items()):
            about = {
                "scale": scale,
                "variant": variant,
                "seeds": len(runs),
                "diverged": sum(r.attrs.get("status") == "diverged" for r in runs),
                "clock": clock,
            }
            curves = {
                name: on_grid(runs, lambda r, n=name: r.eval[n], grid, clock)
                for name in ("loss", "hidden_magnitude", "hidden_saturated")
            }
            rows += [
                {**about, "kind": "curve", "t": t, **{k: v[i] for k, v in curves.items()}}
                for i, t in enumerate(grid)
            ]
            first = min(runs, key=lambda r: int(r.attrs.get("seed", 0)))
            # the path at the grid's instants up to the run's end (its evaluations number
            # hundreds): the figure's shape, a table of kilobytes
            when = first.eval[clock]
            on = [0.0, *grid[(grid > 0) & (grid < when[-1])], when[-1]]
            rows += [
                {**about, "kind": "path", "seed": int(first.attrs.get("seed", 0)), "y1": a, "y2": b}
                for a, b in zip(
                    np.interp(on, when, first.eval["probe_y1"]),
                    np.interp(on, when, first.eval["probe_y2"]),
                )
            ]
            final = np.median(
                [
                    [
                        r.final("eval"),
                        r.final("eval", "hidden_spread"),
                        r.final("eval", "hidden_saturated"),
                    ]
                    for r in runs
                ],
                axis=0,
            )
            rows.append(
                {
                    **about,
                    "kind": "final",
                    "loss": final[0],
                    "hidden_spread": final[1],
                    "hidden_saturated": final[2],
                }
            )
    return pd.DataFrame(rows)


COLUMNS = {  # the kept table's columns and their types: a table from elsewhere is data, checked
    "scale": float,
    "variant": str,
    "seeds": int,
    "diverged": int,
    "clock": str,
    "kind": str,
    "t": float,
    "loss": float,
    "hidden_magnitude": float,
    "hidden_saturated": float,
    "hidden_spread": float,
    "seed": float,
    "y1": float,
    "y2": float,
}
KEPT_LIMIT = 1 << 20  # the kept table is about 60 kB


def read_panels(path: Path) -> pd.DataFrame:
    """The kept table (docs/evidence/toy_book.csv), checked; UserError (one line) otherwise."""
    try:
        frame = pd.read_csv(io.BytesIO(read_own_file(path, KEPT_LIMIT)), dtype=str)
    except (OSError, ValueError) as error:
        why = f"{path}: not a kept toy table ({error}): give docs/evidence/toy_book.csv"
        raise UserError(why) from None
    missing = sorted(set(COLUMNS) - set(frame.columns))
    kinds = set(frame.get("kind", pd.Series(dtype=str)))
    if missing or not kinds <= {"curve", "path", "final"} or not {"curve", "final"} <= kinds:
        raise UserError(
            f"{path}: not a kept toy table (columns missing: {missing}, kinds {sorted(kinds)})"
        )
    try:
        typed = {
            c: frame[c].astype(float) if t is not str else frame[c].fillna("")
            for c, t in COLUMNS.items()
        }
    except ValueError as error:
        raise UserError(f"{path}: a value that is not a number ({str(error)[:80]})") from None
    frame = pd.DataFrame(typed)
    if not set(frame["clock"]) <= set(CLOCK_LABELS) or not set(frame["variant"]) <= set(COLOURS):
        raise UserError(f"{path}: an unknown clock or variant: not the toy's table")
    return frame


def plot(frame: pd.DataFrame, path: Path, note: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = sorted(set(frame["scale"]), reverse=True)
    figure, axes = plt.subplots(len(scales), 3, figsize=(13, 3.6 * len(scales)), squeeze=False)
    target = np.array([np.sin(6 * PROBE), np.cos(9 * PROBE)])
    for row, scale in zip(axes, scales):
        at = frame[frame["scale"] == scale]
        clock = at["clock"].iloc[0]
        seed = "-"
        for variant in sorted(set(at["variant"])):
            mine = at[at["variant"] == variant]
            colour = COLOURS.get(variant)
            curve, path_ = mine[mine["kind"] == "curve"], mine[mine["kind"] == "path"]
            seeds, diverged = int(mine["seeds"].iloc[0]), int(mine["diverged"].iloc[0])
            label = f"{variant} ({seeds} seeds" + (f", {diverged} diverged)" if diverged else ")")
            row[0].plot(curve["t"], curve["loss"], color=colour, label=label)
            row[1].plot(curve["t"], curve["hidden_magnitude"], color=colour, label=variant)
            row[1].plot(curve["t"], curve["hidden_saturated"], "--", color=colour)
            if len(path_):
                seed = int(path_["seed"].iloc[0])
                row[2].plot(path_["y1"], path_["y2"], ".-", color=colour, ms=3, lw=0.8)
                row[2].plot(path_["y1"].iloc[0], path_["y2"].iloc[0], "o", color="0.8")
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
        row[2].set_title(f"output at x = {PROBE} (seed {seed})")
        row[2].legend(fontsize=8)
    if note:
        figure.suptitle(note, fontsize=9)
    figure.tight_layout()
    write_figure(figure, path, dpi=110)
    plt.close(figure)


def summary(frame: pd.DataFrame) -> str:
    """Per lambda and variant: the diverged runs, and medians over seeds of the last held-out loss,
    spread of the activations and share of saturated values (a diverged run's last evaluation)."""
    lines = [
        "| lambda | variant | seeds | diverged | held-out loss | activation spread | saturated |",
        "|---|---|---|---|---|---|---|",
    ]
    final = frame[frame["kind"] == "final"].sort_values(
        ["scale", "variant"], ascending=[False, True]
    )
    for _, r in final.iterrows():
        lines.append(
            f"| {r['scale']:g} | {r['variant']} | {int(r['seeds'])} | {int(r['diverged'])} | "
            f"{fmt(r['loss'])} | {r['hidden_spread']:.2f} | {r['hidden_saturated']:.0%} |"
        )
    return "\n".join(lines) + "\n"


def write(
    folders: list[Path], out: Path, note: str = "", keep: Path | None = None
) -> tuple[list[str], str]:
    """Draw toy_book.png and write toy_book.md into out from the runs under the folders (and the
    table they are drawn from into keep); returns (figure names, the table)."""
    table = collect(folders)
    out.mkdir(parents=True, exist_ok=True)
    if not table:
        return [], "no completed runs of the book's toy\n"
    frame = panels(table)
    if keep is not None:
        replace_file(keep, frame.to_csv(index=False, float_format="%.6g").encode())
    plot(frame, out / "toy_book.png", note)
    text = summary(frame)
    write_text(
        out / "toy_book.md",
        "# The badly scaled toy, as the PBDL book shows it\n\n"
        + (f"{note}\n\n" if note else "")
        + text,
    )
    return ["toy_book.png"], text


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "--evidence":
        try:
            frame = read_panels(Path(argv[1]))
        except UserError as error:
            print(f"toy_figure: error: {error}", file=sys.stderr)
            return 2
        plot(frame, Path(argv[2]), "")
        print(summary(frame))
        return 0
    keep = None
    if len(argv) >= 2 and argv[-2] == "--keep":
        keep, argv = Path(argv[-1]), argv[:-2]
    if len(argv) not in (1, 2):
        print(__doc__.split("\n\n")[-1], file=sys.stderr)
        return 2
    folder = Path(argv[0])
    _, text = write([folder], Path(argv[1]) if len(argv) == 2 else folder, keep=keep)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
