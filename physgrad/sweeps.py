"""What a sweep knows about its jobs and how it stops.

A sweep folder holds `jobs.yaml`, the manifest of the jobs the basic sweeper will launch (each a
list of overrides, as in the job folder's `.hydra/overrides.yaml`), so that the end-of-sweep summary
and `physgrad report` can name jobs that never started or left no results file. Stopping: the
process that launched the sweep handles SIGINT and SIGTERM by writing `.physgrad-stop` into the
sweep folder (how many signals it got); every job watches that file and its launcher (a job in a
worker process stops when the launcher is gone), so a signal to the launcher alone stops every
launcher's workers after their current step, a second one at once, and no job starts after it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

import yaml
from omegaconf import DictConfig, OmegaConf

from physgrad.files import (
    clean_text,
    inside,
    make_folder,
    owner_alive,
    owner_tag,
    read_own_file,
    read_small_yaml,
    replace_file,
    timestamp,
    walk_files,
)
from physgrad.interrupts import StopRequest, handling_signals, take_lost

log = logging.getLogger("physgrad")
MANIFEST = "jobs.yaml"
STOP_MARK = ".physgrad-stop"
# "<pid> <host>" of the process that launched the sweep, inherited by its workers (and by a
# scheduler's jobs on other hosts, where the same pid is another process)
LAUNCHER_ENV = "PHYSGRAD_SWEEP_LAUNCHER"
# pid of the `physgrad compare` whose phase this sweep is: the sweep stops when that process ends
STUDY_ENV = "PHYSGRAD_STUDY"
# what a launcher asks to be done at a sweep's stop (physgrad's SLURM launcher: cancel its waiting
# jobs), called once, at the first signal
ON_STOP: list = []
WATCH_SECONDS = 0.25


def expected_jobs(config: DictConfig) -> list[list[str]] | None:
    """The jobs Hydra's basic sweeper will launch for this config (hydra.sweeper.params, then the
    command line), each a list of overrides; None for another sweeper (Optuna decides its trials as
    it goes)."""
    if not str(config.hydra.sweeper.get("_target_", "")).endswith(".BasicSweeper"):
        return None
    # unresolved: Hydra keeps an override's `${seed}` as written, so must the manifest to match the
    # job folders
    params = config.hydra.sweeper.get("params")
    params = OmegaConf.to_container(params, resolve=False) if params else {}
    overrides = OmegaConf.to_container(config.hydra.overrides.task, resolve=False)
    try:
        return sweep_jobs([f"{key}={value}" for key, value in params.items()] + overrides)
    except Exception as error:  # noqa: BLE001 - Hydra reports these itself when it sweeps
        log.debug("no manifest: %s", error)
        return None


def sweep_jobs(arguments: list[str]) -> list[list[str]]:
    """Expand sweep overrides (`optim=adam,hig seed=0,1`; a later key replaces an earlier one) into
    the basic sweeper's jobs, each a list of overrides, in its order."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = OverridesParser.create().parse_overrides(arguments)
    return [job for batch in BasicSweeper.split_arguments(overrides, None) for job in batch]


def write_manifest(folder: Path, jobs: list[list[str]]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    replace_file(
        folder / MANIFEST,
        yaml.safe_dump({"jobs": jobs}, default_flow_style=None, width=1000).encode(),
    )


def _overrides(listed: object) -> list[str] | None:
    """A list of overrides read from a file (each a scalar), as text; None if it is not one."""
    plain = isinstance(listed, list) and all(
        isinstance(item, (str, int, float, bool)) for item in listed
    )
    return list(map(str, listed)) if plain else None


def read_manifest(folder: Path) -> list[list[str]] | None:
    try:
        jobs = [_overrides(job) for job in read_small_yaml(folder / MANIFEST)["jobs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None if None in jobs else jobs


def job_folders(folder: Path) -> dict[frozenset, Path]:
    """Job folder by its set of overrides, from the `.hydra/overrides.yaml` Hydra writes when a job
    starts."""
    found = {}
    for overrides in walk_files(folder, "overrides.yaml"):
        if overrides.parent.name != ".hydra":
            continue
        try:
            listed = _overrides(read_small_yaml(overrides, 1 << 16) or [])
        except (OSError, ValueError):
            continue
        if listed is not None:
            found[frozenset(listed)] = overrides.parent.parent
    return found


def scheduler_job() -> str | None:
    """This job's id at its scheduler (SLURM: `<array job>_<task>` for a job array), or None."""
    array, task = os.environ.get("SLURM_ARRAY_JOB_ID"), os.environ.get("SLURM_ARRAY_TASK_ID")
    if array and task:
        return f"{array}_{task}"
    return os.environ.get("SLURM_JOB_ID")


JOB_STATES = ".physgrad-jobs"  # in the sweep folder: one small YAML file per job that started


def record_job(
    sweep: Path,
    job_folder: Path,
    overrides: list[str],
    state: str,
    reason: str | None = None,
    scheduler: str | None = None,
) -> None:
    """The job's state (started, or its outcome) and reason in the sweep folder, where it can be
    written even when the job's own folder cannot; written by rename; with the scheduler's id of
    the job (scheduler, else this process's: scheduler_job). A failure to write it is logged, not
    raised."""
    name = hashlib.sha1(str(job_folder.resolve()).encode()).hexdigest()[:16]
    record = {
        "folder": str(job_folder),
        "overrides": [str(o) for o in overrides],
        "state": state,
        "reason": reason,
        "owner": owner_tag(),
        "scheduler": scheduler or scheduler_job(),
        "time": timestamp(),
    }
    try:
        make_folder(sweep / JOB_STATES)
        replace_file(
            sweep / JOB_STATES / f"{name}.yaml", yaml.safe_dump(record, width=1000).encode()
        )
    except OSError as error:
        log.warning("the state of %s was not recorded: %s", job_folder, error.strerror or error)


def job_states(sweep: Path) -> dict[frozenset, dict]:
    """The recorded state of every job of the sweep that started, by its set of overrides (checked
    as data)."""
    found = {}
    for path in sorted((sweep / JOB_STATES).glob("*.yaml")):
        try:
            record = read_small_yaml(path, 1 << 16)
        except (OSError, ValueError):
            continue
        overrides = _overrides(record.get("overrides")) if isinstance(record, dict) else None
        if overrides is not None and isinstance(record.get("state"), str):
            found[frozenset(overrides)] = {
                "state": clean_text(record["state"], 40),
                "reason": clean_text(str(record.get("reason") or ""), 300),
                "folder": clean_text(str(record.get("folder", "")), 500),
                "owner": str(record.get("owner", "")),
                "scheduler": clean_text(str(record.get("scheduler") or ""), 40),
            }
    return found


def unfinished_jobs(folder: Path, interrupted: bool = False) -> list[tuple[str, str]]:
    """The jobs that left no results file (interrupted: or left it interrupted), from the manifest
    and the recorded job states: (their overrides joined by commas, why: `never started`,
    `failed: <reason>` or `interrupted: <reason>` as recorded, `crashed` for a job recorded as
    started whose process is gone, `no results file`; with the scheduler's job id where it ran under
    one)."""
    jobs, states, missing = read_manifest(folder) or [], job_states(folder), []
    folders = job_folders(folder)
    for job in [*jobs, *[sorted(key) for key in states if sorted(key) not in map(sorted, jobs)]]:
        state, where = states.get(frozenset(job)), folders.get(frozenset(job))
        if state is not None and inside(Path(state["folder"] or "/"), folder):
            where = Path(state["folder"])  # a record saying /usr is someone else's: not walked
        # a job's file: its results, or the step costs of a study's calibration job
        ended = (
            where is not None
            and where.is_dir()
            and (any(walk_files(where, "results.h5")) or (where / "calibration.json").is_file())
        )
        if ended and not (interrupted and state is not None and state["state"] == "interrupted"):
            continue
        if state is None:
            why = "never started" if where is None else "no results file"
        elif state["state"] == "started":
            gone = owner_alive(state["owner"]) is False
            why = "crashed before writing results" if gone else "started, no results yet"
        else:
            why = ": ".join(filter(None, (state["state"], state["reason"])))
        at = f" (SLURM job {state['scheduler']})" if state and state.get("scheduler") else ""
        missing.append((",".join(job), why + at))
    return missing


def stop_count(sweep: Path) -> tuple[str, int] | None:
    """(signal name, how many) if the sweep was asked to stop."""
    try:  # a mark in a folder from someone else: no link followed, no FIFO waited on
        name, count = read_own_file(sweep / STOP_MARK, 64).decode().split()
        return name, int(count)
    except (OSError, ValueError):
        return None


def mark_stopped(sweep: Path, name: str, count: int = 1) -> None:
    """Tell every job of the sweep to stop (count >= 2: at once); written by rename, so never read
    half."""
    previous = stop_count(sweep)
    count = max(count, previous[1] if previous else 0)
    try:
        replace_file(sweep / STOP_MARK, f"{name} {count}\n".encode())
    except OSError as error:
        log.warning(
            "could not tell the sweep's jobs to stop (%s): stop the workers themselves", error
        )


def launcher_pid() -> int | None:
    """The pid of the process that launched this sweep, where it runs on this host; else None."""
    pid, _, host = os.environ.get(LAUNCHER_ENV, "").partition(" ")
    return int(pid) if pid.isdigit() and host == socket.gethostname() else None


def in_launcher() -> bool:
    """Whether this process launched the sweep it runs a job of (Hydra's basic launcher runs its
    jobs in that process): a signal to it is the user's, for the whole sweep. A job in a worker
    (joblib, a scheduler's job) takes its own signal for itself: a scheduler sends scancel, time
    limits and preemption to one job."""
    return launcher_pid() == os.getpid()


def cancel_waiting() -> None:
    """What launchers registered in ON_STOP, each once; a failure is logged."""
    while ON_STOP:
        action = ON_STOP.pop()
        try:
            action()
        except Exception as error:  # noqa: BLE001 - stopping goes on
            log.warning("could not cancel the sweep's waiting jobs: %s", error)


class LauncherSignals:
    """The launching process's handler for SIGINT and SIGTERM during a sweep: mark the sweep stopped
    (its jobs, in this process or in workers, see it); a third signal ends the launcher at once
    (KeyboardInterrupt)."""

    def __init__(self, sweep: Path) -> None:
        self.sweep, self.received = sweep, 0

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.received += 1
        name = signal.Signals(signum).name
        mark_stopped(self.sweep, name, self.received)
        if self.received == 1:
            log.warning(
                "%s: stopping the sweep: running jobs end after their current step and are "
                "recorded as interrupted, waiting jobs are cancelled or do not start (send it "
                "again to end running steps at once)",
                name,
            )
            cancel_waiting()
        elif self.received >= 3:
            raise KeyboardInterrupt(name)


def end_with_study() -> None:
    """In a sweep that `physgrad compare` launched (STUDY_ENV: its pid), a SIGTERM to this process
    when that one ends, however it ends (SIGKILL too: Linux's parent-death signal), taken as a stop
    of the sweep (LauncherSignals: running jobs end interrupted, waiting ones are cancelled), so
    that nothing goes on submitting and waiting for a study nobody runs."""
    study = os.environ.pop(STUDY_ENV, "")
    if not study.isdigit() or not sys.platform.startswith("linux"):
        return
    import ctypes

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)
    if os.getppid() != int(study):  # it ended before the line above
        os.kill(os.getpid(), signal.SIGTERM)


@contextmanager
def launcher_signals(sweep: Path) -> Iterator[None]:
    """LauncherSignals handling SIGINT and SIGTERM in the process that launches the sweep (its main
    thread), whose pid its workers inherit (LAUNCHER_ENV)."""
    handler = LauncherSignals(sweep)
    with handling_signals(handler) as installed:
        if not installed:  # not the main thread
            yield
            return
        lost = take_lost()  # one kept while Hydra composed the sweep (physgrad.interrupts)
        if lost is not None:
            handler(signal.Signals[lost], None)
        os.environ[LAUNCHER_ENV] = f"{os.getpid()} {socket.gethostname()}"
        end_with_study()
        try:
            yield
        finally:
            os.environ.pop(LAUNCHER_ENV, None)
            ON_STOP.clear()


@contextmanager
def watching(sweep: Path | None, stop: StopRequest) -> Iterator[None]:
    """While a job of a sweep runs: a thread that passes the sweep's stop mark on to the job's
    StopRequest (physgrad.interrupts), and, in a launcher's worker process, the launcher's end (its
    parent changes) as a SIGTERM."""
    if sweep is None:
        yield
        return
    launcher = launcher_pid()
    watch_parent = launcher is not None and launcher != os.getpid() and launcher == os.getppid()
    parent, finished = os.getppid(), threading.Event()

    def watch() -> None:
        while not finished.wait(WATCH_SECONDS):
            mark = stop_count(sweep)
            if mark is not None:
                stop.request(mark[0], at_once=mark[1] >= 2)
            if watch_parent and os.getppid() != parent:
                stop.request("SIGTERM (the sweep's launcher ended)")

    thread = threading.Thread(target=watch, daemon=True, name="physgrad-sweep-watch")
    thread.start()
    try:
        yield
    finally:
        finished.set()
