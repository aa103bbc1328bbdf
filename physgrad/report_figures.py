"""The report's figures, which compare runs: one panel per scene, one line or set of points per
group of runs in its style (plots.group_styles: the same in every figure); a line is the median over
the group's seeds with markers at the evaluations and the min-max band. Written as PNG and PDF
through matplotlib's Agg backend."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from physgrad.cost_figures import plot_tradeoff, plot_unroll  # noqa: E402
from physgrad.plots import (  # noqa: E402
    by_label,
    design_styles,
    group_styles,
    legend_outside,
    limit_to,
    literal,
    log_axis,
    save_figure,
    styles_for,
)
from physgrad.readout import fmt  # noqa: E402
from physgrad.results import Run, natural_key  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

MAX_MARKERS = 40  # markers per curve at most (evaluations beyond that are thinned out evenly)
FIGURES = ("loss_vs_time", "loss_vs_iteration", "tradeoff", "unroll")
X_LABELS = {
    "wall_time": "training time, measured clock [s]",
    "calibrated_time": "training time, calibrated clock [s]",
}


def write_figures(
    runs: list[Run],
    out: Path,
    note: str,
    logx: str,
    thresholds: dict[str, float],
    design: dict | None = None,
) -> list[str]:
    """The report's figures (PNG and PDF) in one style per group across all of them: by variant
    and tuning study where the design (label -> (variant, study)) is given (design_styles), else
    group_styles; the PNG names written."""
    styles = (
        design_styles(design) if design else group_styles(run.label or run.variant for run in runs)
    )
    plot_comparison(runs, out / "loss_vs_time", "wall_time", note, logx, styles)
    plot_comparison(runs, out / "loss_vs_iteration", "iteration", note, logx, styles)
    figures = [f"{name}.png" for name in FIGURES[:2]]
    calibrated = [run for run in runs if "calibrated_time" in run.eval]
    if calibrated:
        plot_comparison(
            calibrated, out / "loss_vs_calibrated_time", "calibrated_time", note, logx, styles
        )
    plot_tradeoff(runs, out / "tradeoff", note, styles, thresholds)
    figures.append("tradeoff.png")
    if calibrated:
        figures.append("loss_vs_calibrated_time.png")
    if plot_unroll(runs, out / "unroll", note, styles):
        figures.append("unroll.png")
    return figures


def median_band(
    curves: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Median and min-max of several (x, loss) curves at every x where one of them was evaluated, up
    to the shortest curve's end (between a curve's evaluations interpolated in log(loss)). The
    median is that of the losses themselves, as the tables report it (for an even count the mean of
    the middle two, not their geometric mean)."""
    end = min(x[-1] for x, _ in curves)
    grid = np.unique(np.concatenate([x[x <= end] for x, _ in curves]))
    values = 10 ** np.array(
        [np.interp(grid, x, np.log10(np.maximum(y, 1e-300))) for x, y in curves]
    )
    at_evaluations = [np.isin(grid, x) for x, _ in curves]
    for row, (x, y), exact in zip(
        values, curves, at_evaluations
    ):  # no round trip through log10 where measured
        row[exact] = y[np.searchsorted(x, grid[exact])]
    return grid, np.median(values, axis=0), values.min(axis=0), values.max(axis=0)


def _short_reason(reason: str) -> str:
    """'loss became nan at iteration 12 (loss); the SVD ...' -> 'loss became nan at iteration
    12'."""
    return reason.split(" (")[0].split(";")[0]


def use_log_x(ends: list[float], logx: str) -> bool:
    """auto: when the curves' ends (median per group) span a decade or more, so that a fast method
    is not a vertical line at the left of a slow one's curve."""
    if logx != "auto":
        return logx == "on"
    positive = [end for end in ends if end > 0]
    return len(positive) > 1 and max(positive) / min(positive) >= 10


def _panels(
    count: int, width: float = 5.5, height: float = 4.0, max_columns: int = 4
) -> tuple[Figure, list[Axes]]:
    columns = max(1, min(count, max_columns))
    rows = max(1, -(-count // columns))
    # at least 8 inches wide, so that the note above the panels fits
    fig, axes = plt.subplots(
        rows, columns, figsize=(max(8.0, width * columns), height * rows), squeeze=False
    )
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def plot_comparison(
    runs: list[Run],
    path: str | Path,
    x_key: str = "wall_time",
    note: str = "",
    logx: str = "auto",
    styles: dict | None = None,
) -> None:
    """Held-out loss against training time (or iteration), one panel per scene, one line per group
    in its style (group_styles: the same in every figure): the median over its seeds (the tables'
    statistic) with a marker at each evaluation and the min-max band; diverged runs each on their
    own, dashed, ending in a cross labelled with the reason, or in a triangle at the top edge where
    they left the range of the other curves (the y axis is fitted to the runs that did not diverge).
    A run started from another's network begins where that run ended. The x axis is symmetric-log
    (linear around 0, so the initial evaluation stays visible) where use_log_x says so. Legends sit
    right of the panels."""
    styles = styles_for(runs, styles)
    by_scene = _curves_by_scene(runs, x_key)
    scenes = sorted(by_scene, key=natural_key) or ["(no runs with evaluations)"]
    fig, axes = _panels(len(scenes))
    for ax, scene in zip(axes, scenes):
        groups = by_scene.get(scene, {})
        ends, smallest, banded = _draw_medians(ax, groups, styles)
        ax.set_title(literal(scene), fontsize=10)
        ax.set_xlabel(X_LABELS.get(x_key, "iteration"))
        ax.set_ylabel("test loss")
        log_axis(ax)
        if smallest and use_log_x(ends, logx):
            ax.set_xscale("symlog", linthresh=min(smallest))
            ax.set_xlim(left=0)
        # after the scales: where a diverged run's note goes depends on where its end is drawn
        _draw_diverged(ax, groups, styles)
        ax.grid(True, which="both", alpha=0.3)
        if groups:
            legend_outside(
                ax, title="line: median over n seeds" + (", band: min-max" if banded else "")
            )
    save_figure(fig, path, note)


def _curves_by_scene(runs: list[Run], x_key: str) -> dict[str, dict[str, dict[str, list]]]:
    """scene -> group label -> {"ok": [...], "diverged": [...]} of (x, finite losses, reason) per
    run with a finite evaluation."""
    by_scene = defaultdict(lambda: defaultdict(lambda: {"ok": [], "diverged": []}))
    for run in runs:
        loss = run.eval.get("loss")
        if loss is not None and loss.size and np.isfinite(loss).any():
            finite = np.isfinite(loss)
            kind = "diverged" if run.attrs.get("status") == "diverged" else "ok"
            curve = (
                run.eval[x_key][finite] + run.offset(x_key),
                loss[finite],
                run.attrs.get("reason") or "",
            )
            by_scene[run.scene][run.label or run.variant][kind].append(curve)
    return by_scene


def _draw_medians(ax: Axes, groups: dict, styles: dict) -> tuple[list[float], list[float], bool]:
    """Each group's median with its min-max band (a group whose runs all diverged: its legend entry
    alone), and the y axis fitted to them; (each group's median end, the smallest positive x of
    every run, whether a band was drawn)."""
    ends, smallest, banded, shown = [], [], False, []
    for label, kinds in by_label(groups):
        curves = kinds["ok"]
        style = styles.get(label, {})
        text = f"{label} (n={len(curves)}" + (
            f", {len(kinds['diverged'])} diverged)" if kinds["diverged"] else ")"
        )
        if curves:
            grid, median, low, high = median_band([(x, y) for x, y, _ in curves])
            every = max(1, len(grid) // MAX_MARKERS)
            ax.plot(grid, median, ms=3, markevery=every, label=literal(text), **style)
            if len(curves) > 1:
                ax.fill_between(grid, low, high, color=style.get("color"), alpha=0.2, lw=0)
                banded = True
            shown += [*low, *high]
            ends.append(float(np.median([x[-1] for x, _, _ in curves])))
            smallest += [x[x > 0].min() for x, _, _ in curves if (x > 0).any()]
        elif kinds["diverged"]:
            ax.plot([], [], lw=0.8, label=literal(text), **{**style, "linestyle": "--"})
        for x, _, _ in kinds["diverged"]:
            smallest += [x[x > 0].min()] if (x > 0).any() else []
    if not shown:  # every run diverged: fit the axis to where they were finite
        shown = [v for kinds in groups.values() for _, y, _ in kinds["diverged"] for v in y]
    limit_to(ax, shown)
    return ends, smallest, banded


def _draw_diverged(ax: Axes, groups: dict, styles: dict) -> None:
    """Each diverged run dashed, ending in a cross (or a triangle at the top edge where it left the
    axis) numbered beside it, and the numbered reasons listed under the axes: notes drawn among
    the curves overprinted each other, the curves and the tick labels once there were many
    groups."""
    top, notes = ax.get_ylim()[1], []
    for label, kinds in by_label(groups):
        color = styles.get(label, {}).get("color")
        for x, y, reason in kinds["diverged"]:
            ax.plot(x, y, "--", lw=0.8, color=color)
            above = y[-1] > top
            ax.plot(
                x[-1:],
                [min(y[-1], top)],
                "^" if above else "x",
                ms=7,
                color=color,
                clip_on=False,
            )
            # runs that diverge early end at nearly the same point: their numbers stack
            same_end = sum(1 for end, _ in notes if end == (x[-1], min(y[-1], top)))
            ax.annotate(
                str(len(notes) + 1),
                (x[-1], min(y[-1], top)),
                xytext=(4, 2 - 8 * same_end),
                textcoords="offset points",
                fontsize=7,
                color=color,
                annotation_clip=False,
            )
            note = f"{len(notes) + 1}: {label}: {_short_reason(reason)}"
            notes.append(
                ((x[-1], min(y[-1], top)), note + (f" (loss {fmt(float(y[-1]))})" if above else ""))
            )
    if notes:
        shown = [note for _, note in notes[:MAX_DIVERGED_NOTES]]
        if len(notes) > MAX_DIVERGED_NOTES:
            shown.append(f"and {len(notes) - MAX_DIVERGED_NOTES} more (report.md lists every run)")
        # under the x axis's label (the figure is saved with its whole extent)
        ax.annotate(
            literal("diverged:\n" + "\n".join(shown)),
            (0, 0),
            xycoords="axes fraction",
            xytext=(0, -34),
            textcoords="offset points",
            va="top",
            fontsize=7,
            color="dimgray",
            annotation_clip=False,
        )


MAX_DIVERGED_NOTES = 8  # reasons listed under a panel; the rest are counted
