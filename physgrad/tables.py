"""Tidy tables of runs: one row per run (every setting in a column of its own) and one row per
logged iteration (curves), as pandas DataFrames and as the CSV and Parquet files `physgrad report`
writes."""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from physgrad.files import replaced
from physgrad.readout import config_row
from physgrad.results import Run

# repeated in curves
ID_COLUMNS = (
    "set",
    "task",
    "scene",
    "setting",
    "variant",
    "label",
    "seed",
    "status",
)
CSV_TRAIN_ROWS = (
    1000  # curves.csv keeps every evaluation and at most this many training rows per run
)


class Tables(NamedTuple):
    """runs: one row per run, every setting in a column of its own (the config's dotted keys:
    task.*, optim.*,
    trainer.*, precision, ...; the effective unroll; the machine) beside the report's per-run
    numbers; curves: one row per run, split (train | eval) and iteration, every logged column as a
    column of its own, with the run's id (`run`, joining runs.run) and its identifying columns (set,
    task, scene, setting, variant, label, seed, status), so that a plot needs no merge."""

    runs: pd.DataFrame
    curves: pd.DataFrame


def tables(runs: list[Run], rows: list[dict]) -> Tables:
    """The runs (labelled: runs.label_runs) with their report rows (report.run_rows) as tidy
    pandas tables; see Tables."""
    by_path = {str(run.path): run for run in runs}
    records, curves = [], []
    for number, row in enumerate(rows):
        run = by_path[row["path"]]
        settings = {k: v for k, v in config_row(run).items() if k not in ("seed", "unroll")}
        records.append({"run": number, **row, "unroll": run.attrs.get("unroll"), **settings})
        for split in ("train", "eval"):
            columns = getattr(run, split)
            if "iteration" in columns:
                frame = pd.DataFrame(columns)
                frame.insert(0, "split", split)
                frame.insert(0, "run", number)
                curves.append(frame)
    runs_frame = _plain_columns(pd.DataFrame.from_records(records))
    curve_frame = (
        pd.concat(curves, ignore_index=True) if curves else pd.DataFrame(columns=["run", "split"])
    )
    if len(runs_frame):
        identity = runs_frame[["run", *ID_COLUMNS]]
        curve_frame = identity.merge(curve_frame, on="run", how="right")
    return Tables(runs_frame, curve_frame)


def _plain_columns(frame: pd.DataFrame) -> pd.DataFrame:
    """Columns of one type each (a setting that is a number in one run and text in another becomes
    text; lists become their text), so that CSV and Parquet hold them as they are."""
    for column in frame.columns:
        values = frame[column].dropna()
        kinds = {type(v) for v in values}
        if kinds - {int, float, bool, np.integer, np.floating} and (
            len(kinds) > 1 or kinds & {tuple, list, dict}
        ):
            frame[column] = frame[column].map(
                lambda v: v if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)
            )
    return frame


def write_tables(frames: Tables, out: Path) -> None:
    """runs.csv and runs.parquet; curves.parquet (every row) and curves.csv (every evaluation, and
    the training rows thinned to CSV_TRAIN_ROWS per run, evenly in iteration with the first and the
    last: a long run's CSV would be tens of MB). Each written beside and renamed into place."""
    with replaced(out / "runs.csv", text=True) as f:
        frames.runs.to_csv(f, index=False)
    with replaced(out / "curves.csv", text=True) as f:
        _thinned(frames.curves).to_csv(f, index=False)
    for name, frame in (("runs", frames.runs), ("curves", frames.curves)):
        with replaced(out / f"{name}.parquet") as f:
            frame.to_parquet(f, index=False)


def _thinned(curves: pd.DataFrame) -> pd.DataFrame:
    if not len(curves):
        return curves
    train = curves["split"] == "train"
    position = curves[train].groupby("run").cumcount()
    size = curves[train].groupby("run")["run"].transform("size")
    step = np.maximum(1, np.ceil(size / CSV_TRAIN_ROWS)).astype(int)
    keep = pd.Series(True, index=curves.index)
    keep[train] = (position % step == 0) | (position == size - 1)
    return curves[keep]
