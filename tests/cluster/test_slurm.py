"""Studies and sweeps on a real SLURM cluster (`make test-cluster`: tests/cluster/slurm.sh starts a
two-node cluster on the one machine and sets SLURM_CONF), through `hydra/launcher=submitit_slurm`,
with the faults a cluster brings: scancel of a running and of a waiting job, a job's time limit,
SIGKILL of the launching command, a node lost while a job runs on it; then the reruns. Checked:
one job's end is not the sweep's, the study names the jobs that did not finish with their SLURM
ids, reruns submit only what is missing, nothing is left running, and the verdict and test losses
equal those of the local launcher.

A cluster is shared: every check of the queue or of processes is scoped to the test's own jobs (a
SLURM job name of its own) and its own processes (those whose command line names its folder), so
the tests pass beside other users' jobs and physgrad sweeps."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.cluster

PHYSGRAD = [sys.executable, "-m", "physgrad"]
# the SLURM job name of the running test's jobs (set per test: the queue checks see only them)
OWN = {"name": "", "folder": ""}
LAUNCHER: list[str] = []


@pytest.fixture(scope="module", autouse=True)
def cluster() -> None:
    if not os.environ.get("SLURM_CONF"):
        pytest.fail("no cluster: run `make test-cluster` (it starts one and sets SLURM_CONF)")
    subprocess.run(["sinfo"], check=True, capture_output=True)


@pytest.fixture(scope="module", autouse=True)
def someone_elses_sweep(tmp_path_factory: pytest.TempPathFactory) -> None:
    """An unrelated `physgrad run -m` alive beside the tests (stopped with SIGSTOP, so that it takes
    no core from them), as on a shared node: the tests must not take it for their own."""
    folder = tmp_path_factory.mktemp("someone-else")
    other = subprocess.Popen(
        [*PHYSGRAD, "run", "-m", "task=toy", "optim=adam,gd", f"hydra.sweep.dir={folder}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    time.sleep(1.0)
    os.killpg(other.pid, signal.SIGSTOP)
    yield
    os.killpg(other.pid, signal.SIGKILL)
    other.wait()


@pytest.fixture(autouse=True)
def own_jobs(tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """This test's jobs carry a job name of their own and its commands name its tmp_path."""
    OWN["name"] = f"pg{os.getpid()}-{request.node.name[:40]}"
    OWN["folder"] = str(tmp_path)
    LAUNCHER[:] = [
        "hydra/launcher=submitit_slurm",
        "hydra.launcher.partition=debug",
        "hydra.launcher.timeout_min=10",
        f"hydra.launcher.name={OWN['name']}",
    ]


def squeue(*options: str) -> list[tuple[str, ...]]:
    """(job id, state) of this test's jobs in the queue (its job name), or the columns options ask
    for."""
    out = subprocess.run(
        ["squeue", "-h", "-n", OWN["name"], *(options or ("-o", "%i %t"))],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return [tuple(line.split()) for line in out.splitlines() if line.strip()]


def wait_until(what: str, test: object, seconds: float = 120.0) -> object:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        value = test()
        if value:
            return value
        time.sleep(0.5)
    raise AssertionError(f"waited {seconds:.0f} s for {what}; queue: {squeue()}")


def running_task(task: int, seconds: float = 0.0) -> str | None:
    """The id of array task `task` once it has run for `seconds` (the queue's TIME column). A sweep
    of one job (a rerun that sends only what is missing) is sent as a plain job, without an array
    suffix: it is task 0."""
    for job, elapsed in squeue("-t", "R", "-o", "%i %M"):
        parts = [int(p) for p in elapsed.replace("-", ":").split(":")]
        ran = sum(p * 60**i for i, p in enumerate(reversed(parts)))
        task_of_job = int(job.rsplit("_", 1)[1]) if "_" in job else 0
        if task_of_job == task and ran >= seconds:
            return job
    return None


def states(sweep: Path) -> dict[str, dict]:
    """The recorded state of each job of a sweep, by its overrides."""
    import yaml

    found = {}
    for path in (sweep / ".physgrad-jobs").glob("*.yaml"):
        record = yaml.safe_load(path.read_text())
        found[",".join(record["overrides"])] = record
    return found


def own_physgrad_processes() -> list[int]:
    """The physgrad processes alive whose command line names this test's folder (the sweeps and
    studies it started, and their children's multiruns), whoever else runs physgrad here."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            words = (proc / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:  # ended meanwhile
            continue
        if any("physgrad" in w for w in words) and any(OWN["folder"] in w for w in words):
            found.append(int(proc.name))
    return found


def no_sweep_left() -> bool:
    """None of this test's physgrad processes alive and none of its jobs in the queue."""
    return not own_physgrad_processes() and not squeue()


def test_one_jobs_end_is_not_the_sweeps(tmp_path: Path) -> None:
    """scancel of a running job ends it alone, interrupted with its rows and its SLURM id; scancel
    of a waiting job records it as not run; the other jobs complete; the sweep exits 1."""
    sweep = tmp_path / "sweep"
    process = subprocess.Popen(
        [
            *PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "optim=adam,hig,gauss_newton",
            "trainer.iterations=100000000",
            "trainer.time_budget=12",
            *LAUNCHER,
            f"hydra.sweep.dir={sweep}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        # 2 cores: tasks 0 and 1 run, task 2 waits. Task 0 (Adam) is cancelled once its file holds
        # trained rows: a job's queue time says nothing of it, as start-up and compiling take from
        # 3 s to over 10 s with the machine's load
        first = wait_until("task 0 running", lambda: running_task(0))
        wait_until("Adam's first trained rows", lambda: trained_rows(sweep, "adam"), 180)
        waiting = wait_until(
            "task 2 waiting",
            lambda: next((j for j, s in squeue() if j.endswith("_2") and s == "PD"), None),
        )
        subprocess.run(["scancel", first], check=True)
        subprocess.run(["scancel", waiting], check=True)
        out, _ = process.communicate(timeout=180)
    finally:
        process.kill()
    assert process.returncode == 1, out
    recorded = states(sweep)
    by_optim = {key.split("optim=")[1].split(",")[0]: r for key, r in recorded.items()}
    assert by_optim["adam"]["state"] == "interrupted" and "SIGTERM" in by_optim["adam"]["reason"]
    assert by_optim["adam"]["scheduler"] == first
    assert by_optim["hig"]["state"] == "completed"
    assert by_optim["gauss_newton"]["state"] == "not run"
    assert "CANCELLED" in by_optim["gauss_newton"]["reason"]
    from physgrad.results import read_final

    attrs, _ = read_final(next((sweep).glob("*optim=adam*/results.h5")))
    assert attrs["status"] == "interrupted" and int(attrs["iterations"]) > 0
    assert f"(SLURM job {first})" in out and f"(SLURM job {waiting})" in out
    wait_until("the queue to empty", no_sweep_left, 60)


def test_a_time_limit_ends_the_job_interrupted(tmp_path: Path) -> None:
    """A job whose time limit comes: SLURM's warning signal (submitit's SIGUSR2) ends it
    interrupted, not failed, and the sweep reports it."""
    sweep = tmp_path / "sweep"
    done = subprocess.run(
        [
            *PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "optim=adam",
            "trainer.iterations=100000000",
            "trainer.time_budget=600",
            *(o for o in LAUNCHER if not o.startswith("hydra.launcher.timeout_min")),
            "hydra.launcher.timeout_min=1",
            "hydra.launcher.signal_delay_s=30",
            f"hydra.sweep.dir={sweep}",
        ],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 1, done.stdout + done.stderr
    (record,) = states(sweep).values()
    assert record["state"] == "interrupted", record
    assert record["reason"].startswith("SIGUSR2 (the scheduler's warning"), record
    wait_until("the queue to empty", no_sweep_left, 60)


def test_a_stopped_sweep_cancels_its_waiting_jobs(tmp_path: Path) -> None:
    """SIGTERM to the launching command: the running jobs end interrupted after their step, the
    waiting job is cancelled without ever running, the sweep exits 130 and nothing is left."""
    sweep = tmp_path / "sweep"
    process = subprocess.Popen(
        [
            *PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "optim=adam,gd,hig",
            "trainer.iterations=100000000",
            "trainer.time_budget=60",
            *LAUNCHER,
            f"hydra.sweep.dir={sweep}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        wait_until("tasks 0 and 1 running", lambda: running_task(0, 4) and running_task(1, 4))
        waiting = wait_until(
            "task 2 waiting",
            lambda: next((j for j, s in squeue() if j.endswith("_2") and s == "PD"), None),
        )
        process.send_signal(signal.SIGTERM)
        out, _ = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == 130, out
    wait_until("the queue to empty", no_sweep_left, 60)

    array, task = waiting.split("_")

    def accounted() -> str:
        """The waiting task's accounting record, once slurmdbd has it (it lags the queue): its own
        (`123_2`), or, where the array was cancelled whole, the record of the array's tasks that
        were still waiting (`123_[1-2%3]`)."""
        lines = subprocess.run(
            ["sacct", "-n", "-X", "-P", "-o", "JobID,State,Start", "-j", array],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.splitlines()  # a state may hold spaces: "CANCELLED by 0"
        return next((line for line in lines if int(task) in tasks_of(line.split("|")[0])), "")

    accounting = wait_until("the cancelled task's accounting record", accounted, 60)
    job, state, start = accounting.split("|")
    assert state.startswith("CANCELLED") and start in ("None", "Unknown"), accounting  # never ran
    recorded = {key.split("optim=")[1].split(",")[0]: r for key, r in states(sweep).items()}
    assert recorded["adam"]["state"] == recorded["gd"]["state"] == "interrupted", recorded
    assert recorded["hig"]["state"] == "not run", recorded


def test_an_equal_time_study_calibrates_where_its_jobs_run(tmp_path: Path) -> None:
    """The calibration of an equal-time study is a job of the study, sent to SLURM with the others;
    calibration.json records the host it ran on."""
    import socket

    folder = tmp_path / "study"
    done = subprocess.run(
        [
            *PHYSGRAD,
            "compare",
            "task=toy",
            "optim=adam,gd",
            "trainer.time_budget=1",
            "compare.trials=2",
            # where the calibration runs is checked, not a verdict: two seeds (12 jobs took 40 s)
            "compare.seeds=2",
            "compare.studies=1",
            f"compare.dir={folder}",
            "figures=false",
            *LAUNCHER,
        ],
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "SLURM job array" in (folder / "calibration.log").read_text()
    calibration = json.loads((folder / "calibration.json").read_text())
    assert calibration["machine"]["hostname"] == socket.gethostname()
    # the same machine (a load beside the test may add "calibrated on a busy machine": not this)
    assert "step costs were calibrated on" not in (folder / "compare.md").read_text()


STUDY = [
    "task=toy",
    # three 20-neuron layers: HIG's tuning job (two trials together, about 5 ms a step on 2 cores)
    # trains 3000 iterations for about 15 s after its start-up, long enough to be cancelled 5 s
    # into its run and killed 3 s into its rerun; the book's 7-neuron toy finishes it in a second or
    # two. Every iteration is paid again in the evaluation and in the local twin study
    "task.hidden=[20,20,20]",
    "optim=adam,hig",
    "trainer.iterations=3000",
    "compare.trials=2",
    "compare.seeds=6",
    "compare.studies=1",
    "figures=false",  # the tables are what is compared
]


def compare(folder: Path, *extra: str, **popen: object) -> subprocess.Popen:
    return subprocess.Popen(
        [*PHYSGRAD, "compare", *STUDY, f"compare.dir={folder}", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # a SIGKILL to it alone, as a user's kill -9
        **popen,
    )


def local_twin(factory: pytest.TempPathFactory) -> Path:
    """The study of STUDY under the local launcher, run once for every test that compares with it
    (its folder is this module's; a test's own SLURM jobs are named after the test, these none)."""
    if "local" not in LOCAL:
        folder = factory.mktemp("local-twin") / "local"
        here = compare(folder)
        out, _ = here.communicate(timeout=600)
        assert here.returncode == 0, out
        LOCAL["local"] = folder
    return LOCAL["local"]


LOCAL: dict[str, Path] = {}


def test_a_study_survives_scancel_and_a_killed_launcher(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A study under SLURM: scancel of one tuning job (the study names it and exits non-zero), the
    rerun killed with SIGKILL while a job runs (nothing is left running or waiting), the last rerun
    submits only what is missing; the verdict and every test loss equal the local launcher's."""
    folder = tmp_path / "slurm"
    first = compare(folder, *LAUNCHER)
    try:
        # tuning: one job per variant (trials together); task 1 is HIG's
        hig = wait_until("HIG's tuning job running for 5 s", lambda: running_task(1, 5), 180)
        subprocess.run(["scancel", hig], check=True)
        out, _ = first.communicate(timeout=300)
    finally:
        first.kill()
    assert first.returncode == 2, out
    assert "tune: 1 of 2 jobs did not finish" in out and f"(SLURM job {hig})" in out, out

    second = compare(folder, *LAUNCHER)
    try:
        wait_until("the rerun's job running", lambda: running_task(0, 3), 180)
        os.killpg(second.pid, signal.SIGKILL)
        second.wait(timeout=30)
        out = second.stdout.read()
    finally:
        second.kill()
    assert "tune: 1 of 2 jobs finished before" in out, out
    wait_until("nothing left running or waiting", no_sweep_left, 90)

    finished = {
        path: path.stat().st_mtime_ns
        for path in (folder / "tune").rglob("results.h5")
        if read_status(path) in ("completed", "diverged")
    }
    assert finished
    third = compare(folder, *LAUNCHER)
    out, _ = third.communicate(timeout=600)
    assert third.returncode == 0, out
    redone = [p for p, t in finished.items() if p.stat().st_mtime_ns != t]
    assert not redone, f"finished jobs ran again: {redone}"
    again = compare(folder, *LAUNCHER)
    out, _ = again.communicate(timeout=300)
    assert again.returncode == 0 and "jobs ->" not in out, out  # nothing submitted

    local = local_twin(tmp_path_factory)
    assert verdicts(folder) == verdicts(local)
    assert final_losses(folder) == pytest.approx(final_losses(local), rel=1e-6)


def tasks_of(job: str) -> set[int]:
    """The array tasks an accounting record's JobID stands for: `12_3` is task 3, `12_[0-2,5%3]`
    tasks 0, 1, 2 and 5 (the `%3` is the array's limit of tasks running at once)."""
    _, _, part = job.partition("_")
    found = set()
    for piece in part.strip("[]").split("%")[0].split(","):
        low, _, high = piece.partition("-")
        if low.isdigit() and (high.isdigit() or not high):
            found |= set(range(int(low), int(high or low) + 1))
    return found


def trained_rows(sweep: Path, optim: str) -> int:
    """The /train rows the running job of `optim` has written to its results file so far (0 before
    its first write; the file is replaced whole at each write, never half-written)."""
    from physgrad.results import read_run

    for path in sweep.glob(f"*optim={optim}*/results.h5"):
        try:
            return len(read_run(path).train.get("iteration", ()))
        except (OSError, ValueError):
            return 0
    return 0


def read_status(path: Path) -> str:
    from physgrad.results import read_final

    return str(read_final(path)[0].get("status"))


def verdicts(folder: Path) -> list[tuple[str, str, str]]:
    with open(folder / "comparisons.csv") as file:
        return [(r["study"], r["a"], r["b"], r["verdict"]) for r in csv.DictReader(file)]


def final_losses(folder: Path) -> dict[tuple[str, str], float]:
    with open(folder / "runs.csv") as file:
        return {(r["variant"], r["seed"]): float(r["test_loss_at_1"]) for r in csv.DictReader(file)}


def node_processes(node: str) -> list[int]:
    """The processes a node of the harness's cluster runs: its slurmd (started with -N node), the
    job steps it started (slurmstepd holding the node's log or spool open) and the jobs' own
    processes (SLURMD_NODENAME=node in their environment)."""
    state = str(Path(os.environ["SLURM_CONF"]).parent)
    marks = (f"{state}/log/slurmd-{node}.log", f"{state}/spool/d-{node}")
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            words = (proc / "cmdline").read_bytes().split(b"\0")
            environ = (proc / "environ").read_bytes().split(b"\0")
            opened = [os.readlink(fd) for fd in (proc / "fd").iterdir()]
        except OSError:  # ended meanwhile
            continue
        slurmd = words[:1] == [b"/usr/sbin/slurmd"] and node.encode() in words
        if (
            slurmd
            or f"SLURMD_NODENAME={node}".encode() in environ
            or any(path.startswith(marks) for path in opened)
        ):
            found.append(int(proc.name))
    return found


def node_of(job: str) -> str:
    """The node a running job of this test's runs on."""
    return squeue("-j", job, "-o", "%N")[0][0]


def node_state(node: str) -> str:
    out = subprocess.run(
        ["sinfo", "-h", "-N", "-n", node, "-o", "%t"], check=True, capture_output=True, text=True
    ).stdout
    return out.strip()


def test_a_study_resumes_to_the_local_verdict_after_a_node_is_lost(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A study over the harness's two nodes (its tuning jobs one per node); the node of HIG's
    tuning job lost 3 s into that job (its slurmd, job steps and the job's processes killed with
    SIGKILL, as a machine that goes away): SLURM sets the node down and requeues the job
    (JobRequeue), which trains again from the start of its folder (the dead owner's file is not
    taken for finished); with the node back, the study finishes on its own, nothing is left
    running, a rerun submits nothing, and the verdict and every test loss equal the local
    launcher's. HIG's job, not Adam's: Adam's trains for under a second and has ended, its result
    taken, when the node goes, 3 s in; SLURM then requeues a job that finished, which is not what
    this test is about (docs/cluster.md says what happens then)."""
    folder = tmp_path / "slurm"
    state = str(Path(os.environ["SLURM_CONF"]).parent)
    first = compare(folder, *LAUNCHER)
    try:
        lost = wait_until("HIG's tuning job running for 3 s", lambda: running_task(1, 3), 180)
        node = node_of(lost)
        for pid in node_processes(node):
            os.kill(pid, signal.SIGKILL)
        wait_until(f"{node} down", lambda: node_state(node).startswith("down"), 120)
        harness = Path(__file__).parent / "slurm.sh"
        env = {**os.environ, "PHYSGRAD_SLURM_STATE": state}
        subprocess.run(["bash", str(harness), "start-node", node], check=True, env=env)
        wait_until(f"{node} back", lambda: node_state(node) in ("idle", "mix", "alloc"), 120)
        out, _ = first.communicate(timeout=600)
    finally:
        first.kill()
    assert first.returncode == 0, out
    requeued = subprocess.run(
        ["sacct", "-n", "-D", "-X", "-j", lost, "-o", "State"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    assert "NODE_FAIL" in requeued or "REQUEUED" in requeued, requeued  # the run was lost
    wait_until("nothing left running or waiting", no_sweep_left, 90)
    again = compare(folder, *LAUNCHER)
    out, _ = again.communicate(timeout=300)
    assert again.returncode == 0 and "jobs ->" not in out, out  # nothing submitted
    local = local_twin(tmp_path_factory)
    assert verdicts(folder) == verdicts(local)
    assert final_losses(folder) == pytest.approx(final_losses(local), rel=1e-6)
