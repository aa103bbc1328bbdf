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
from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator  # noqa: E402

from physgrad.plots import (  # noqa: E402
    design_styles,
    group_styles,
    legend_outside,
    limit_to,
    literal,
    log_axis,
    save_figure,
    styles_for,
)
from physgrad.readout import loss_at, targets, time_to_target  # noqa: E402
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


def _by_label(groups: dict) -> list[tuple[str, dict]]:
    return sorted(groups.items(), key=lambda item: natural_key(item[0]))


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
    for label, kinds in _by_label(groups):
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
    for label, kinds in _by_label(groups):
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
                ((x[-1], min(y[-1], top)), note + (f" (loss {y[-1]:.3g})" if above else ""))
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


def plot_tradeoff(
    runs: list[Run],
    path: str | Path,
    note: str = "",
    styles: dict | None = None,
    thresholds: dict | None = None,
) -> None:
    """Error against run time, per scene, one point per seed in its group's style: the final test
    loss against the seconds per iteration (top) and against the training seconds until the test
    loss first reached the scene's threshold (bottom; readout.targets: the best group's median, so a
    budget does not set the x value); a diverged seed as a triangle at the top edge of the top panel
    at its seconds per iteration."""
    styles = styles_for(runs, styles)
    limits = targets(runs) if thresholds is None else thresholds
    by_scene = _tradeoff_points(runs, limits)
    scenes = sorted(by_scene, key=natural_key) or ["(no finished runs)"]
    # scenes per row; each scene is a pair of panels stacked vertically
    columns = min(len(scenes), 4)
    rows = -(-len(scenes) // columns)
    fig, axes = plt.subplots(
        2 * rows, columns, figsize=(max(8.0, 5.0 * columns), 7.0 * rows), squeeze=False
    )
    for ax in axes[:, :].flat:
        ax.set_visible(False)
    for index, scene in enumerate(scenes):
        top, bottom = (
            axes[2 * (index // columns), index % columns],
            axes[2 * (index // columns) + 1, index % columns],
        )
        groups = _by_label(by_scene.get(scene, {}))
        _draw_tradeoff_points(top, bottom, groups, styles)
        _tradeoff_axes(top, bottom, groups, limits.get(scene, np.nan))
        top.set_title(literal(scene), fontsize=10)
        if groups:
            legend_outside(top, title="one point per seed; \u25b2 diverged")
    save_figure(fig, path, note)


def _tradeoff_points(runs: list[Run], limits: dict) -> dict[str, dict[str, dict[str, list]]]:
    """scene -> group label -> {"ok": [(s/iter, time to the threshold, final test loss) per
    completed run], "diverged": [s/iter per diverged run]}."""
    by_scene = defaultdict(lambda: defaultdict(lambda: {"ok": [], "diverged": []}))
    for run in runs:
        final, per_iter = loss_at(run), run.seconds_per_iteration
        if not np.isfinite(per_iter):
            continue
        if run.attrs.get("status") == "completed" and np.isfinite(final):
            limit = limits.get(run.scene, np.nan)
            reach = time_to_target(run, limit)
            by_scene[run.scene][run.label or run.variant]["ok"].append((per_iter, reach, final))
        elif run.attrs.get("status") == "diverged":
            by_scene[run.scene][run.label or run.variant]["diverged"].append(per_iter)
    return by_scene


def _draw_tradeoff_points(
    top: Axes, bottom: Axes, groups: list[tuple[str, dict]], styles: dict
) -> None:
    """One point per completed seed in both panels (bottom: those that reached the threshold), the
    y axes fitted to them, and the diverged seeds as triangles at the top panel's upper edge."""
    for label, kinds in groups:
        style = {k: v for k, v in styles.get(label, {}).items() if k != "linestyle"}
        points = np.array(kinds["ok"], float).reshape(-1, 3)
        diverged = f", {len(kinds['diverged'])} diverged" if kinds["diverged"] else ""
        top.plot(
            points[:, 0],
            points[:, 2],
            linestyle="none",
            label=literal(f"{label} (n={len(points)}{diverged})"),
            **style,
        )
        reached = np.isfinite(points[:, 1])
        bottom.plot(points[reached, 1], points[reached, 2], linestyle="none", **style)
    limit_to(top, [p[2] for _, kinds in groups for p in kinds["ok"]])
    limit_to(bottom, [p[2] for _, kinds in groups for p in kinds["ok"]])
    edge = top.get_ylim()[1]
    for label, kinds in groups:
        for per_iter in kinds["diverged"]:
            top.plot(
                [per_iter],
                [edge],
                "^",
                ms=7,
                color=styles.get(label, {}).get("color"),
                clip_on=False,
            )


def _tradeoff_axes(top: Axes, bottom: Axes, groups: list[tuple[str, dict]], limit: float) -> None:
    """How many completed runs reached the threshold, and both panels' axes (log where the values
    allow it) and labels."""
    finished = [p for _, kinds in groups for p in kinds["ok"]]
    reached = sum(np.isfinite(p[1]) for p in finished)
    bottom.text(
        0.98,
        0.96,
        f"reached by {reached} of {len(finished)} completed runs",
        transform=bottom.transAxes,
        ha="right",
        va="top",
        fontsize=7,
        color="dimgray",
    )
    for ax, label in (
        (top, "seconds per iteration"),
        (
            bottom,
            f"training seconds to test loss {limit:.3g}"
            if np.isfinite(limit)
            else "training seconds to the threshold (none)",
        ),
    ):
        ax.set_visible(True)
        xs = np.concatenate(
            [np.asarray(line.get_xdata(), float) for line in ax.get_lines()] or [np.empty(0)]
        )
        if (
            xs.size and xs.min() > 0
        ):  # (a threshold reached at the start has time 0: a linear axis then)
            log_axis(ax, "x")
        if xs.size:
            log_axis(ax, "y")
        ax.set_xlabel(label)
        ax.set_ylabel("final test loss")
        ax.grid(True, which="both", alpha=0.3)


def plot_unroll(
    runs: list[Run], path: str | Path, note: str = "", styles: dict | None = None
) -> bool:
    """Final test loss and seconds per iteration against the unroll length, per task and group
    (median over seeds, with min-max bars); False (and no file) when no task has runs at several
    unroll lengths."""
    by_scene = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for run in runs:
        unroll = run.attrs.get("unroll")
        if unroll is not None:
            scene = " ".join(word for word in run.scene.split() if not word.startswith("unroll="))
            # diverged: no loss
            final = loss_at(run) if run.attrs.get("status") == "completed" else np.nan
            by_scene[scene][run.label or run.variant][int(unroll)].append(
                (final, run.seconds_per_iteration)
            )
    scenes = sorted(
        scene
        for scene, groups in by_scene.items()
        if len({u for lengths in groups.values() for u in lengths}) > 1
    )
    if not scenes:
        return False
    styles = styles_for(runs, styles)
    fig, axes = plt.subplots(
        2, len(scenes), figsize=(max(8.0, 5 * len(scenes)), 7.5), squeeze=False
    )
    for column, scene in enumerate(scenes):
        every_unroll = sorted({u for lengths in by_scene[scene].values() for u in lengths})
        for label, lengths in sorted(
            by_scene[scene].items(), key=lambda item: natural_key(item[0])
        ):
            unrolls = sorted(lengths)
            for row in (0, 1):
                values = [np.array([v[row] for v in lengths[u]], float) for u in unrolls]
                median = np.array(
                    [np.nanmedian(v) if np.isfinite(v).any() else np.nan for v in values]
                )
                low = median - np.array(
                    [np.nanmin(v) if np.isfinite(v).any() else np.nan for v in values]
                )
                high = (
                    np.array([np.nanmax(v) if np.isfinite(v).any() else np.nan for v in values])
                    - median
                )
                axes[row, column].errorbar(
                    unrolls,
                    median,
                    yerr=[low, high],
                    capsize=3,
                    label=literal(label) if row == 0 else None,
                    **styles.get(label, {}),
                )
        for row, label in enumerate(("final test loss", "seconds per iteration")):
            ax = axes[row, column]
            ax.set_xscale("log", base=2)
            # a tick at every unroll length run (a log axis alone labels only the powers of ten in
            # range)
            ax.xaxis.set_major_locator(FixedLocator(every_unroll))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.0f}"))
            ax.xaxis.set_minor_locator(NullLocator())
            log_axis(ax)
            ax.set_xlabel("unroll length (time steps)")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
        axes[0, column].set_title(literal(scene), fontsize=10)
        legend_outside(axes[0, column], title="median over seeds, bars: min-max")
    save_figure(fig, path, note)
    return True
