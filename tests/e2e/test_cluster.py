"""End-to-end layer of what a cluster does to a study, on the local launchers: a signal to one
worker ends its job alone, a killed `physgrad compare` leaves no sweep running and resumes, a rerun
launches only the unfinished jobs, physgrad's SLURM launcher waits for every job and cancels the
waiting ones, and the cluster harness ends only its own job steps."""

from __future__ import annotations

import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from physgrad.sweeps import job_states

PHYSGRAD = [sys.executable, "-m", "physgrad"]


def wait_for(what: str, test, seconds: float = 120.0):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        value = test()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"waited {seconds:.0f} s for {what}")


def started_pids(sweep: Path) -> dict[str, int]:
    """The pid of every job recorded as started in the sweep, by its optim override."""
    found = {}
    for path in (sweep / ".physgrad-jobs").glob("*.yaml"):
        record = yaml.safe_load(path.read_text())
        if record["state"] == "started" and (sweep / Path(record["folder"]).name).is_dir():
            optim = next(o for o in record["overrides"] if o.startswith("optim="))
            found[optim] = int(re.match(r"pid (\d+)", record["owner"])[1])
    return found


# SIGUSR2 (the scheduler's warning) in make test-long: the same path as SIGTERM to the job
@pytest.mark.long  # a fault at a random instant (make test-cluster sends scancel to one job)
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGUSR2])
def test_a_signal_to_one_worker_ends_that_job_alone(tmp_path, signum):
    """A joblib worker's job given SIGTERM (scancel, preemption) or SIGUSR2 (a scheduler's warning
    before a time limit) at a random instant of its training ends interrupted with its rows; the
    other job goes on to its end; the sweep exits 1 and names the interrupted job."""
    sweep = tmp_path / "sweep"
    process = subprocess.Popen(
        [
            *PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "optim=adam,gd",
            "trainer.iterations=100000000",
            "trainer.time_budget=4",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            f"hydra.sweep.dir={sweep}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        pids = wait_for(
            "both jobs started", lambda: (p := started_pids(sweep)).__len__() == 2 and p
        )
        wait_for("adam training", lambda: list(sweep.glob("*optim=adam*/results.h5")))
        time.sleep(random.uniform(0.2, 2.0))
        subprocess.run(["kill", f"-{signal.Signals(signum).name[3:]}", str(pids["optim=adam"])])
        out, _ = process.communicate(timeout=180)
    finally:
        process.kill()
    assert process.returncode == 1, out
    states = {",".join(k): v for k, v in job_states(sweep).items()}
    adam = next(v for k, v in states.items() if "optim=adam" in k)
    gd = next(v for k, v in states.items() if "optim=gd" in k)
    assert adam["state"] == "interrupted", adam
    assert adam["reason"].startswith(signal.Signals(signum).name), adam
    assert gd["state"] == "completed", gd
    assert "interrupted: " + signal.Signals(signum).name in out
    assert "sweep finished" in out  # not stopped: one job's end is not the sweep's


# make test-long (and tests/cluster, under SLURM): SIGKILL of a run is in tests/e2e/test_cli.py
@pytest.mark.long
def test_a_killed_study_leaves_no_sweep_running_and_resumes(tmp_path):
    """SIGKILL of `physgrad compare` at random instants of its tuning: its sweep (in a session of
    its own) stops within seconds every time; the rerun finishes the study."""
    folder = tmp_path / "study"
    study = [
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=20000",
        "compare.trials=2",
        "compare.seeds=6",
        "compare.studies=1",
        f"compare.dir={folder}",
        "figures=false",  # the tables only: what is checked
    ]
    for _ in range(2):
        process = subprocess.Popen(
            [*PHYSGRAD, "compare", *study], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        wait_for("the tuning sweep", lambda: (folder / "tune" / "jobs.yaml").exists())
        time.sleep(random.uniform(0.0, 4.0))
        process.kill()
        process.wait()
        wait_for(
            "the orphaned sweep to end",
            lambda: (
                not subprocess.run(
                    ["pgrep", "-f", f"hydra.sweep.dir={folder}/"], capture_output=True
                ).stdout
            ),
            60,
        )
    done = subprocess.run(
        [*PHYSGRAD, "compare", *study], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert (folder / "compare.md").is_file()


# make test-long: a study's resume is decided by physgrad.comparison.jobs (tests/unit and
# tests/integration test_compare.py) and checked under SLURM in tests/cluster
@pytest.mark.long
def test_a_rerun_launches_only_the_jobs_without_finished_results(tmp_path):
    """A finished study launches nothing again; with one seed's file of one evaluation job removed,
    only that job runs, and the other job's files are untouched."""
    folder = tmp_path / "study"
    study = [
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=60",
        "compare.trials=2",
        "compare.seeds=6",
        "compare.studies=1",
        f"compare.dir={folder}",
        "figures=false",  # the tables only: what is checked
    ]
    first = subprocess.run([*PHYSGRAD, "compare", *study], capture_output=True, text=True)
    assert first.returncode == 0, first.stdout + first.stderr
    again = subprocess.run([*PHYSGRAD, "compare", *study], capture_output=True, text=True)
    assert again.returncode == 0 and "jobs ->" not in again.stdout, again.stdout
    assert "eval: the 2 jobs finished before: nothing to launch" in again.stdout
    (folder / "eval" / "+compare_job=eval_v1" / "seed=3" / "results.h5").unlink()
    kept = {
        p: p.stat().st_mtime_ns for p in (folder / "eval" / "+compare_job=eval_v0").rglob("*.h5")
    }
    third = subprocess.run([*PHYSGRAD, "compare", *study], capture_output=True, text=True)
    assert third.returncode == 0, third.stdout + third.stderr
    assert "eval: 1 of 2 jobs finished before" in third.stdout
    assert "eval: 1 jobs ->" in third.stdout
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())

    def verdicts(out: str) -> list[str]:
        """compare.md up to its timing section, without the last column of the verdict table:
        "contended runs" says how loaded the machine was while a job ran: a rerun may change it."""
        text = out.split("# Which")[1].split("## Timing")[0].splitlines()
        head = next(i for i, line in enumerate(text) if line.startswith("| A vs B"))
        assert text[head].endswith("| contended runs A, B |")
        rows = range(head, head + 3)
        return [line.rsplit("|", 2)[0] if i in rows else line for i, line in enumerate(text)]

    assert verdicts(third.stdout) == verdicts(first.stdout)


class FakeJob:
    def __init__(self, job_id: str, result=None, state: str = "COMPLETED"):
        from types import SimpleNamespace

        self.job_id, self.result, self.state = job_id, result, state
        self.paths = SimpleNamespace(result_pickle=Path("/nonexistent/result.pkl"))  # none written

    def results(self):
        if self.result is None:
            import submitit

            raise submitit.core.utils.UncompletedJobError(f"job {self.job_id} has no result")
        return [self.result]


def test_physgrads_slurm_launcher_waits_for_every_job_and_cancels_the_waiting(
    tmp_path, monkeypatch
):
    """A job that ends without a result (scancel while waiting) is recorded with its SLURM id and
    state, the others' results come back; a stop of the sweep runs scancel of the array's waiting
    tasks."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    import submitit
    from hydra.core.utils import JobReturn, JobStatus
    from omegaconf import OmegaConf

    import physgrad.cluster as cluster
    from physgrad.sweeps import ON_STOP, cancel_waiting

    sweep = tmp_path / "sweep"
    ok = JobReturn(overrides=["optim=adam"], _return_value=1.5, status=JobStatus.COMPLETED)
    jobs = [FakeJob("88_0", ok), FakeJob("88_1", None, "CANCELLED by 0")]

    class FakeExecutor:
        def __init__(self, **kwargs):
            self.init = kwargs

        def update_parameters(self, **kwargs):
            self.params = kwargs

        def map_array(self, fn, *args):
            assert len(args[0]) == 2
            return jobs

    monkeypatch.setattr(submitit, "AutoExecutor", FakeExecutor)
    ran = []

    def run(command, **kw):  # squeue: the cancelled job is not queued again; scancel: recorded
        ran.append(command)
        return subprocess.CompletedProcess(command, 0, stdout="", stderr="")

    monkeypatch.setattr(cluster.subprocess, "run", run)

    class Launcher:
        params = {
            "submitit_folder": str(sweep / ".submitit/%j"),
            "max_num_timeout": 0,
            "partition": "debug",
            "timeout_min": 5,
        }
        config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}})

    returns = cluster.launch_array(Launcher(), [["optim=adam"], ["optim=hig"]], 0)
    assert returns[0].return_value == 1.5 and returns[1].return_value == float("inf")
    lost = job_states(sweep)[frozenset(["optim=hig"])]
    assert lost["state"] == "not run" and lost["scheduler"] == "88_1"
    assert "CANCELLED" in lost["reason"]
    # asked once whether SLURM queued the cancelled job again (no wait: no requeue follows)
    assert ran == [["squeue", "-h", "-j", "88_1", "-o", "%T"]]
    assert len(ON_STOP) == 1
    cancel_waiting()
    assert ran[1:] == [["scancel", "--state=PENDING", "88"]] and not ON_STOP


def test_the_cluster_harness_ends_only_its_own_job_steps(tmp_path):
    """tests/cluster/slurm.sh stop ends the job steps (processes named slurmstepd) of its own
    cluster only: a stand-in step started with the harness's SLURM_CONF in its environment, and
    one holding a file of its state folder open, are ended; a third, another cluster's (another
    SLURM_CONF, no file of the state folder), is left running. Needs no SLURM: the stand-ins are
    copies of sleep named slurmstepd, and the state folder has no daemon to stop."""
    import os
    import shutil

    state = tmp_path / "state"
    (state / "log").mkdir(parents=True)
    step = tmp_path / "bin" / "slurmstepd"
    step.parent.mkdir()
    shutil.copy(shutil.which("sleep"), step)
    base = {k: v for k, v in os.environ.items() if k != "SLURM_CONF"}
    ours = subprocess.Popen([step, "300"], env={**base, "SLURM_CONF": f"{state}/slurm.conf"})
    with open(state / "log" / "step.out", "w") as log:
        holding = subprocess.Popen([step, "300"], env=base, stdout=log)
    other = subprocess.Popen([step, "300"], env={**base, "SLURM_CONF": "/elsewhere/slurm.conf"})
    try:
        stopped = subprocess.run(
            ["bash", str(Path(__file__).parents[1] / "cluster" / "slurm.sh"), "stop"],
            env={**base, "PHYSGRAD_SLURM_STATE": str(state)},
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert stopped.returncode == 0, stopped.stderr
        assert ours.wait(timeout=10) == -signal.SIGTERM
        assert holding.wait(timeout=10) == -signal.SIGTERM
        assert other.poll() is None
    finally:
        for process in (ours, holding, other):
            process.kill()
            process.wait()
