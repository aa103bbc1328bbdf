"""The Hydra application behind `physgrad run`: one job = one (task, optim, seed, ...)
configuration."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

# files.replace_file looked up when called: every renamed write goes through it (the fault tests
# fill the disk there)
import physgrad.files as files

# the resolver of hydra.sweep.subdir (physgrad_job_folder), registered before Hydra composes a job
import physgrad.sweep_hooks  # noqa: E402, F401, I001
from physgrad.configs import CONF_DIR, name_options
from physgrad.errors import UserError, innermost_cause
from physgrad.experiment import run_job
from physgrad.files import make_folder, own_folder
from physgrad.gpus import claim_gpu
from physgrad.interrupts import raising_interrupts, stop_on_signals
from physgrad.job_spec import Calibration, JobSpec, calibration_of, check
from physgrad.results import member_order, read_final
from physgrad.runner import Outcome
from physgrad.sweeps import record_job, stop_count
from physgrad.timing import write_calibration_of
from physgrad.trackers import build_trackers, track

log = logging.getLogger("physgrad")


def save_traceback(folder: Path) -> Path | None:
    """The current exception's traceback in folder/error.txt (None if it cannot be written
    either)."""
    import traceback

    try:
        folder.mkdir(parents=True, exist_ok=True)
        # beside and renamed: a link planted at error.txt is replaced, not written through
        files.replace_file(folder / "error.txt", traceback.format_exc().encode())
        return folder / "error.txt"
    except OSError:
        return None


def write_provenance(out_dir: Path, cfg: DictConfig, hydra_cfg: DictConfig) -> None:
    """What Hydra writes into .hydra/ when hydra.output_subdir is set (config.yaml, hydra.yaml,
    overrides.yaml), written here instead, once the job holds its folder: a second process refused
    for that folder must not replace a live job's record of how it was started."""
    folder = make_folder(out_dir / ".hydra")
    hydra_node = OmegaConf.create({"hydra": OmegaConf.to_container(hydra_cfg, resolve=False)})
    for name, node in (
        ("config.yaml", cfg),
        ("hydra.yaml", hydra_node),
        ("overrides.yaml", OmegaConf.create(list(hydra_cfg.overrides.task))),
    ):
        files.replace_file(folder / name, OmegaConf.to_yaml(node).encode())


SEED_LINES = 8


def seed_lines(folder: Path) -> list[str]:
    """For a job of several seeds (folder/seed=<s>/results.h5): each seed's status and test loss,
    the first SEED_LINES of them, then the median [min, max] over all that completed."""
    rows = []
    for path in sorted(folder.glob("seed=*/results.h5"), key=member_order):
        try:
            attrs, last = read_final(path)
        except ValueError as error:
            rows.append((path.parent.name, "unreadable", None, str(error)))
            continue
        rows.append(
            (
                path.parent.name.replace("=", " "),
                attrs["status"],
                last.get("loss"),
                attrs.get("reason"),
            )
        )
    lines = [
        f"  {seed}: {status}"
        + (f", test loss {loss:.4g}" if loss is not None and status == "completed" else "")
        + (f" ({why})" if why and status != "completed" else "")
        for seed, status, loss, why in rows[:SEED_LINES]
    ]
    losses = [loss for _, status, loss, _ in rows if status == "completed" and loss is not None]
    if len(rows) > SEED_LINES and losses:
        lines.append(
            f"  test loss over the {len(losses)} of {len(rows)} seeds that completed: median "
            f"{float(np.median(losses)):.4g} [{min(losses):.4g}, {max(losses):.4g}]"
        )
    return lines


def objective(outcome: Outcome) -> float:
    """What the job returns to a sweeper that optimises: the final VALIDATION loss of a completed
    run (trainer.validation=true; a budgeted run's last evaluation is at its budget), never the test
    loss, which verdicts read; infinity for anything else (no validation data, diverged, refused,
    failed), so such a trial ranks last instead of stopping the study."""
    loss = outcome.final_eval.get("validation_loss") if outcome.status == "completed" else None
    return float(loss) if loss is not None else float("inf")


@dataclass
class Job:
    """One job of `physgrad run` as Hydra started it: its label (task/optim seeds), its folder, the
    sweep's folder (None for a single run), its overrides, and whether it held its folder."""

    name: str
    out_dir: Path
    sweep: Path | None
    overrides: list[str]
    owned: bool = False  # set once the job holds its folder: only then is anything written there

    @property
    def multirun(self) -> bool:
        return self.sweep is not None


def job_of(cfg: DictConfig, hydra_cfg: DictConfig) -> Job:
    """The job Hydra started, its task and optim named after their options."""
    # a scene or optimiser named by _target_ may live in the folder the command was started from,
    # also when a launcher runs this job in another process
    if hydra_cfg.runtime.cwd not in sys.path:
        sys.path.append(hydra_cfg.runtime.cwd)
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    name_options(cfg, hydra_cfg.runtime.choices)
    count = cfg.get("seeds", 1)
    seeds = (
        f"seeds {cfg.seed}-{cfg.seed + count - 1}"
        if isinstance(count, int) and isinstance(cfg.seed, int) and count > 1
        else f"seed {cfg.seed}"
    )
    return Job(
        name=f"{cfg.task.get('name')}/{cfg.optim.get('name')} {seeds}",
        out_dir=Path(hydra_cfg.runtime.output_dir),
        sweep=Path(hydra_cfg.sweep.dir) if multirun else None,
        overrides=[str(o) for o in hydra_cfg.overrides.task],
    )


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def job(cfg: DictConfig) -> float:
    """One job of `physgrad run`: not started in a stopped sweep, its config checked at the door
    (physgrad.job_spec.check: below it nothing reads the config), its trackers built, the run
    (run_job: a refused job's files say why), then its record in the sweep, its trackers fed and its
    end told; returns what a sweeper optimises (objective). A single run exits 2 when refused, 1
    when failed, 130 when interrupted. Up to the door, where OmegaConf still builds and reads
    nodes, a signal is kept for the job's first check (cli's composing()); past it signals raise
    again."""
    hydra_cfg = HydraConfig.get()
    claim_gpu(int(hydra_cfg.job.get("num") or 0))  # before jax starts: one GPU per job process
    this = job_of(cfg, hydra_cfg)
    stopped = stop_count(this.sweep) if this.sweep is not None else None
    if stopped is not None:
        log.warning("%s not started: the sweep was stopped (%s)", this.name, stopped[0])
        return float("inf")
    try:
        calibration = calibration_of(cfg)
    except UserError as error:
        return job_failed(this, error)
    if calibration is not None:
        return calibration_job(calibration, this)
    spec = check(cfg)
    with raising_interrupts():
        return checked_job(spec, this, cfg, hydra_cfg)


def checked_job(spec: JobSpec, this: Job, cfg: DictConfig, hydra_cfg: DictConfig) -> float:
    """A job past the door: its trackers built, the run, its record and its end (job)."""
    trackers = job_trackers(spec.trackers, this)
    if trackers is None:
        return float("inf")

    def on_owned() -> None:  # the job folder is held: only now is anything written into it
        this.owned = True
        write_provenance(this.out_dir, cfg, hydra_cfg)
        if this.sweep is not None:
            record_job(this.sweep, this.out_dir, this.overrides, "started")

    try:
        outcome, path = run_job(spec, this.out_dir, this.sweep, on_owned)
    except Exception as error:  # noqa: BLE001 - one line, the traceback in the job folder; a sweep goes on
        return job_failed(this, error)
    if this.owned:  # a job refused because another process holds its folder records nothing
        record_and_track(this, outcome, trackers)
    return job_ended(this, outcome, path)


def calibration_job(calibration: Calibration, this: Job) -> float:
    """A study's calibration as one of its jobs, so that the step costs are measured where the jobs
    run: the step costs of the calibration's configs ({variant: config}) on its seed
    (physgrad.timing.calibrate, with the host and device) into the job folder's calibration.json. A
    signal ends it at once, interrupted (no file)."""
    try:
        with own_folder(this.out_dir), stop_on_signals() as stop:
            this.owned = True
            if this.sweep is not None:
                record_job(this.sweep, this.out_dir, this.overrides, "started")
            stop.raising = True
            stop.raise_if_stopped()
            path = write_calibration_of(calibration.configs, calibration.seed, this.out_dir)
            stop.raising = False
    except KeyboardInterrupt as interrupt:
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} while calibrating"
        if this.sweep is not None and this.owned:
            record_job(this.sweep, this.out_dir, this.overrides, "interrupted", why)
        log.warning("calibration interrupted: %s", why)
        return float("inf")
    except Exception as error:  # noqa: BLE001 - one line, the traceback in the job folder
        return job_failed(this, error)
    if this.sweep is not None:
        record_job(this.sweep, this.out_dir, this.overrides, "completed")
    log.info("calibrated the step costs of %d variants -> %s", len(calibration.configs), path)
    return 0.0


def job_trackers(settings: dict[str, dict], this: Job) -> list | None:
    """The experiment trackers of logger=... (their settings, checked at the door); None when one
    cannot be built (the job is skipped in a sweep; a single run exits 2)."""
    try:
        return build_trackers(settings)
    except UserError as error:
        if not this.multirun:
            print(f"physgrad: error: {error}", file=sys.stderr)
            sys.exit(2)
        log.warning("%s skipped: %s", this.name, error)
        return None


def job_failed(this: Job, error: Exception) -> float:
    """A job that raised: one line (the traceback in the job folder's error.txt), recorded in the
    sweep, which goes on; a single run exits 1. Called while the error is handled."""
    where = save_traceback(this.out_dir) if this.owned else None
    if isinstance(error, OSError):  # the results file could not be written (disk full, permissions)
        message = str(error).splitlines()[0]
        if not this.owned:
            message = f"cannot write the job folder {this.out_dir}: {error.strerror or message}"
    else:
        message = innermost_cause(error)
    message += f" (traceback: {where})" if where else ""
    if this.sweep is not None:
        record_job(this.sweep, this.out_dir, this.overrides, "failed", message)
    if not this.multirun:
        print(f"physgrad: error: {this.name} failed: {message}", file=sys.stderr)
        sys.exit(1)
    log.error("%s failed: %s", this.name, message)
    return float("inf")


def record_and_track(this: Job, outcome: Outcome, trackers: list) -> None:
    """For a job that held its folder: its outcome in the sweep's record, and its results files
    sent to the experiment trackers."""
    if this.sweep is not None:
        record_job(this.sweep, this.out_dir, this.overrides, outcome.status, outcome.reason)
    if trackers:
        track(
            trackers,
            [
                p
                for p in [
                    this.out_dir / "results.h5",
                    *sorted(this.out_dir.glob("seed=*/results.h5")),
                ]
                if p.is_file()
            ],
            this.out_dir,
        )


def job_ended(this: Job, outcome: Outcome, path: Path) -> float:
    """The job's end told: a refused job's reason (a single run exits 2), else one line of how it
    ended, each seed's for several; a single run that was interrupted exits 130."""
    if outcome.status == "refused":
        if not this.multirun:
            print(f"physgrad: error: {outcome.reason}", file=sys.stderr)
            sys.exit(2)
        log.warning("%s skipped: %s", this.name, outcome.reason)
        return objective(outcome)
    test = outcome.final_eval.get("loss") if outcome.status == "completed" else None
    stopped = f" (stopped by {outcome.stopped_by.replace('_', ' ')})" if outcome.stopped_by else ""
    log.info(
        "%s %s after %d iterations%s, %.1f s of training%s%s -> %s",
        this.name,
        outcome.status,
        outcome.iterations,
        stopped,
        outcome.train_seconds,
        f", test loss {test:.4g}" if test is not None else "",
        f" ({outcome.reason})" if outcome.reason else "",
        path,
    )
    for line in seed_lines(path) if path.is_dir() else ():
        log.info("%s", line)
    if outcome.status == "interrupted" and not this.multirun:
        sys.exit(130)  # in a sweep, the others are told (physgrad.sweeps)
    return objective(outcome)
