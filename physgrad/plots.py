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


def plot_comparison(runs: list[Run], path: str | Path, x_key: str = "wall_time") -> None:
    """Held-out loss against training wall-clock (or iteration), one panel per scene (task and setting), one
    line per variant."""
    by_task = defaultdict(lambda: defaultdict(list))
    for run in runs:
        loss = run.eval.get("loss")
        if loss is not None and loss.size and np.isfinite(loss).any():
            finite = np.isfinite(loss)
            by_task[run.scene][run.variant].append((run.eval[x_key][finite], loss[finite]))
    tasks = sorted(by_task) or ["(no runs with evaluations)"]
    columns = min(len(tasks), 4)
    rows = -(-len(tasks) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(5.5 * columns, 4 * rows), squeeze=False)
    for ax in axes.flat[len(tasks):]:
        ax.set_visible(False)
    for ax, task in zip(axes.flat, tasks):
        for variant, curves in sorted(by_task.get(task, {}).items()):
            grid, median, low, high = median_band(curves)
            line, = ax.plot(grid, median, label=f"{variant} ({len(curves)} seed{'s' * (len(curves) > 1)})")
            if len(curves) > 1:
                ax.fill_between(grid, low, high, color=line.get_color(), alpha=0.2)
        ax.set_title(task)
        ax.set_xlabel("training wall-clock [s]" if x_key == "wall_time" else x_key)
        ax.set_ylabel("test loss")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        if by_task.get(task):
            ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
