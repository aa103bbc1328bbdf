"""Experiment trackers: the `logger` config group (off by default), as in lightning-hydra-template.

`physgrad run logger=tensorboard` (or mlflow, wandb, or several: `logger=many`) sends every results
file of a job to each tracker the group names, as one tracker run per file (per seed) when the job
has ended: every /train and /eval column as a metric against the iteration (`train/loss`,
`eval/loss`, `eval/fidelity`, ...), the stored configuration as parameters (dotted keys), the task,
variant, seed and status as tags, and the run's end status. The results file stays the source of
truth: a tracker that fails (not installed, unreachable) costs one warning line, never the run. Each
tracker is a class with log_run(run, name, folder); a config entry names it by `_target_`, so a
user's own tracker works the same way.
"""

from __future__ import annotations

import logging
import math
import os
from collections import defaultdict
from collections.abc import Iterator, Mapping
from pathlib import Path

import yaml

from physgrad.readout import config_row
from physgrad.results import Run, read_run
from physgrad.validate import call_target

log = logging.getLogger("physgrad")
TAGS = ("task", "optim", "variant", "seed", "status", "stopped_by", "unroll")


def run_metrics(run: Run) -> Iterator[tuple[str, int, float]]:
    """(key, iteration, value) of every finite value of every /train and /eval column but the
    iteration."""
    for split in ("train", "eval"):
        columns = getattr(run, split)
        if "iteration" not in columns:
            continue
        steps = columns["iteration"].tolist()
        for key, values in columns.items():
            if key == "iteration":
                continue
            for step, value in zip(steps, values.tolist()):
                if isinstance(value, (int, float)) and math.isfinite(value):
                    yield f"{split}/{key}", int(step), float(value)


def run_params(run: Run) -> dict:
    """The stored configuration flattened to dotted keys (lists as text), as a report's columns."""
    return {
        key: value if isinstance(value, (int, float, str, bool)) or value is None else str(value)
        for key, value in config_row(run).items()
    }


def run_tags(run: Run) -> dict[str, str]:
    return {key: str(run.attrs[key]) for key in TAGS if key in run.attrs}


class TensorBoard:
    """Event files for TensorBoard (written with tensorboardX, which needs no TensorFlow), in
    save_dir/<name> (default: the job folder's tensorboard/, one folder per seed): `tensorboard
    --logdir <sweep folder>` then shows every job of a sweep."""

    def __init__(self, save_dir: str | None = None) -> None:
        self.save_dir = save_dir

    def log_run(self, run: Run, name: str, folder: Path) -> None:
        from tensorboardX import SummaryWriter

        logdir = Path(self.save_dir) / name if self.save_dir else folder / "tensorboard"
        writer = SummaryWriter(logdir=str(logdir))
        try:
            writer.add_text(
                "config", "```\n" + yaml.safe_dump(run.config, sort_keys=False) + "```", 0
            )
            writer.add_text("run", ", ".join(f"{k}={v}" for k, v in run_tags(run).items()), 0)
            for key, step, value in run_metrics(run):
                writer.add_scalar(key, value, step)
        finally:
            writer.close()


MLFLOW_STATUS = {
    "completed": "FINISHED",
    "diverged": "FAILED",
    "failed": "FAILED",
    "interrupted": "KILLED",
    "refused": "KILLED",
    "crashed": "FAILED",
    "running": "RUNNING",
}


def opens_as_sqlite(path: Path) -> None:
    """ValueError (one line) unless path is, or can become, an SQLite database: MLflow retries a
    store it cannot open for minutes."""
    import contextlib
    import sqlite3

    if path.exists() and not path.is_file():
        raise ValueError(f"{path} is not a file: move it away or set logger's tracking_uri")
    try:
        uri = f"{path.resolve().as_uri()}?mode=rwc"  # MLflow reads a relative path from here
        with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
            db.execute("PRAGMA schema_version").fetchone()
    except sqlite3.Error as error:
        raise ValueError(
            f"{path} cannot be opened as an SQLite database ({error}): move it away or set "
            "logger's tracking_uri"
        ) from None


class MLflow:
    """An MLflow run per results file in `experiment_name`, in the store at tracking_uri (default:
    the local
    database outputs/mlflow.db under the folder the command runs from; `mlflow ui
    --backend-store-uri sqlite:///outputs/mlflow.db` shows it). Metrics go in batches (MLflow takes
    1000 metrics, 100 parameters per call); the run ends FINISHED (completed), FAILED (diverged,
    failed) or KILLED (interrupted, refused)."""

    def __init__(self, tracking_uri: str | None = None, experiment_name: str = "physgrad") -> None:
        self.tracking_uri = tracking_uri or f"sqlite:///{os.path.abspath('outputs/mlflow.db')}"
        self.experiment_name = experiment_name

    def log_run(self, run: Run, name: str, folder: Path) -> None:
        from mlflow.entities import Metric, Param
        from mlflow.tracking import MlflowClient

        if self.tracking_uri.startswith("sqlite:///"):
            database = Path(self.tracking_uri[len("sqlite:///") :])
            database.parent.mkdir(parents=True, exist_ok=True)
            opens_as_sqlite(database)
        client = MlflowClient(self.tracking_uri)
        experiment = client.get_experiment_by_name(self.experiment_name)
        experiment_id = (
            experiment.experiment_id
            if experiment
            else client.create_experiment(self.experiment_name)
        )
        tracked = client.create_run(
            experiment_id, run_name=name, tags={**run_tags(run), "results": str(run.path)}
        )
        run_id = tracked.info.run_id
        try:
            params = [Param(key, str(value)[:6000]) for key, value in run_params(run).items()]
            for start in range(0, len(params), 100):
                client.log_batch(run_id, params=params[start : start + 100])
            metrics = [Metric(key, value, 0, step) for key, step, value in run_metrics(run)]
            for start in range(0, len(metrics), 1000):
                client.log_batch(run_id, metrics=metrics[start : start + 1000])
        finally:
            client.set_terminated(run_id, MLFLOW_STATUS.get(str(run.attrs.get("status")), "FAILED"))


class WandB:
    """A Weights & Biases run per results file, offline by default (mode: offline | online |
    disabled): the run is written under dir (default: the job folder) as wandb/offline-run-*, for
    `wandb sync` later. Rows are logged per iteration (train and eval columns of one iteration
    together: W&B needs its steps in order)."""

    def __init__(
        self,
        project: str = "physgrad",
        mode: str = "offline",
        dir: str | None = None,
        entity: str | None = None,
    ) -> None:
        self.project, self.mode, self.dir, self.entity = project, mode, dir, entity

    def log_run(self, run: Run, name: str, folder: Path) -> None:
        import wandb

        by_step = defaultdict(dict)
        for key, step, value in run_metrics(run):
            by_step[step][key] = value
        tracked = wandb.init(
            project=self.project,
            entity=self.entity,
            name=name,
            mode=self.mode,
            dir=str(self.dir or folder),
            config=run_params(run),
            tags=[f"{k}={v}" for k, v in run_tags(run).items()][:64],
            reinit="finish_previous",
            settings=wandb.Settings(silent=True),
        )
        try:
            for step in sorted(by_step):
                tracked.log(by_step[step], step=step)
            tracked.summary["status"] = str(run.attrs.get("status"))
        finally:
            tracked.finish(exit_code=0 if run.attrs.get("status") == "completed" else 1)
            # W&B's service process writes the run on its own schedule (measured: the history
            # reached the offline log only when the process ended): ending the service makes the run
            # whole on disk now
            wandb.teardown()
        if self.mode == "offline":
            log.info("W&B offline run of %s in %s: upload it with `wandb sync`", name, tracked.dir)


def build_trackers(settings: Mapping[str, Mapping]) -> list:
    """The trackers of logger=... (name -> the settings of one, with its _target_, as the door
    checked them: physgrad.job_spec.tracker_settings); UserError (one line) for an entry that
    cannot be built."""
    return [call_target(f"logger.{name}", node) for name, node in settings.items()]


def track(trackers: list, paths: list[Path], job_folder: Path) -> None:
    """Each results file to each tracker; a failure is one warning line (the results file has it
    all)."""
    for path in paths:
        try:
            run = read_run(path)
        except ValueError as error:
            log.warning("not sent to the trackers: %s", error)
            continue
        seed = f"seed={run.attrs.get('seed')}"
        name = f"{job_folder.name}/{seed}" if path.parent != job_folder else job_folder.name
        for tracker in trackers:
            try:
                tracker.log_run(run, name, path.parent)
            except Exception as error:  # noqa: BLE001 - a tracker is never worth the run
                log.warning(
                    "%s could not log %s: %s: %s",
                    type(tracker).__name__,
                    path,
                    type(error).__name__,
                    str(error).splitlines()[0] if str(error) else "",
                )
