"""Figures: per run (losses, gradient norm and the scene's metrics) and per comparison (one line per group of
runs: the median over seeds with markers at the evaluations and the min-max band). Comparison figures are
written as PNG and PDF through matplotlib's Agg backend."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
# labels come from results files (anyone's): a `$` in one is text, not the start of mathtext to parse
matplotlib.rcParams["text.parse_math"] = False
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, MaxNLocator, NullFormatter, NullLocator  # noqa: E402

from physgrad.results import Run, natural_key  # noqa: E402

MAX_MARKERS = 40  # markers per curve at most (evaluations beyond that are thinned out evenly)


def _three_figures(value, _position=None) -> str:
    return f"{value:.3g}"


def log_axis(ax, which: str = "y") -> None:
    """A log axis whose labels read well: decades in scientific notation, and where the data span less than
    a decade, a few evenly spaced values with three significant figures (matplotlib's default then labels
    minor ticks such as 9.9992x10^-1)."""
    axis = ax.yaxis if which == "y" else ax.xaxis
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    low, high = ax.get_ylim() if which == "y" else ax.get_xlim()
    if low > 0 and high / low < 10:
        axis.set_major_locator(MaxNLocator(5))
        axis.set_major_formatter(FuncFormatter(_three_figures))
        axis.set_minor_locator(NullLocator())
        axis.set_minor_formatter(NullFormatter())


def plot_run(run: Run, path: str | Path) -> None:
    """One run: train and test loss against iteration and training time, the gradient norm, and the scene's
    metrics (fidelity, poles upright, ...) at the evaluations."""
    metrics = sorted(k for k in run.eval if k not in ("iteration", "wall_time", "loss"))
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    for ax, x_key, x_label in zip(axes[0], ("iteration", "wall_time"), ("iteration", "training time [s]")):
        if run.train.get("loss") is not None and run.train["loss"].size:
            ax.plot(run.train[x_key], run.train["loss"], lw=0.7, alpha=0.5, label="train (minibatch)")
        if run.eval.get("loss") is not None and run.eval["loss"].size:
            ax.plot(run.eval[x_key], run.eval["loss"], "o-", ms=3, label="test")
        ax.set_xlabel(x_label)
        ax.set_ylabel("loss")
        log_axis(ax)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_lines():  # a run stopped before its first evaluation has nothing to show
            ax.legend(fontsize=8)
    ax = axes[1, 0]
    if run.train.get("grad_norm") is not None and run.train["grad_norm"].size:
        ax.plot(run.train["iteration"], run.train["grad_norm"], lw=0.7)
        log_axis(ax)
    ax.set_xlabel("iteration")
    ax.set_ylabel("gradient norm (before the update rule)")
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1, 1]
    if metrics:
        for name in metrics:
            ax.plot(run.eval["iteration"], run.eval[name], "o-", ms=3, label=name)
        ax.set_ylabel("test metric")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "this scene has no metric besides the loss", ha="center", va="center",
                transform=ax.transAxes, color="dimgray")
    ax.set_xlabel("iteration")
    ax.grid(True, alpha=0.3)
    status = run.attrs.get("status", "?")
    reason = f" ({run.attrs['reason']})" if run.attrs.get("reason") else ""
    fig.suptitle(f"{run.attrs.get('task')} / {run.variant}, seed {run.attrs.get('seed')}: {status}{reason}",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def median_band(curves: list[tuple[np.ndarray, np.ndarray]]):
    """Median and min-max of several (x, loss) curves at every x where one of them was evaluated, up to the
    shortest curve's end, interpolated in log(loss)."""
    end = min(x[-1] for x, _ in curves)
    grid = np.unique(np.concatenate([x[x <= end] for x, _ in curves]))
    logs = np.array([np.interp(grid, x, np.log10(np.maximum(y, 1e-300))) for x, y in curves])
    return grid, 10 ** np.median(logs, axis=0), 10 ** logs.min(axis=0), 10 ** logs.max(axis=0)


def _panels(count: int, width: float = 5.5, height: float = 4.0, max_columns: int = 4):
    columns = max(1, min(count, max_columns))
    rows = max(1, -(-count // columns))
    # at least 8 inches wide, so that the note above the panels fits
    fig, axes = plt.subplots(rows, columns, figsize=(max(8.0, width * columns), height * rows), squeeze=False)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def _save(fig, path, note: str) -> None:
    """path without suffix: written as path.png and path.pdf."""
    top = 1.0
    if note:
        fig.suptitle(note, fontsize=9, color="dimgray")
        top -= (0.2 + 0.17 * (note.count("\n") + 1)) / fig.get_figheight()  # the note's lines, in inches
    fig.tight_layout(rect=(0, 0, 1, top))
    for suffix in (".png", ".pdf"):
        fig.savefig(Path(path).with_suffix(suffix), dpi=110)
    plt.close(fig)


def _short_reason(reason: str) -> str:
    """'loss became nan at iteration 12 (loss); the SVD ...' -> 'loss became nan at iteration 12'."""
    return reason.split(" (")[0].split(";")[0]


def use_log_x(ends: list[float], logx: str) -> bool:
    """auto: when the curves' ends (median per group) span a decade or more, so that a fast method is not a
    vertical line at the left of a slow one's curve."""
    if logx != "auto":
        return logx == "on"
    positive = [end for end in ends if end > 0]
    return len(positive) > 1 and max(positive) / min(positive) >= 10


def plot_comparison(runs: list[Run], path: str | Path, x_key: str = "wall_time", note: str = "",
                    logx: str = "auto") -> None:
    """Held-out loss against training time (or iteration), one panel per scene, one line per group: the
    median over its seeds with a marker at each evaluation and the min-max band; diverged runs each on their
    own, ending in a cross labelled with the reason. A run started from another's network begins where that
    run ended. The x axis is symmetric-log (linear around 0, so the initial evaluation stays visible) where
    use_log_x says so."""
    by_scene = defaultdict(lambda: defaultdict(lambda: {"ok": [], "diverged": []}))
    for run in runs:
        loss = run.eval.get("loss")
        if loss is not None and loss.size and np.isfinite(loss).any():
            finite = np.isfinite(loss)
            kind = "diverged" if run.attrs.get("status") == "diverged" else "ok"
            curve = (run.eval[x_key][finite] + run.offset(x_key), loss[finite], run.attrs.get("reason") or "")
            by_scene[run.scene][run.label or run.variant][kind].append(curve)
    scenes = sorted(by_scene, key=natural_key) or ["(no runs with evaluations)"]
    fig, axes = _panels(len(scenes))
    for ax, scene in zip(axes, scenes):
        groups = by_scene.get(scene, {})
        ends, smallest, banded, notes = [], [], False, 0
        for label, kinds in sorted(groups.items(), key=lambda item: natural_key(item[0])):
            curves, diverged = kinds["ok"], kinds["diverged"]
            text = f"{label} (n={len(curves)}" + (f", {len(diverged)} diverged)" if diverged else ")")
            color = None
            if curves:
                grid, median, low, high = median_band([(x, y) for x, y, _ in curves])
                every = max(1, len(grid) // MAX_MARKERS)
                line, = ax.plot(grid, median, "-o", ms=3, markevery=every, label=text)
                color = line.get_color()
                if len(curves) > 1:
                    ax.fill_between(grid, low, high, color=color, alpha=0.2, lw=0)
                    banded = True
                ends.append(float(np.median([x[-1] for x, _, _ in curves])))
                smallest += [x[x > 0].min() for x, _, _ in curves if (x > 0).any()]
            for index, (x, y, reason) in enumerate(diverged):
                line, = ax.plot(x, y, "--", lw=0.8, color=color, label=text if color is None and not index else None)
                color = line.get_color()
                ax.plot(x[-1:], y[-1:], "x", ms=8, color=color)
                # runs that diverge early end at nearly the same point: stack their notes instead of overprinting
                ax.annotate(_short_reason(reason), (x[-1], y[-1]), xytext=(4, 4 - 9 * notes),
                            textcoords="offset points", fontsize=7, color=color)
                notes += 1
                smallest += [x[x > 0].min()] if (x > 0).any() else []
        ax.set_title(scene, fontsize=10)
        ax.set_xlabel({"wall_time": "training time, measured clock [s]",
                       "calibrated_time": "training time, calibrated clock [s]"}.get(x_key, "iteration"))
        ax.set_ylabel("test loss")
        log_axis(ax)
        if smallest and use_log_x(ends, logx):
            ax.set_xscale("symlog", linthresh=min(smallest))
            ax.set_xlim(left=0)
        ax.grid(True, which="both", alpha=0.3)
        if groups:
            ax.legend(fontsize=7, title="line: median over n seeds" + (", band: min-max" if banded else ""),
                      title_fontsize=7)
    _save(fig, path, note)


def plot_tradeoff(runs: list[Run], path: str | Path, note: str = "") -> None:
    """Error against run time: per scene, every completed run's final test loss against its seconds per
    iteration (top) and its total training time (bottom); one marker colour per group, one point per seed."""
    by_scene = defaultdict(lambda: defaultdict(list))
    for run in runs:
        final = run.final("eval")
        if run.attrs.get("status") == "completed" and np.isfinite(final) and np.isfinite(run.seconds_per_iteration):
            total = run.final("train", "wall_time") + run.offset("wall_time")
            by_scene[run.scene][run.label or run.variant].append((run.seconds_per_iteration, total, final))
    scenes = sorted(by_scene, key=natural_key) or ["(no finished runs)"]
    columns = min(len(scenes), 4)  # scenes per row; each scene is a pair of panels stacked vertically
    rows = -(-len(scenes) // columns)
    fig, axes = plt.subplots(2 * rows, columns, figsize=(max(8.0, 4.5 * columns), 7.0 * rows), squeeze=False)
    for ax in axes[:, :].flat:
        ax.set_visible(False)
    for index, scene in enumerate(scenes):
        top, bottom = axes[2 * (index // columns), index % columns], axes[2 * (index // columns) + 1, index % columns]
        for label, points in sorted(by_scene.get(scene, {}).items()):
            per_iter, total, final = np.array(points).T
            line, = top.plot(per_iter, final, "o", label=f"{label} (n={len(points)})")
            bottom.plot(total, final, "o", color=line.get_color())
        for ax, label in ((top, "seconds per iteration"), (bottom, "total training time [s]")):
            ax.set_visible(True)
            log_axis(ax, "x")
            log_axis(ax, "y")
            ax.set_xlabel(label)
            ax.set_ylabel("final test loss")
            ax.grid(True, which="both", alpha=0.3)
        top.set_title(scene, fontsize=10)
        if by_scene.get(scene):
            top.legend(fontsize=7, title="one point per seed", title_fontsize=7)
    _save(fig, path, note)


def plot_unroll(runs: list[Run], path: str | Path, note: str = "") -> bool:
    """Final test loss and seconds per iteration against the unroll length, per task and group (median over
    seeds, with min-max bars); False (and no file) when no task has runs at several unroll lengths."""
    by_scene = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for run in runs:
        unroll = run.attrs.get("unroll")
        if unroll is not None:
            scene = " ".join(word for word in run.scene.split() if not word.startswith("unroll="))
            final = run.final("eval") if run.attrs.get("status") == "completed" else np.nan  # diverged: no loss
            by_scene[scene][run.label or run.variant][int(unroll)].append((final, run.seconds_per_iteration))
    scenes = sorted(scene for scene, groups in by_scene.items()
                    if len({u for lengths in groups.values() for u in lengths}) > 1)
    if not scenes:
        return False
    fig, axes = plt.subplots(2, len(scenes), figsize=(max(8.0, 5 * len(scenes)), 7.5), squeeze=False)
    for column, scene in enumerate(scenes):
        for label, lengths in sorted(by_scene[scene].items()):
            unrolls = sorted(lengths)
            for row in (0, 1):
                values = [np.array([v[row] for v in lengths[u]], float) for u in unrolls]
                median = np.array([np.nanmedian(v) if np.isfinite(v).any() else np.nan for v in values])
                low = median - np.array([np.nanmin(v) if np.isfinite(v).any() else np.nan for v in values])
                high = np.array([np.nanmax(v) if np.isfinite(v).any() else np.nan for v in values]) - median
                axes[row, column].errorbar(unrolls, median, yerr=[low, high], fmt="o-", capsize=3,
                                           label=label if row == 0 else None)
        for row, label in enumerate(("final test loss", "seconds per iteration")):
            ax = axes[row, column]
            ax.set_xscale("log", base=2)
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.0f}"))
            log_axis(ax)
            ax.set_xlabel("unroll length (time steps)")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
        axes[0, column].set_title(scene, fontsize=10)
        axes[0, column].legend(fontsize=7, title="median over seeds, bars: min-max", title_fontsize=7)
    _save(fig, path, note)
    return True
