"""A sweep's jobs on SLURM (docs/cluster.md): physgrad's commands run
`hydra/launcher=submitit_slurm` through physgrad's subclass of submitit's launcher
(hydra_plugins.physgrad_launchers.slurm), which sends the jobs as one job array as submitit's
does, and then:
- waits for every job, a job that SLURM puts back in the queue (a lost node, JobRequeue) until it
  ends again: one that ends without a result (scancel of a waiting job, SIGKILL after the
  scheduler's grace period, a lost node without a requeue) is recorded in the sweep with its
  SLURM id and state, and the others go on (submitit's launcher stops the whole sweep at the
  first such job);
- at a stop of the sweep (a signal to the launching command, or the end of `physgrad compare`
  above it), cancels the tasks of the array still waiting, instead of starting them to be skipped.
A job's own signal (scancel, its time limit, preemption, submitit's SIGUSR2 warning) ends that job
alone, `interrupted`, its rows kept (physgrad.experiment, physgrad.interrupts).
"""

from __future__ import annotations

import dataclasses
import logging
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from physgrad.errors import LauncherRefused
from physgrad.files import clean_text
from physgrad.sweeps import ON_STOP, job_states, record_job

log = logging.getLogger("physgrad")


def own_submitit_folder(template: str) -> str:
    """submitit's folder for this launch. submitit unpickles each job's result from it, so a pickle
    planted there by whoever wrote a sweep folder would run as code: the template's folder (before
    its %j, `<sweep>/.submitit` by default) must be the user's own and not a link, and the jobs'
    files go into a folder created in it for this launch alone (mode 0700; %j below it).
    LauncherRefused (one line) otherwise."""
    import os
    import stat

    base, jobs, rest = template.partition("%j")
    parent = Path(base)
    parent.mkdir(parents=True, exist_ok=True)
    found = os.lstat(parent)
    link = stat.S_ISLNK(found.st_mode)
    if link or found.st_uid != os.getuid():
        raise LauncherRefused(
            f"{parent}: submitit's folder is {'a link' if link else 'not yours'}"
            ": refused (a sweep folder may come from someone else); remove it or set "
            "hydra.launcher.submitit_folder"
        )
    stamp, number = time.strftime("%Y%m%dT%H%M%S"), 0
    while True:
        own = parent / (f"{stamp}-{os.getpid()}" + (f"-{number}" if number else ""))
        try:
            own.mkdir(mode=0o700)  # exclusively: a folder left there is someone's, not ours
            break
        except FileExistsError:
            number += 1
    return str(own / f"{jobs}{rest}") if jobs else str(own)


def launch_array(launcher: Any, job_overrides: Sequence[Sequence[str]], first: int) -> list:
    """The jobs as one SLURM job array (submitit), each job's result in turn: the job's return
    value, or, for a job that ended without one, infinity with the job recorded in the sweep as
    `not run` or `killed` (its SLURM id and state); the array's waiting tasks are cancelled at a
    stop of the sweep (physgrad.sweeps.ON_STOP)."""
    import submitit
    from hydra.core.singleton import Singleton
    from hydra.core.utils import JobReturn, JobStatus, filter_overrides
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf

    sweep = Path(str(launcher.config.hydra.sweep.dir))
    sweep.mkdir(parents=True, exist_ok=True)
    calls = []
    for number, overrides in enumerate(job_overrides, start=first):
        log.info("\t#%d : %s", number, " ".join(filter_overrides(overrides)))
        calls.append(
            (
                list(overrides),
                "hydra.sweep.dir",
                number,
                f"job_id_for_{number}",
                Singleton.get_state(),
            )
        )
    try:
        params = dict(launcher.params)
        executor = submitit.AutoExecutor(
            cluster="slurm",
            folder=params.pop("submitit_folder"),
            slurm_max_num_timeout=params.pop("max_num_timeout", 0),
        )
        shared = {field.name for field in dataclasses.fields(BaseQueueConf)}
        executor.update_parameters(
            **{key if key in shared else f"slurm_{key}": value for key, value in params.items()}
        )
        jobs = executor.map_array(launcher, *zip(*calls))
    except (
        RuntimeError,  # submitit finding no srun
        OSError,
        subprocess.SubprocessError,
        submitit.core.utils.FailedJobError,
        submitit.core.utils.FailedSubmissionError,
    ) as error:
        # no srun or sbatch, sbatch refusing the array, or an answer naming no job: their words
        lines = [line.strip() for line in str(error).splitlines() if line.strip()]
        why = lines[0] if lines else type(error).__name__
        raise LauncherRefused(
            f"SLURM did not take the sweep's {len(calls)} jobs: {clean_text(why, 300)} (check "
            "hydra.launcher's partition, account and limits, and that sbatch runs here)"
        ) from None
    if jobs:
        log.info("SLURM job array %s: %d jobs", array_id(jobs[0].job_id), len(jobs))
        ON_STOP.append(lambda: cancel_waiting(jobs))
    returns = []
    for job, overrides in zip(jobs, job_overrides):
        outcome = job_result(job)
        if isinstance(outcome, Exception):
            record_lost_job(sweep, list(overrides), job.job_id, job.state, outcome)
            outcome = JobReturn(
                overrides=list(overrides), _return_value=float("inf"), status=JobStatus.COMPLETED
            )
        returns.append(outcome)
    return returns


# states after which SLURM may put a job back in the queue (JobRequeue, preemption by requeue)
REQUEUED_AFTER = frozenset({"NODE_FAIL", "BOOT_FAIL", "PREEMPTED", "REQUEUED"})
# a job in slurmctld's queue with one of these states has not ended (squeue prints a flag such as
# COMPLETING, STAGE_OUT or SIGNALING before the base state: a job winding down after its end shows
# them, so they decide nothing)
QUEUED = frozenset(
    {"PENDING", "CONFIGURING", "RUNNING", "SUSPENDED", "STOPPED", "RESIZING", "REQUEUED"}
    | {"REQUEUE_HOLD", "REQUEUE_FED", "SPECIAL_EXIT", "RESV_DEL_HOLD"}
)


def job_result(job: Any, patience: float = 60.0, poll: float = 2.0) -> Any:
    """A submitit job's result, or the exception of a job that ended without one. submitit reads
    the state from the accounting (sacct), which says NODE_FAIL for a job on a lost node before,
    or while, slurmctld puts it back in the queue: so a job that ended without a result (no
    result or error file of submitit's) is asked of slurmctld (squeue), for up to `patience`
    seconds after a state that a requeue follows, and one that is queued again is waited for
    again."""
    while True:
        try:
            return job.results()[0]
        except Exception as error:  # noqa: BLE001 - one job's end is not the sweep's
            if job.paths.result_pickle.exists():  # it ended with its own outcome, an error
                return error
            wait = patience if str(job.state).upper() in REQUEUED_AFTER else 0.0
            if not queued_again(job.job_id, wait, poll):
                return error
            log.warning(
                "SLURM job %s was put back in the queue (%s): waiting for it", job.job_id, job.state
            )
            job.watcher.clear()  # submitit keeps a finished job finished
            time.sleep(poll)


def queued_again(job_id: str, patience: float, poll: float = 2.0) -> bool:
    """Whether slurmctld holds the job in its queue, not ended (QUEUED), within `patience` s."""
    deadline = time.monotonic() + patience
    while True:
        try:
            found = subprocess.run(
                ["squeue", "-h", "-j", str(job_id), "-o", "%T"],
                check=False,
                capture_output=True,
                text=True,
                timeout=60,
            ).stdout.split()
        except (OSError, subprocess.SubprocessError):  # no answer: taken as not queued
            found = []
        if any(state.upper() in QUEUED for state in found):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll)


def array_id(job_id: str) -> str:
    """The array's id of a task's id (`123_4`: 123)."""
    return str(job_id).partition("_")[0]


def cancel_waiting(jobs: list) -> None:
    """scancel of the array's tasks still waiting (running ones stop themselves at the sweep's stop
    mark, ending interrupted with their rows)."""
    ids = sorted({array_id(job.job_id) for job in jobs})
    subprocess.run(
        ["scancel", "--state=PENDING", *ids], check=False, capture_output=True, timeout=60
    )
    log.warning("cancelled the waiting jobs of SLURM job array %s", ", ".join(ids))


def record_lost_job(
    sweep: Path, overrides: list[str], job_id: str, state: str, error: Exception
) -> None:
    """A job that ended without a result, in the sweep's job states (where the job recorded nothing
    itself: it never started, or was killed before it could): `not run` (cancelled or failed
    waiting) or `killed`, with its SLURM id and state."""
    known = job_states(sweep).get(frozenset(overrides))
    log.warning("SLURM job %s ended without a result (%s): %s", job_id, state, error)
    if known is not None and known["state"] != "started":
        return  # it ended itself (interrupted, failed): its own record says how
    folder = Path(known["folder"]) if known is not None else sweep / f".slurm-{job_id}"
    what = "killed" if known is not None else "not run"
    record_job(sweep, folder, overrides, what, f"SLURM state {state}", scheduler=job_id)
