"""Figures: per run (loss vs iteration and vs training wall-clock) and per comparison (one line per variant,
median and min-max band over seeds). PNG through matplotlib's Agg backend."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from physgrad.results import Run  # noqa: E402


def plot_run(run: Run, path: str | Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, x_key, x_label in zip(axes, ("iteration", "wall_time"), ("iteration", "training wall-clock [s]")):
        if run.train.get("loss") is not None and run.train["loss"].size:
            ax.plot(run.train[x_key], run.train["loss"], lw=0.7, alpha=0.5, label="train (minibatch)")
        if run.eval.get("loss") is not None and run.eval["loss"].size:
            ax.plot(run.eval[x_key], run.eval["loss"], "o-", ms=3, label="test")
        ax.set_xlabel(x_label)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("loss")
    axes[0].legend()
    status = run.attrs.get("status", "?")
    fig.suptitle(f"{run.attrs.get('task')} / {run.variant}, seed {run.attrs.get('seed')}: {status}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def median_band(curves: list[tuple[np.ndarray, np.ndarray]], points: int = 200):
    """Median and min-max of several (x, loss) curves on a shared x grid up to the shortest curve's end,
    interpolated in log(loss)."""
    end = min(x[-1] for x, _ in curves)
    grid = np.linspace(0.0, end, points) if end > 0 else np.array([0.0])
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
    if note:
        fig.suptitle(note, fontsize=9, color="dimgray")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _seeds(count: int) -> str:
    return f"{count} seed{'s' * (count > 1)}"


def plot_comparison(runs: list[Run], path: str | Path, x_key: str = "wall_time", note: str = "") -> None:
    """Held-out loss against training wall-clock (or iteration), one panel per scene (task and setting), one
    line per variant: the median over seeds and the min-max band. A run started from another's network
    begins where that run ended."""
    by_task = defaultdict(lambda: defaultdict(lambda: {"ok": [], "diverged": []}))
    for run in runs:
        loss = run.eval.get("loss")
        if loss is not None and loss.size and np.isfinite(loss).any():
            finite = np.isfinite(loss)
            kind = "diverged" if run.attrs.get("status") == "diverged" else "ok"
            by_task[run.scene][run.variant][kind].append((run.eval[x_key][finite] + run.offset(x_key), loss[finite]))
    tasks = sorted(by_task) or ["(no runs with evaluations)"]
    fig, axes = _panels(len(tasks))
    for ax, task in zip(axes, tasks):
        for variant, kinds in sorted(by_task.get(task, {}).items()):
            curves, diverged = kinds["ok"], kinds["diverged"]
            label = f"{variant} ({_seeds(len(curves))}" + (f", {len(diverged)} diverged)" if diverged else ")")
            color = None
            if curves:
                start = min(x[0] for x, _ in curves)
                grid, median, low, high = median_band([(x - start, y) for x, y in curves])
                line, = ax.plot(grid + start, median, label=label)
                color = line.get_color()
                if len(curves) > 1:
                    ax.fill_between(grid + start, low, high, color=color, alpha=0.2)
            for index, (x, y) in enumerate(diverged):  # each on its own, ending in a cross where it diverged
                line, = ax.plot(x, y, "--", lw=0.8, color=color, label=label if color is None and not index else None)
                color = line.get_color()
                ax.plot(x[-1:], y[-1:], "x", ms=8, color=color)
        ax.set_title(task)
        ax.set_xlabel("training wall-clock [s]" if x_key == "wall_time" else x_key)
        ax.set_ylabel("test loss")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        if by_task.get(task):
            ax.legend(fontsize=8)
    _save(fig, path, note)


def plot_tradeoff(runs: list[Run], path: str | Path, note: str = "") -> None:
    """Error against run time: per scene, every completed run's final test loss against its seconds per
    iteration (top) and its total training time (bottom); one marker colour per variant, one point per seed."""
    by_task = defaultdict(lambda: defaultdict(list))
    for run in runs:
        final = run.final("eval")
        if run.attrs.get("status") == "completed" and np.isfinite(final) and np.isfinite(run.seconds_per_iteration):
            total = run.final("train", "wall_time") + run.offset("wall_time")
            by_task[run.scene][run.variant].append((run.seconds_per_iteration, total, final))
    tasks = sorted(by_task) or ["(no finished runs)"]
    columns = min(len(tasks), 4)  # scenes per row; each scene is a pair of panels stacked vertically
    rows = -(-len(tasks) // columns)
    fig, axes = plt.subplots(2 * rows, columns, figsize=(max(8.0, 4.5 * columns), 7.0 * rows), squeeze=False)
    for ax in axes[:, :].flat:
        ax.set_visible(False)
    for index, task in enumerate(tasks):
        top, bottom = axes[2 * (index // columns), index % columns], axes[2 * (index // columns) + 1, index % columns]
        for variant, points in sorted(by_task.get(task, {}).items()):
            per_iter, total, final = np.array(points).T
            line, = top.plot(per_iter, final, "o", label=f"{variant} ({_seeds(len(points))})")
            bottom.plot(total, final, "o", color=line.get_color())
        for ax, label in ((top, "seconds per iteration"), (bottom, "total training time [s]")):
            ax.set_visible(True)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(label)
            ax.set_ylabel("final test loss")
            ax.grid(True, which="both", alpha=0.3)
        top.set_title(task)
        if by_task.get(task):
            top.legend(fontsize=8)
    _save(fig, path, note)


def plot_unroll(runs: list[Run], path: str | Path, note: str = "") -> bool:
    """Final test loss and seconds per iteration against the unroll length, per task and variant (median over
    seeds, with min-max bars); False (and no file) when no task has runs at several unroll lengths."""
    by_task = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for run in runs:
        unroll = run.attrs.get("unroll")
        if unroll is not None:
            scene = " ".join(word for word in run.scene.split() if not word.startswith("unroll="))
            final = run.final("eval") if run.attrs.get("status") == "completed" else np.nan  # diverged: no loss
            by_task[scene][run.variant][int(unroll)].append((final, run.seconds_per_iteration))
    tasks = sorted(task for task, variants in by_task.items()
                   if len({u for lengths in variants.values() for u in lengths}) > 1)
    if not tasks:
        return False
    fig, axes = plt.subplots(2, len(tasks), figsize=(max(8.0, 5 * len(tasks)), 7.5), squeeze=False)
    for column, task in enumerate(tasks):
        for variant, lengths in sorted(by_task[task].items()):
            unrolls = sorted(lengths)
            for row in (0, 1):
                values = [np.array([v[row] for v in lengths[u]], float) for u in unrolls]
                median = np.array([np.nanmedian(v) if np.isfinite(v).any() else np.nan for v in values])
                low = median - np.array([np.nanmin(v) if np.isfinite(v).any() else np.nan for v in values])
                high = np.array([np.nanmax(v) if np.isfinite(v).any() else np.nan for v in values]) - median
                axes[row, column].errorbar(unrolls, median, yerr=[low, high], fmt="o-", capsize=3,
                                           label=variant if row == 0 else None)
        for row, label in enumerate(("final test loss", "seconds per iteration")):
            ax = axes[row, column]
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel("unroll length (time steps)")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
        axes[0, column].set_title(task)
        axes[0, column].legend(fontsize=8)
    _save(fig, path, note)
    return True
