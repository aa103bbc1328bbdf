"""The report's figures of what a result costs: the final test loss against seconds per iteration
and against the training time to a target (tradeoff), and against the unroll length (unroll), in
the groups' shared styles (plots.group_styles)."""

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
    by_label,
    legend_outside,
    limit_to,
    literal,
    log_axis,
    save_figure,
    styles_for,
)
from physgrad.readout import fmt, loss_at, targets, time_to_target  # noqa: E402
from physgrad.results import Run, natural_key  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes


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
        groups = by_label(by_scene.get(scene, {}))
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
            f"training seconds to test loss {fmt(float(limit))}"
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
