"""`physgrad report`: tables, figures and CSV files that compare runs, from results files alone.

Runs are compared like with like: by scene (one panel and one block of rows each) and, within a
scene, by group (every seed of one configuration), as physgrad.runs finds, labels and de-duplicates
them. The report names what it dropped as a duplicate and what it could not read.
"""

from __future__ import annotations

import math
import os
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from physgrad.errors import UserError
from physgrad.files import clean_text, read_small_yaml, replaced
from physgrad.readout import fmt, loss_at, run_budget, run_record, targets
from physgrad.results import Run, natural_key
from physgrad.runs import Dropped, collect, label_runs, parse_sources, setting_text
from physgrad.sweeps import unfinished_jobs
from physgrad.tables import Tables, tables, write_tables

METADATA = ("iteration", "wall_time", "calibrated_time")


def common_clock(runs: list[Run]) -> dict[str, str]:
    """Per scene, the clock its runs' budgets were on: calibrated_time where every completed run
    trained to a budget on the calibrated clock (a compare's verdict reads that clock, so its
    report must too), else wall_time (the measured clock)."""
    clocks: dict[str, set] = defaultdict(set)
    for run in runs:
        if run.attrs.get("status") == "completed":
            clocks[run.scene].add(run_budget(run)[0])
    return {
        scene: "calibrated_time" if found == {"calibrated_time"} else "wall_time"
        for scene, found in clocks.items()
    }


def common_times(runs: list[Run]) -> dict[str, tuple[str, float]]:
    """Per scene, (clock, the time every completed run covers): the shortest end of training among
    them (a time budget ends a run at its budget) on the scene's clock (common_clock), on the shared
    time axis (a run started from another's network starts where that one ended). Losses at this
    time compare variants at equal training time, on the clock their budget was."""
    clocks = common_clock(runs)
    shortest: dict[str, float] = defaultdict(lambda: math.inf)
    for run in runs:
        clock = clocks.get(run.scene, "wall_time")
        end = run.final("train", clock) + run.offset(clock)
        if run.attrs.get("status") == "completed" and math.isfinite(end):
            shortest[run.scene] = min(shortest[run.scene], end)
    return {scene: (clocks.get(scene, "wall_time"), t) for scene, t in shortest.items()}


CLOCK_WORDS = {"wall_time": "measured clock", "calibrated_time": "calibrated clock"}


def metric_names(runs: list[Run]) -> list[str]:
    """The scene metrics the runs evaluate besides the loss (e.g. fidelity, upright)."""
    return sorted({k for run in runs for k in run.eval if k not in (*METADATA, "loss")})


def run_rows(
    runs: list[Run],
    threshold: float | None = None,
    variant_of: Callable[[Run], str] | None = None,
) -> list[dict]:
    """One row per run (the per-seed table and runs.csv): where it stands in the report (set,
    task, scene, setting, label), its record at its own budget with the scene's target
    (readout.run_record), its last minibatch losses, its loss at the scene's common time, its
    step time and its scene metrics. variant: the run's variant as its study names it
    (variant_of, a compare's report) or as its file does."""
    limits, common = targets(runs), common_times(runs)
    names = metric_names(runs)
    rows = []

    def order(r: Run) -> tuple:
        return natural_key(r.scene), natural_key(r.label), natural_key(str(r.attrs.get("seed")))

    for run in sorted(runs, key=order):
        clock, at = common.get(run.scene, ("wall_time", math.nan))
        train_loss = run.train.get("loss", np.empty(0))
        record = run_record(
            run, threshold if threshold is not None else limits.get(run.scene, math.nan)
        )
        reason = record.pop("reason")
        named = record.pop("variant")  # as the file names it
        rows.append(
            {
                "path": record.pop("path"),
                "set": run.collection,
                "task": run.attrs.get("task"),
                "scene": run.scene,
                "setting": run.setting,
                "variant": variant_of(run) if variant_of else named,
                "label": run.label,
                **record,
                "train_loss": float(np.median(train_loss[-10:])) if train_loss.size else math.nan,
                "common_time": at,
                "common_clock": CLOCK_WORDS[clock],
                # the common time is on the shared axis; a continued run's own clock starts later
                "loss_at_common_time": loss_at(run, at - run.offset(clock), clock)
                if math.isfinite(at)
                else math.nan,
                "s_per_iter": run.seconds_per_iteration,
                **{name: run.final("eval", name) for name in names},
                "reason": reason,
            }
        )
    return rows


def _spread(values: Iterable[object]) -> str:
    """median [min, max] of the finite values (the median alone for one)."""
    finite = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    if not finite:
        return "-"
    if len(finite) == 1:
        return fmt(float(finite[0]))
    return f"{fmt(float(np.median(finite)))} [{fmt(float(min(finite)))}, {fmt(float(max(finite)))}]"


def _counts(values: Iterable[str], plain_if_one: bool = False) -> str:
    """'2 completed, 1 diverged'; the value alone if all agree and plain_if_one."""
    counts = Counter(v for v in values if v)
    if plain_if_one and len(counts) == 1:
        return next(iter(counts))
    return ", ".join(f"{n} {v}" for v, n in sorted(counts.items())) or "-"


def group_rows(rows: list[dict], names: list[str]) -> list[dict]:
    """One row per (scene, group): seeds, status counts, spread of the final test loss (completed
    runs) and of the loss at the common time (every run that got there), time to the target
    (median over the seeds that reached it, and how many did), iterations, s/iter, what stopped the
    runs, and the scene's metrics."""
    groups = defaultdict(list)
    for row in rows:
        groups[(row["scene"], row["label"])].append(row)
    table = []
    for (scene, label), members in groups.items():
        # a diverged run's last loss says nothing
        completed = [r for r in members if r["status"] == "completed"]
        reached = [r["time_to_target"] for r in members if math.isfinite(r["time_to_target"])]
        time_to = (
            "-"
            if not reached
            else fmt(float(np.median(reached)))
            + ("" if len(reached) == len(members) else f" ({len(reached)}/{len(members)})")
        )
        table.append(
            {
                "scene": scene,
                "group": label,
                "seeds": len(members),
                "status": _counts(r["status"] for r in members),
                "final test loss": _spread(r["test_loss_at_1"] for r in completed),
                "loss at common time": _spread(r["loss_at_common_time"] for r in members),
                "time to target s": time_to,
                "iterations": str(round(float(np.median([r["iterations"] for r in members])))),
                "s/iter": _spread(r["s_per_iter"] for r in members),
                "stopped by": _counts((r["stopped_by"] for r in members), plain_if_one=True),
                "contended": f"{sum(r['contended'] for r in members)}/{len(members)}",
                "machine": "; ".join(sorted({r["machine"] for r in members})),
                **{name: _spread(r[name] for r in completed) for name in names},
            }
        )
    return table


def timing_notes(rows: list[dict], scenes: list[str]) -> list[str]:
    """The machine of each scene's runs (a warning where one scene's runs come from several: their
    times are not comparable) and the runs whose timing was contended
    (physgrad.machine.contention)."""
    notes = [""]
    for scene in scenes:
        machines = sorted({r["machine"] for r in rows if r["scene"] == scene})
        if len(machines) > 1:
            notes.append(
                f"warning: the runs of {scene} come from {len(machines)} machines "
                f"({'; '.join(machines)}): their times are not comparable"
            )
        else:
            notes.append(f"{scene} measured on {machines[0]}.")
    contended = [r for r in rows if r["contended"]]
    if contended:
        notes.append(
            f"warning: {len(contended)} of {len(rows)} runs were contended (their measured times "
            "were slowed by other work; calibrated times, where present, are not): "
            + "; ".join(f"{r['label']} seed {r['seed']}: {r['contention']}" for r in contended[:5])
            + (" ..." if len(contended) > 5 else "")
        )
    return notes


PER_SEED = (
    "scene",
    "label",
    "seed",
    "status",
    "stopped_by",
    "iterations",
    "test_loss_at_1",
    "loss_at_common_time",
    "time_to_target",
    "s_per_iter",
    "train_seconds",
    "compile_seconds",
)


def markdown_table(rows: list[dict], columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(fmt(row[c]).replace("|", "/") for c in columns) + " |")
    return "\n".join(lines) + "\n"


def read_runs(
    paths: Iterable[str | Path] | str | os.PathLike, threshold: float | None = None
) -> Tables:
    """Every readable run under the paths (files, folders, LABEL=PATH sets, as `physgrad report`
    takes them; one path may be given alone, as a string or a Path) as tidy tables (Tables: .runs
    and .curves, pandas DataFrames), grouped and labelled as a report does. UserError (one line) if
    a path does not exist or holds no results file; unreadable files are left out, with one warning
    that names the first and why."""
    if isinstance(paths, (str, os.PathLike)):  # one path, not its characters
        paths = [paths]
    runs, unreadable, _ = collect([os.fspath(path) for path in paths])
    if unreadable:
        import warnings

        first, why = unreadable[0]
        why = str(why).removeprefix(f"{first}: ")
        more = f" (and {len(unreadable) - 1} more)" if len(unreadable) > 1 else ""
        warnings.warn(
            f"{len(unreadable)} results file{'s' if len(unreadable) > 1 else ''} left out as "
            f"unreadable: {first}: {why}{more}",
            UserWarning,
            stacklevel=3,
        )
    label_runs(runs)
    return tables(runs, run_rows(runs, threshold))


def output_folder(arguments: Sequence[str | Path], out_dir: str | Path | None) -> Path:
    """--out, else the first path's folder; UserError (one line) if it cannot be created or
    written."""
    first = parse_sources(arguments)[0][1]
    out = Path(out_dir) if out_dir else (first if first.is_dir() else first.parent)
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not os.access(out, os.W_OK | os.X_OK):
            raise PermissionError(13, "Permission denied", str(out))
    except OSError as error:
        raise UserError(
            f"cannot write the report to {out}: {error.strerror or error}: give --out <a writable "
            "folder>"
        ) from None
    return out


def write_report(
    paths: Sequence[str | Path],
    out_dir: str | Path | None = None,
    threshold: float | None = None,
    note: str = "",
    logx: str = "auto",
    figures: bool = True,
    study_of: Callable[[Run], int] | None = None,
    variant_of: Callable[[Run], str] | None = None,
) -> str:
    """Print-ready text; also writes into out_dir (default: the first path's folder) report.md,
    runs.csv, curves.csv and, with ``figures``, the figures (PNG and PDF): loss_vs_time,
    loss_vs_iteration, tradeoff (final test loss against seconds per iteration and total time) and,
    where runs differ in unroll length, unroll. ``note`` is printed on every figure; ``logx`` is
    auto (log where the curves' ends span a decade or more), on or off. ``study_of``: a run's
    tuning study (1, 2, ...) in a compare: each group is then labelled "variant, tuning study k:
    its tuned settings" and drawn in its variant's colour and its study's line style;
    ``variant_of``: a run's variant as its compare names it (runs.csv's `variant`, as in the
    study's own runs.csv)."""
    runs, unreadable, dropped = collect(paths)
    if not runs:
        raise UserError(
            f"no readable results file under {', '.join(map(str, paths))}: "
            f"{unreadable[0][1] if unreadable else 'nothing found'}"
        )
    out = output_folder(paths, out_dir)
    label_runs(runs)
    design = _label_studies(runs, study_of) if study_of is not None else {}
    rows = run_rows(runs, threshold, variant_of)
    limits = targets(runs)
    text = summary_lines(paths, runs, rows, threshold, limits)
    text += timing_notes(rows, sorted({run.scene for run in runs}, key=natural_key))
    text += file_notes(paths, unreadable, dropped)
    body = "\n".join(text) + "\n"
    write_tables(tables(runs, rows), out)
    # last: a report.md beside complete tables only
    with replaced(out / "report.md", text=True) as f:
        f.write(body)
    written = f"wrote {out / 'report.md'}, runs.csv, curves.csv (and .parquet)"
    if not figures:
        return body + written + "\n"
    chosen = {scene: threshold for scene in limits} if threshold is not None else limits
    from physgrad.report_figures import write_figures  # matplotlib only once it draws

    drawn = write_figures(runs, out, note, logx, chosen, design)
    return body + f"{written} and {', '.join(drawn)} (and .pdf)\n"


def _label_studies(runs: list[Run], study_of: Callable[[Run], int]) -> dict:
    """Each run's group label with its tuning study ("adam, tuning study 2: learning_rate=0.0044");
    the labels' (variant, study) for design_styles."""
    design = {}
    for run in runs:
        study = study_of(run)
        settings = (run.label or run.variant).removeprefix(run.variant).strip()
        run.label = f"{run.variant}, tuning study {study}" + (f": {settings}" if settings else "")
        design[run.label] = (run.variant, study)
    return design


def summary_lines(
    paths: Sequence[str | Path],
    runs: list[Run],
    rows: list[dict],
    threshold: float | None,
    limits: dict[str, float],
) -> list[str]:
    """report.md's tables (per group, per seed) with what their columns mean."""
    names = metric_names(runs)
    group_columns = (
        "scene",
        "group",
        "seeds",
        "status",
        "final test loss",
        "loss at common time",
        "time to target s",
        "iterations",
        "s/iter",
        "stopped by",
        "contended",
        *names,
    )
    common = common_times(runs)
    scenes = sorted({run.scene for run in runs}, key=natural_key)
    if threshold is not None:
        threshold_text = f"the test loss {fmt(threshold)} (--threshold)"
    else:
        threshold_text = (
            "each scene's target: the median final test loss of its best group, as physgrad "
            "compare sets it (--threshold sets one)"
        )
    per_scene = "; ".join(
        f"{scene}: common time {fmt(common.get(scene, ('', math.nan))[1])} s "
        f"({CLOCK_WORDS.get(common.get(scene, ('wall_time',))[0])}), target "
        f"{fmt(threshold if threshold is not None else limits.get(scene, math.nan))}"
        for scene in scenes
    )
    return [
        f"{len(runs)} runs under {', '.join(map(str, paths))}",
        "",
        markdown_table(group_rows(rows, names), group_columns),
        "Per group, as median [min, max] over seeds: the final test loss (at each run's budget) "
        "and the metrics "
        "over the completed seeds, the loss at the common time over the seeds that got there, "
        "s/iter over all; "
        "loss at common time: the last evaluation at or before the shortest training time of the "
        "scene's completed runs (as physgrad compare reads a budget: physgrad.readout), on the "
        "clock their budgets were on (the calibrated clock where every run's was, as in the "
        "verdicts; the measured clock otherwise), so every variant is compared at equal training "
        "time; time to target: "
        f"median training seconds until the test loss first reached {threshold_text}, over the "
        f"seeds that did (n/N when not all). {per_scene}.",
        "",
        "Per seed:",
        "",
        markdown_table(rows, PER_SEED + tuple(names)),
        "Times are training seconds (steps only; train_seconds on the measured clock whatever "
        "the budget's: compilation and the first step's one-off cost are apart, in "
        "compile_seconds and runs.csv); a run started from another's network counts from where "
        "that run ended on the common time axis, and from its own start in train_seconds.",
    ]


def file_notes(
    paths: Sequence[str | Path], unreadable: list[tuple[Path, str]], dropped: list[Dropped]
) -> list[str]:
    """What the report did not count, and why: unreadable files, duplicates, jobs a sweep expected
    that left no results file; and the best trial of a study of Hydra's Optuna sweeper."""
    text = [f"unreadable: {reason}" for _, reason in unreadable]
    for item in dropped:
        text.append(
            f"counted once: {item.path}: {item.why}"
            if item.path.resolve() == item.kept.resolve()
            else f"dropped {item.path}: {item.why} as {item.kept}"
        )
    for _, path in parse_sources(paths):
        if path.is_dir():  # jobs a sweep expected (its jobs.yaml) that left no results file
            text += [f"not run: {job}: {why}" for job, why in unfinished_jobs(path)]
    for _, path in parse_sources(paths):  # a study of Hydra's Optuna sweeper (hydra/sweeper=optuna)
        study = path / "optimization_results.yaml" if path.is_dir() else None
        if study is not None and study.exists():
            try:
                best = read_small_yaml(study) or {}
                best = (
                    best
                    if isinstance(best, dict) and isinstance(best.get("best_params") or {}, dict)
                    else {}
                )
            except (OSError, ValueError) as error:
                text.append(f"unreadable: {clean_text(str(error))}")
                continue
            settings = " ".join(
                f"{k}={setting_text(v)}" for k, v in (best.get("best_params") or {}).items()
            )
            text.append(
                f"tuned by Optuna in {path}: best {settings} (objective "
                f"{fmt(best.get('best_value'))}: the final test loss)"
            )
    return text
