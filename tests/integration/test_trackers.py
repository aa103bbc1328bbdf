"""Integration layer of the `logger` group: TensorBoard, MLflow and W&B (offline) get each seed's
run, a failing tracker is a warning, every tracker runs once per job of a sweep, and an MLflow
database that is no SQLite file or a relative path is checked where it is opened."""

import struct
from pathlib import Path

import numpy as np
import pytest

from physgrad.results import read_run
from physgrad.trackers import MLflow, TensorBoard, WandB, track
from tests.helpers import load
from tests.unit.test_trackers import (
    TINY,
)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A job of two seeds, run once for every tracker test."""
    from physgrad.experiment import run_experiment

    folder = tmp_path_factory.mktemp("job")
    run_experiment(load(*TINY, "seeds=2"), folder)
    return folder, sorted(folder.glob("seed=*/results.h5"))


def same_series(logged, steps, values) -> bool:
    """(step, value) pairs against the file's columns: steps exactly, values to float32
    (TensorBoard's)."""
    return [s for s, _ in logged] == list(steps) and [v for _, v in logged] == pytest.approx(
        list(values), rel=1e-6
    )


def test_tensorboard_gets_every_column_of_every_seed(job, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    folder, paths = job
    track([TensorBoard(save_dir=str(tmp_path / "tb"))], paths, folder)
    for path in paths:
        run = read_run(path)
        events = EventAccumulator(
            str(tmp_path / "tb" / f"{folder.name}" / f"seed={run.attrs['seed']}")
        )
        events.Reload()
        logged = [(e.step, e.value) for e in events.Scalars("eval/loss")]
        assert same_series(logged, run.eval["iteration"].tolist(), run.eval["loss"].tolist())
        assert {"train/loss", "train/grad_norm", "train/wall_time"} <= set(events.Tags()["scalars"])


def test_mlflow_gets_a_finished_run_with_params_metrics_and_tags(job, tmp_path):
    from mlflow.tracking import MlflowClient

    folder, paths = job
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    track([MLflow(tracking_uri=uri, experiment_name="test")], paths, folder)
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("test")
    runs = client.search_runs([experiment.experiment_id])
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    for tracked in runs:
        run = read_run(tracked.data.tags["results"])
        assert tracked.data.params["optim.learning_rate"] == str(
            run.config["optim"]["learning_rate"]
        )
        assert (
            tracked.data.tags["seed"] == str(run.attrs["seed"])
            and tracked.data.tags["variant"] == "adam"
        )
        history = client.get_metric_history(tracked.info.run_id, "train/loss")
        assert same_series(
            [(m.step, m.value) for m in sorted(history, key=lambda m: m.step)],
            run.train["iteration"].tolist(),
            run.train["loss"].tolist(),
        )


def wandb_records(path: Path):
    """The protobuf records of a W&B offline log (run-*.wandb): a 7-byte header (':W&B', a 2-byte
    magic, a version), then 32 KiB blocks of chunks, each a 7-byte header (CRC32, length, type: 1
    full, 2 first, 3 middle, 4 last) and its bytes."""
    from wandb.proto import wandb_internal_pb2

    data, block, records, pending = path.read_bytes(), 32 * 1024, [], b""
    assert data[:4] == b":W&B"
    position = 7
    while position + 7 <= len(data):
        left = block - position % block
        if left < 7:  # the rest of a block too short for a header is padding
            position += left
            continue
        _, length, kind = struct.unpack("<IHB", data[position : position + 7])
        chunk = data[position + 7 : position + 7 + length]
        position += 7 + length
        if kind == 0 and length == 0:
            continue
        pending = chunk if kind in (1, 2) else pending + chunk
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
    return records


def test_wandb_offline_run_holds_the_history_and_the_config(job, tmp_path):
    import json

    folder, paths = job
    track([WandB(dir=str(tmp_path))], paths[:1], folder)  # whole on disk when it returns
    (log,) = tmp_path.glob("wandb/offline-run-*/run-*.wandb")
    records = wandb_records(log)
    history = [
        {
            item.key or "/".join(item.nested_key): json.loads(item.value_json)
            for item in r.history.item
        }
        for r in records
        if r.WhichOneof("record_type") == "history"
    ]
    run = read_run(paths[0])
    eval_loss = [(h["_step"], h["eval/loss"]) for h in history if "eval/loss" in h]
    assert same_series(eval_loss, run.eval["iteration"].tolist(), run.eval["loss"].tolist())
    keys = {
        item.key
        for r in records
        if r.WhichOneof("record_type") == "run"
        for item in r.run.config.update
    }
    assert "optim.learning_rate" in keys and "trainer.iterations" in keys
    assert any(r.WhichOneof("record_type") == "exit" and r.exit.exit_code == 0 for r in records)


def test_a_failing_tracker_is_a_warning_and_the_run_stands(job, caplog):
    class Broken:
        def log_run(self, run, name, folder):
            raise ConnectionError("tracking server unreachable")

    folder, paths = job
    track([Broken()], paths, folder)
    assert "Broken could not log" in caplog.text and "unreachable" in caplog.text
    assert all(read_run(path).attrs["status"] == "completed" for path in paths)


# a sweep with every tracker (8 s): make test-long; each tracker has its own test here
@pytest.mark.long
def test_the_logger_group_runs_every_tracker_once_per_job_of_a_sweep(tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    from physgrad.cli import main

    monkeypatch.chdir(tmp_path)
    code = main(
        [
            "run",
            "-m",
            *TINY,
            "optim=adam,gd",
            "logger=many",
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ]
    )
    assert code == 0
    assert len(list((tmp_path / "sweep").glob("*/tensorboard/events.out.tfevents.*"))) == 2
    client = MlflowClient(f"sqlite:///{tmp_path / 'outputs' / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("physgrad").experiment_id])
    assert sorted(r.data.tags["variant"] for r in runs) == ["adam", "gd"]
    assert np.all([r.info.status == "FINISHED" for r in runs])


def test_a_database_that_is_no_sqlite_file_is_one_warning_at_once(job, tmp_path, caplog):
    """An outputs/mlflow.db that cannot be opened (garbage bytes, a folder in its place): one
    warning line naming it, without MLflow's minutes of connection retries."""
    import logging

    folder, paths = job
    garbage = tmp_path / "garbage.db"
    garbage.write_bytes(b"this is not an sqlite database\x00" * 64)
    a_folder = tmp_path / "folder.db"
    a_folder.mkdir()
    for bad in (garbage, a_folder):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="physgrad"):
            track([MLflow(tracking_uri=f"sqlite:///{bad}")], paths[:1], folder)
        warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(warnings) == 1 and str(bad) in warnings[0] and "\n" not in warnings[0]


def test_a_relative_database_path_is_checked_where_mlflow_opens_it(tmp_path, monkeypatch):
    from physgrad.trackers import opens_as_sqlite

    monkeypatch.chdir(tmp_path)
    opens_as_sqlite(Path("relative.db"))  # created here, as MLflow would
    assert (tmp_path / "relative.db").is_file()
