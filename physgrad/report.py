"""`physgrad report`: the error-against-run-time table and comparison figure from results files alone."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import yaml

from physgrad.results import Run, find_results, read_run

COLUMNS = ("task", "setting", "variant", "seed", "status", "iters", "train loss", "test loss", "s/iter", "train s",
           "t(thr) s", "note")


def collect(paths) -> tuple[list[Run], list[tuple[Path, str]]]:
    """Every readable run under paths, and (path, reason) for each file that is not a readable results file."""
    runs, unreadable = [], []
    for path in find_results(paths):
        try:
            runs.append(read_run(path))
        except ValueError as error:
            unreadable.append((path, str(error)))
    return runs, unreadable


# Settings that change the problem (not the method), shown and grouped by when they differ between runs.
SETTING_KEYS = {"unroll": "unroll", "precision": "precision"}


def _flat(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value if not isinstance(value, list) else tuple(value)
    return flat


def label_settings(runs: list[Run]) -> None:
    """Set run.setting to the problem settings that differ between runs of the same task (task.* keys other
    than the batch size, unroll, precision), e.g. "poles=3": a difficulty sweep then gets one row group and one
    panel per setting, never a median over different problems."""
    configs = {}
    for run in runs:
        try:
            config = _flat(yaml.safe_load(run.attrs.get("config", "")) or {})
        except yaml.YAMLError:
            config = {}
        configs[run.path] = {k.removeprefix("task."): v for k, v in config.items()
                             if (k.startswith("task.") and k not in ("task.name", "task.batch_size"))
                             or k in SETTING_KEYS}
    by_task = defaultdict(list)
    for run in runs:
        by_task[run.attrs.get("task")].append(run)
    for task_runs in by_task.values():
        keys = sorted({k for run in task_runs for k in configs[run.path]})
        varying = [k for k in keys if len({repr(configs[run.path].get(k)) for run in task_runs}) > 1]
        for run in task_runs:
            run.setting = " ".join(f"{k}={configs[run.path].get(k)}" for k in varying)


def thresholds(runs: list[Run]) -> dict[str, float]:
    """Per scene (task and setting), the worst final test loss among the completed runs: every one of them
    reaches it (a diverged or interrupted run's last evaluation says nothing about where training gets)."""
    worst = defaultdict(lambda: -math.inf)
    for run in runs:
        final = run.final("eval")
        if math.isfinite(final) and run.attrs.get("status") == "completed":
            worst[run.scene] = max(worst[run.scene], final)
    return dict(worst)


def _fmt(value, digits=4) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}g}"
    return str(value)


def table_rows(runs: list[Run], threshold: float | None = None) -> list[dict]:
    per_scene = thresholds(runs)
    rows = []
    for run in sorted(runs, key=lambda r: (r.scene, r.variant, str(r.attrs.get("seed")))):
        limit = threshold if threshold is not None else per_scene.get(run.scene, math.nan)
        train_loss = run.train.get("loss", np.empty(0))
        rows.append({
            "task": run.attrs.get("task"), "setting": run.setting, "variant": run.variant, "seed": run.attrs.get("seed"), "status": run.attrs.get("status"),
            "iters": int(train_loss.size),
            "train loss": float(np.median(train_loss[-10:])) if train_loss.size else math.nan,
            "test loss": run.final("eval"),
            "s/iter": run.seconds_per_iteration,
            "train s": run.final("train", "wall_time"),
            "t(thr) s": run.time_to_reach(limit) if math.isfinite(limit) else math.nan,
            "note": run.attrs.get("reason", "") or "",
        })
    return rows


def markdown_table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row[c]) for c in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def write_report(paths, out_dir=None, threshold: float | None = None, note: str = "") -> str:
    """Print-ready text; also writes into out_dir (default: the first path's folder) report.md and the figures:
    loss_vs_time.png, loss_vs_iteration.png, tradeoff.png (final test loss against seconds per iteration and
    total time) and, where runs differ in unroll length, unroll.png. ``note`` is printed on every figure."""
    runs, unreadable = collect(paths)
    label_settings(runs)
    first = Path(paths[0])
    out = Path(out_dir) if out_dir else (first if first.is_dir() else first.parent)
    out.mkdir(parents=True, exist_ok=True)
    rows = table_rows(runs, threshold)
    if threshold is not None:
        legend = f"t(thr): training seconds until the test loss first reached {threshold:.4g}."
    else:
        legend = "t(thr): training seconds until the test loss first reached the scene's threshold (" + ", ".join(
            f"{scene}: {value:.4g}" for scene, value in sorted(thresholds(runs).items())
        ) + "; the worst final test loss of the scene's completed runs, so each of them reaches it; --threshold sets it)."
    text = [f"{len(runs)} runs under {', '.join(map(str, paths))}", "", markdown_table(rows), legend,
            "train loss: median of the last 10 minibatch losses; s/iter: median seconds per training step; "
            "train s: training seconds (a run started from another's network counts from its own start)."]
    for path, reason in unreadable:
        text.append(f"unreadable: {reason}")
    body = "\n".join(text) + "\n"
    (out / "report.md").write_text(body)
    from physgrad.plots import plot_comparison, plot_tradeoff, plot_unroll

    plot_comparison(runs, out / "loss_vs_time.png", "wall_time", note)
    plot_comparison(runs, out / "loss_vs_iteration.png", "iteration", note)
    plot_tradeoff(runs, out / "tradeoff.png", note)
    figures = [FIGURES[0], FIGURES[1], FIGURES[2]]
    if plot_unroll(runs, out / "unroll.png", note):
        figures.append(FIGURES[3])
    return body + f"wrote {out / 'report.md'} and {', '.join(figures)}\n"


FIGURES = ("loss_vs_time.png", "loss_vs_iteration.png", "tradeoff.png", "unroll.png")
