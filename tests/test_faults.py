"""Faults injected many times and at many instants: writers killed mid-write, a second writer, live
readers with HDF5's default file locking, full disks, signals in bursts, damaged files, stopped
sweeps.

The short form runs in `make test`; `make test-faults` repeats every randomised fault many more
times (PHYSGRAD_FAULT_REPEATS, see docs/results.md)."""

import dataclasses
import errno
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgrad.errors import FolderOwned, ResultsWriteError
from physgrad.files import own_folder
from physgrad.results import ResultsWriter, read_run
from tests.helpers import load

REPEATS = int(os.environ.get("PHYSGRAD_FAULT_REPEATS", "1"))  # the long form multiplies every count
PHYSGRAD = str(Path(sys.executable).with_name("physgrad"))
WRITER = textwrap.dedent("""
    import sys, time
    from physgrad.results import ResultsWriter
    writer = ResultsWriter(sys.argv[1], {"task": "toy", "optim": "adam", "seed": 0})
    writer.set_columns("train", ("iteration", "wall_time", "loss", "grad_norm"))
    print("ready", flush=True)
    for i in range(10**9):
        writer.append_row("train", (i, 0.001 * (i + 1), 1.0 / (i + 1), float(i)))
        if i % 7 == 0:
            row = {"iteration": i, "wall_time": 0.001 * (i + 1), "loss": 2.0 / (i + 1)}
            writer.append("eval", row)
        if i % 50 == 49:
            writer.flush()
""")


def start_writer(path: Path) -> subprocess.Popen:
    process = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout.readline().strip() == "ready"
    return process


def assert_consistent(path: Path) -> None:
    """What every results file must be after any fault: readable, equal columns, rows in order."""
    run = read_run(path)  # raises on unequal columns or an unreadable file
    iterations = run.train.get("iteration", np.empty(0))
    assert iterations.tolist() == list(range(iterations.size))
    assert np.array_equal(run.train.get("loss", np.empty(0)), 1.0 / (iterations + 1))
    assert np.all(np.diff(run.eval.get("iteration", np.empty(0))) > 0)


def test_a_writer_killed_at_random_instants_leaves_a_consistent_file(tmp_path):
    rng = random.Random(0)
    kills = 60 * REPEATS
    path = tmp_path / "results.h5"
    rows_seen = set()  # (which writer, rows in the file)
    process = start_writer(path)
    for kill in range(kills):
        time.sleep(rng.uniform(0.0, 0.03))  # every instant of the writer's cycle, flushes included
        if (
            kill % 10 == 9
        ):  # a fresh writer now and then: the file is rewritten from its first rows again
            process.kill()
            process.wait()
            assert_consistent(path)
            assert read_run(path).attrs["status"] == "crashed"  # its writer is gone
            process = start_writer(path)
            continue
        # freeze it anywhere: what a kill at this instant leaves
        os.kill(process.pid, signal.SIGSTOP)
        assert_consistent(path)
        rows_seen.add((kill // 10, read_run(path).train.get("iteration", np.empty(0)).size))
        os.kill(process.pid, signal.SIGCONT)
    process.kill()
    process.wait()
    assert_consistent(path)
    # the instants really were spread over many writes of each writer
    assert len(rows_seen) > kills // 3


def test_sigkill_at_random_instants_leaves_readable_files(tmp_path):
    rng = random.Random(1)
    for trial in range(8 * REPEATS):
        path = tmp_path / f"{trial}" / "results.h5"
        process = start_writer(path)
        time.sleep(rng.uniform(0.0, 0.3))
        process.kill()
        process.wait()
        assert_consistent(path)
        assert [p.name for p in path.parent.glob("*.h5")] == ["results.h5"]


def test_readers_with_default_locking_never_disturb_a_writer(tmp_path):
    path = tmp_path / "results.h5"
    process = start_writer(path)
    deadline = time.time() + 3 * REPEATS
    reads = 0
    while time.time() < deadline:
        with h5py.File(
            path
        ) as f:  # plain h5py: default file locking, held while the writer goes on
            lengths = {f["train"][key].shape[0] for key in f["train"]}
            assert len(lengths) <= 1
            time.sleep(0.01)
        reads += 1
    assert process.poll() is None, "the writer died while files were being read"
    process.kill()
    process.wait()
    assert reads > 20
    assert_consistent(path)


def test_a_second_owner_is_refused_and_a_dead_one_replaced(tmp_path):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
        import time
        from physgrad.files import own_folder
        with own_folder({str(tmp_path)!r}):
            print("held", flush=True)
            time.sleep(60)
    """),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(
            FolderOwned, match=rf"being written by pid {holder.pid} on .* since 20\d\d-"
        ):
            with own_folder(tmp_path):
                pass
        # a job into that folder is refused without touching what is there
        (tmp_path / "results.h5").write_bytes(b"someone else's")
        outcome, _ = run_experiment_in(tmp_path)
        assert outcome.status == "refused" and f"pid {holder.pid}" in outcome.reason
        assert (tmp_path / "results.h5").read_bytes() == b"someone else's"
    finally:
        holder.kill()
        holder.wait()
    with own_folder(tmp_path):  # the owner died: its lock went with it
        pass


def run_experiment_in(folder, *overrides):
    from physgrad.experiment import run_experiment

    return run_experiment(load("task=toy", "trainer.iterations=3", *overrides), folder)


def test_a_full_disk_at_any_write_is_one_line_and_leaves_the_last_good_file(tmp_path, monkeypatch):
    import physgrad.results as results

    real = h5py.File
    flushes = 5 * REPEATS
    for failing_write in range(1, flushes + 3):  # the first write, each flush, and the final one
        path = tmp_path / f"{failing_write}" / "results.h5"
        writes = []

        def file(name, mode="r", **kwargs):
            if mode == "w":
                writes.append(name)
                if len(writes) == failing_write:
                    raise OSError(errno.ENOSPC, "No space left on device")
            return real(name, mode, **kwargs)

        monkeypatch.setattr(results.h5py, "File", file)
        try:
            writer = ResultsWriter(path, {"task": "toy", "optim": "adam", "seed": 0})
            for i in range(flushes):
                writer.append("train", {"iteration": i, "loss": 1.0})
                writer.flush()
            writer.finish("completed")
            raise AssertionError("the full disk went unnoticed")
        except ResultsWriteError as error:
            assert str(error) == f"cannot write {path}: No space left on device"
        finally:
            monkeypatch.setattr(results.h5py, "File", real)
        if (
            failing_write > 1
        ):  # the file of the last good write is intact: write k holds rows 0 .. k - 2
            run = read_run(path)
            assert run.train.get("iteration", np.empty(0)).tolist() == list(
                range(failing_write - 2)
            )
            assert run.attrs["status"] == "running"
        assert not list(path.parent.glob(".*.tmp"))


def test_a_file_size_limit_is_a_write_error_not_a_crash(tmp_path):
    """A real failing write() (RLIMIT_FSIZE, without privileges), not a mocked one."""
    script = textwrap.dedent(f"""
        import resource, signal
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
        from physgrad.errors import ResultsWriteError
        from physgrad.results import ResultsWriter
        attrs = {{"task": "toy", "optim": "adam", "seed": 0}}
        writer = ResultsWriter({str(tmp_path / "results.h5")!r}, attrs)
        try:
            for i in range(10**6):
                writer.append("train", {{"iteration": i, "loss": 1.0, "a": 2.0, "b": 3.0}})
                if i % 1000 == 999:
                    writer.flush()
        except ResultsWriteError as error:
            print("refused:", error)
            print("marked:", writer.mark_failed_in_place(str(error)))
    """)
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "refused: cannot write" in result.stdout and "File too large" in result.stdout, (
        result.stdout
    )
    run = read_run(tmp_path / "results.h5")
    assert run.attrs["status"] == "failed" and "File too large" in run.attrs["reason"]
    assert (
        run.train["iteration"].tolist() == list(range(run.train["iteration"].size))
        and run.train["iteration"].size
    )


def test_signals_in_bursts_at_random_instants_always_end_interrupted(tmp_path):
    """Two to four signals a few milliseconds apart, at random instants of a run (compile, steps,
    flushes); the process stays alive, the file is final and consistent."""
    from physgrad.experiment import prepare
    from physgrad.interrupts import stop_on_signals
    from physgrad.runner import TrainerSettings, train

    rng = random.Random(2)
    cfg = load("task=toy", "trainer.flush_seconds=0.001")
    settings = TrainerSettings.from_config(cfg.trainer)
    settings = dataclasses.replace(settings, iterations=None, time_budget=30.0)
    for trial in range(4 * REPEATS):
        scene, rule, seeds = prepare(cfg, [0], settings)
        writer = ResultsWriter(
            tmp_path / f"{trial}" / "results.h5", {"task": "toy", "optim": "adam", "seed": 0}
        )
        times = sorted(
            rng.uniform(0.0, 2.0) + k * rng.uniform(0.0, 0.01) for k in range(rng.randint(2, 4))
        )
        with stop_on_signals() as stop:  # stays installed until the last signal arrived
            start = time.monotonic()
            timers = [
                threading.Timer(
                    t, os.kill, (os.getpid(), rng.choice([signal.SIGINT, signal.SIGTERM]))
                )
                for t in times
            ]
            for timer in timers:
                timer.start()
            (outcome,) = train(scene, rule, seeds, [writer], settings, stop=stop)
            for timer in timers:
                timer.join()
        assert time.monotonic() - start < 25
        run = read_run(writer.path)
        assert outcome.status == run.attrs["status"] == "interrupted", run.attrs
        assert run.train.get("iteration", np.empty(0)).tolist() == list(range(outcome.iterations))


def test_a_completed_file_is_replaced_only_by_a_completed_one(tmp_path):
    first, path = run_experiment_in(tmp_path)
    kept = read_run(path).attrs["created"]
    # a re-run (overwrite=true) that ends interrupted
    writer = ResultsWriter(path, {"task": "toy", "optim": "adam", "seed": 0})
    writer.append("train", {"iteration": 0, "loss": 1.0})
    writer.finish("interrupted", "SIGINT after 1 iterations")
    assert read_run(path).attrs["created"] == kept and read_run(path).attrs["status"] == "completed"
    assert read_run(path.with_name("results.overwriting.h5")).attrs["status"] == "interrupted"
    again, _ = run_experiment_in(tmp_path, "overwrite=true", "trainer.iterations=4")
    assert again.status == "completed" and read_run(path).train["iteration"].size == 4
    assert not path.with_name("results.overwriting.h5").exists()  # renamed onto results.h5


@pytest.mark.parametrize("content", [b"", b"not hdf5 at all", "foreign"])
def test_a_damaged_or_foreign_file_is_set_aside_and_the_job_reruns(tmp_path, content):
    path = tmp_path / "results.h5"
    if content == "foreign":
        with h5py.File(path, "w") as f:
            f["data"] = np.arange(3)
    else:
        path.write_bytes(content)
    outcome, _ = run_experiment_in(tmp_path)
    assert outcome.status == "completed" and read_run(path).attrs["status"] == "completed"
    (aside,) = tmp_path.glob("results.h5.unreadable-*")
    if content != "foreign":
        assert aside.read_bytes() == content


@pytest.mark.long
def test_a_stopped_sweep_records_its_running_job_and_names_the_ones_that_never_ran(tmp_path):
    sweep = tmp_path / "sweep"
    process = subprocess.Popen(
        [
            PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "trainer.iterations=100000000",
            "seed=0,1,2",
            f"hydra.sweep.dir={sweep}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.time() + 120
        while not list(sweep.glob("*/results.h5")) and time.time() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)
        process.send_signal(signal.SIGTERM)  # to the launcher only, as `kill` or a scheduler would
        output, _ = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == 130, output
    assert "sweep stopped by SIGTERM: 1 interrupted, 2 never started" in output
    from physgrad.report import write_report

    text = write_report([sweep])
    assert text.count("not run: ") == 2 and "seed=2: never started" in text
    # a second sweep into a folder whose sweep still runs is refused in one line
    with own_folder(sweep, "sweep"):
        second = subprocess.run(
            [PHYSGRAD, "run", "-m", "task=toy", "seed=0,1", f"hydra.sweep.dir={sweep}"],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert second.returncode == 2 and second.stderr.count("\n") == 1
    assert "is being written by pid" in second.stderr and "(another sweep)" in second.stderr


def finished(process: subprocess.Popen, seconds: float) -> tuple[str, str]:
    try:
        return process.communicate(timeout=seconds)
    except subprocess.TimeoutExpired:
        process.kill()
        raise AssertionError(f"still running {seconds} s after the signal") from None


@pytest.mark.parametrize("seeds", [1, pytest.param(300, marks=pytest.mark.long)])
def test_a_signal_at_any_instant_of_a_run_ends_it_in_one_line(tmp_path, seeds):
    """SIGINT or SIGTERM at random instants from the console script's first line to its last:
    imports (jaxlib's
    extension), composing, resume checks, building 300 seeds' data, compiling, training, final
    writes. The process ends soon after, with 130 (or 0 if it had finished), no traceback and no
    crash, and every file it left is readable and truthful."""
    rng = random.Random(seeds)
    for trial in range((3 if seeds == 1 else 2) * REPEATS):
        folder = tmp_path / f"{trial}"
        process = subprocess.Popen(
            [
                PHYSGRAD,
                "run",
                "task=toy",
                f"seeds={seeds}",
                "trainer.iterations=40",
                f"hydra.run.dir={folder}",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        time.sleep(rng.uniform(0.0, 6.0 if seeds == 1 else 12.0))
        sent = rng.choice([signal.SIGINT, signal.SIGTERM])
        process.send_signal(sent)
        # compiling cannot be cut short (seconds here); 300 seeds write 300 small files when
        # interrupted
        _, err = finished(process, 60)
        # in the interpreter's first milliseconds, before Python handles signals, the signal's
        # default action ends the process (a shell reports 128 + its number); never another signal
        # (SIGSEGV, SIGABRT: a crash)
        assert process.returncode in (0, 130, -sent) and "Traceback" not in err, (
            process.returncode,
            err[-3000:],
        )
        if process.returncode == -sent:
            assert not list(folder.rglob("results.h5"))
        for path in folder.rglob("results.h5"):
            status = read_run(path).attrs["status"]
            assert status in ("interrupted", "completed") and (status == "completed") <= (
                process.returncode == 0 or "completed" in status
            ), (process.returncode, status)


# Runs the console script with a garbage-collector callback that raises a signal inside itself, at
# the AT-th collection of PHASE (start-up: the console script's handler; job: the job's); the
# handler runs before raise_signal returns, so its exception is raised where the interpreter cannot
# propagate it (jaxlib's own callback is where real signals land there)
INJECT_IN_COLLECTOR = textwrap.dedent("""
    import gc, os, signal, sys
    PHASE, AT, SIGNAL = sys.argv.pop(1), int(sys.argv.pop(1)), signal.Signals[sys.argv.pop(1)]
    seen = {"start-up": 0, "job": 0}

    def inject(phase, info):
        if phase != "start" or SIGNAL in signal.pthread_sigmask(signal.SIG_BLOCK, []):
            return
        handler = type(signal.getsignal(SIGNAL)).__name__
        now = "job" if handler == "StopRequest" else "start-up" if seen["job"] == 0 else None
        if now is None or (handler != "StopRequest" and signal.getsignal(SIGNAL) in (signal.SIG_DFL,
                                                                                     signal.default_int_handler)):
            return
        seen[now] += 1
        if (now, seen[now]) == (PHASE, AT):
            print(f"injected {SIGNAL.name}", file=sys.stderr, flush=True)
            signal.raise_signal(SIGNAL)

    gc.callbacks.insert(0, inject)
    from physgrad.cli import main
    sys.exit(main())
""")


def test_a_signal_raised_inside_a_garbage_collector_callback_is_not_lost(tmp_path):
    """A signal whose KeyboardInterrupt lands in a garbage-collector callback (the interpreter
    prints "Exception ignored" and drops it) at many instants of the start-up (composing) and of a
    job's set-up: the run still stops, with 130 and files saying interrupted, and without a
    traceback; if it landed while the job's final file was written (only counted there, by design)
    the run completes with 0."""
    rng = random.Random(7)
    # a toy run has ~40 collections with the console script's handler and ~200 with the job's
    cases = [("start-up", rng.randint(1, 35)), ("job", rng.randint(1, 150))] * REPEATS
    for trial, (phase, at) in enumerate(cases):
        folder, sent = tmp_path / f"{trial}", rng.choice(["SIGINT", "SIGTERM"])
        result = subprocess.run(
            [
                sys.executable,
                "-c",
                INJECT_IN_COLLECTOR,
                phase,
                str(at),
                sent,
                "run",
                "task=toy",
                "trainer.iterations=40",
                f"hydra.run.dir={folder}",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        case = (phase, at, sent, result.returncode, result.stderr[-3000:])
        assert f"injected {sent}" in result.stderr, case
        assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr, case
        status = read_run(folder / "results.h5").attrs["status"]
        assert (result.returncode, status) in ((130, "interrupted"), (0, "completed")), case
        if phase == "start-up":
            assert (result.returncode, status) == (130, "interrupted"), case
            assert f"{sent} before training" in read_run(folder / "results.h5").attrs["reason"], (
                case
            )


def test_an_intruder_is_refused_without_touching_a_live_job(tmp_path):
    """A second process into the folder of a job a sweep is running: refused (exit 2) before
    anything is written, so the live job's provenance (.hydra/) and recorded state stay as they
    were."""
    sweep = tmp_path / "sweep"
    process = subprocess.Popen(
        [
            PHYSGRAD,
            "run",
            "-m",
            "task=toy",
            "trainer.iterations=100000000",
            "seed=0",
            f"hydra.sweep.dir={sweep}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.time() + 120
        while not list(sweep.glob("*/results.h5")) and time.time() < deadline:
            time.sleep(0.2)
        (job,) = [path.parent for path in sweep.glob("*/results.h5")]
        before = {
            path: path.read_bytes()
            for path in [*job.glob(".hydra/*"), *sweep.glob(".physgrad-jobs/*")]
        }
        assert len(before) == 4  # config, hydra and overrides; the job's record
        intruder = subprocess.run(
            [
                PHYSGRAD,
                "run",
                "task=toy",
                "seed=5",
                "trainer.iterations=2",
                f"hydra.run.dir='{job}'",
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert intruder.returncode == 2 and "is being written by pid" in intruder.stderr, (
            intruder.stderr
        )
        assert {path: path.read_bytes() for path in before} == before
        assert read_run(job / "results.h5").attrs["seed"] == 0
        process.send_signal(signal.SIGINT)
        output, _ = finished(process, 120)
    finally:
        process.kill()
    assert process.returncode == 130 and "1 interrupted" in output, output
    from physgrad.sweeps import job_states

    (state,) = job_states(sweep).values()
    assert state["state"] == "interrupted" and Path(state["folder"]) == job


def test_a_job_folder_that_cannot_be_written_fails_alone_with_its_reason(tmp_path, monkeypatch):
    """A read-only job folder (injected: the tests may run as root, whom chmod does not stop) fails
    that job with one line; the sweep goes on, its summary and exit code say so, and the reason is
    recorded."""
    import physgrad.experiment as experiment
    from physgrad.cli import main
    from physgrad.sweeps import unfinished_jobs

    real = experiment.own_folder

    def read_only(folder, what="job"):
        if "optim=gd" in str(folder):
            raise PermissionError(errno.EACCES, "Permission denied", str(folder))
        return real(folder, what)

    monkeypatch.setattr(experiment, "own_folder", read_only)
    code = main(
        [
            "run",
            "-m",
            "task=toy",
            "optim=gd,adam",
            "trainer.iterations=2",
            f"hydra.sweep.dir={tmp_path}",
        ]
    )
    assert code == 1
    assert read_run(next(tmp_path.glob("optim=adam*/results.h5"))).attrs["status"] == "completed"
    ((job, why),) = unfinished_jobs(tmp_path)
    assert (
        "optim=gd" in job
        and why.startswith("failed: cannot write the job folder")
        and "Permission denied" in why
    )
    assert not list(tmp_path.glob("optim=gd*/.hydra"))


def test_where_flock_is_unsupported_posix_locks_hold_the_folder(tmp_path, monkeypatch):
    """ENOLCK (NFS without flock) and ENOSYS (Lustre mounted without flock) fall back to POSIX
    locks, which still refuse a second process; where neither works, one line with the real
    reason."""
    import physgrad.errors as errors
    import physgrad.files as files

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
        import fcntl, os, time
        fd = os.open({str(tmp_path / ".physgrad-job")!r}, os.O_RDWR | os.O_CREAT)
        fcntl.lockf(fd, fcntl.LOCK_EX)
        os.pwrite(fd, b"pid 1 on elsewhere since then", 0)
        print("held", flush=True)
        time.sleep(60)
    """),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        for number in (errno.ENOLCK, errno.ENOSYS):

            def no_flock(fd, operation, number=number):
                raise OSError(number, os.strerror(number))

            monkeypatch.setattr(files.fcntl, "flock", no_flock)
            with pytest.raises(FolderOwned, match="pid 1 on elsewhere"):
                with own_folder(tmp_path):
                    pass
    finally:
        holder.kill()
        holder.wait()
    with own_folder(tmp_path):  # the holder is gone: the POSIX lock is free
        pass
    outcome, _ = run_experiment_in(tmp_path / "run")
    assert outcome.status == "completed"
    monkeypatch.setattr(
        files.fcntl,
        "lockf",
        lambda fd, op: (_ for _ in ()).throw(OSError(errno.ENOLCK, "No locks available")),
    )
    with pytest.raises(
        errors.LockingUnsupported, match="supports no file locks .*No locks available.*mount"
    ):
        with own_folder(tmp_path / "other"):
            pass


def test_a_writer_on_another_host_is_judged_by_its_heartbeat():
    from physgrad.files import STALE_SECONDS, timestamp, with_live_status

    now = time.time()
    old = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(now - STALE_SECONDS - 60))
    for heartbeat, status in (
        (timestamp(), "running"),
        (old, "crashed"),
        ("not a time", "running"),
    ):
        attrs = with_live_status(
            {
                "status": "running",
                "owner": "pid 7 on a-host-that-is-not-this-one",
                "heartbeat": heartbeat,
            },
            now,
        )
        assert attrs["status"] == status
    assert (
        "has not written for"
        in with_live_status(
            {"status": "running", "owner": "pid 7 on elsewhere", "heartbeat": old}, now
        )["reason"]
    )


def test_a_scene_figure_that_raises_costs_a_warning_not_the_run(tmp_path, monkeypatch):
    import physgrad.experiment as experiment

    def broken(*args):
        raise TypeError("figure() takes 2 positional arguments but 3 were given")

    monkeypatch.setattr(experiment, "draw_run_figures", broken)
    outcome, path = run_experiment_in(tmp_path)
    assert outcome.status == "completed" and read_run(path).attrs["status"] == "completed"


def test_an_interrupted_report_leaves_the_previous_tables(tmp_path, monkeypatch):
    import physgrad.report as report
    import physgrad.tables as tables

    run_experiment_in(tmp_path / "run")
    report.write_report([tmp_path / "run"], out_dir=tmp_path / "report")
    before = {
        name: (tmp_path / "report" / name).read_bytes()
        for name in ("report.md", "runs.csv", "curves.csv")
    }
    rng = random.Random(4)
    real = tables.pd.DataFrame.to_csv
    for _ in range(5 * REPEATS):
        calls, stop_at, cut = [0], rng.randint(1, 2), rng.random()

        def interrupted(frame, f, *args, **kwargs):  # part of a table written, then a signal
            calls[0] += 1
            text = real(frame, None, *args, **kwargs)
            if calls[0] >= stop_at:
                f.write(text[: int(cut * len(text))])
                raise KeyboardInterrupt("SIGINT")
            f.write(text)

        monkeypatch.setattr(tables.pd.DataFrame, "to_csv", interrupted)
        with pytest.raises(KeyboardInterrupt):
            report.write_report([tmp_path / "run"], out_dir=tmp_path / "report")
        after = {name: (tmp_path / "report" / name).read_bytes() for name in before}
        assert after == before and not list((tmp_path / "report").glob(".*.tmp"))


@pytest.mark.parametrize("name", ["config.yaml", "hydra.yaml", "overrides.yaml"])
def test_a_full_disk_while_writing_hydra_fails_that_job_alone_in_one_line(
    tmp_path, monkeypatch, name
):
    """ENOSPC while physgrad writes a job's .hydra/ (each of its files): that job fails with one
    line and its reason recorded, no half-written file is left, and the sweep's other job runs."""
    import physgrad.files as files
    from physgrad.cli import main
    from physgrad.sweeps import job_states

    real = files.replace_file

    def full(path, content, sync=False):
        if path.name == name and path.parent.name == ".hydra" and "optim=gd" in str(path):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, content, sync)

    monkeypatch.setattr(files, "replace_file", full)
    assert (
        main(
            [
                "run",
                "-m",
                "task=toy",
                "optim=gd,adam",
                "trainer.iterations=2",
                f"hydra.sweep.dir={tmp_path}",
            ]
        )
        == 1
    )
    states = {Path(s["folder"]).name.split(",")[0]: s for s in job_states(tmp_path).values()}
    assert states["optim=adam"]["state"] == "completed"
    assert (
        states["optim=gd"]["state"] == "failed"
        and "No space left on device" in states["optim=gd"]["reason"]
    )
    assert not list(tmp_path.rglob("*.tmp")) and not list(tmp_path.glob("optim=gd*/results.h5"))


def test_a_signal_inside_a_garbage_collector_callback_is_kept_not_printed(capfd):
    """During set-up a signal raises at once, but raised inside code the interpreter runs on its own
    (jax's gc callback, injected here at every collection) it cannot propagate: no 'Exception
    ignored' traceback, and the stop stays requested for the job's next check."""
    import gc

    from physgrad.interrupts import stop_on_signals

    def callback(phase, info):
        if phase == "start":
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000):  # Python bytecode: the handler runs in here
                pass

    for _ in range(5 * REPEATS):
        with stop_on_signals() as stop:
            stop.raising = True
            gc.callbacks.append(callback)
            try:
                gc.collect()
            except KeyboardInterrupt:
                pytest.fail("raised out of the garbage collector")
            finally:
                gc.callbacks.remove(callback)
            assert stop.signal_name == "SIGINT" and not stop.raising
            with pytest.raises(KeyboardInterrupt):
                stop.raise_if_stopped()
        assert "Exception ignored" not in capfd.readouterr().err


def test_a_lock_file_or_job_log_that_is_a_link_is_never_written_through(tmp_path, capsys):
    """A job folder from someone else whose .physgrad-job or physgrad.log links to a file elsewhere:
    the lock is refused in one line (OSError naming it), the log is refused with one warning and
    the run logs to the terminal; the linked file is untouched either way."""
    import logging

    from physgrad.app import JobLogFile
    from physgrad.files import own_folder

    outside = tmp_path / "outside"
    outside.write_text("theirs\n")
    job = tmp_path / "job"
    job.mkdir()
    (job / ".physgrad-job").symlink_to(outside)
    with pytest.raises(OSError, match=r"\.physgrad-job is a link: refused"):
        with own_folder(job):
            pass
    (job / "physgrad.log").symlink_to(outside)
    handler = JobLogFile(job / "physgrad.log")
    handler.emit(logging.LogRecord("physgrad", logging.INFO, __file__, 1, "a line", None, None))
    handler.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot be written" in err[0] and "logging to the terminal" in err[0]
    assert outside.read_text() == "theirs\n"


def test_a_held_folder_names_the_process_holding_its_lock_not_only_what_its_file_says(tmp_path):
    """The lock file's text comes from whoever wrote the folder (it may be someone else's): the
    refusal names the process that holds the lock, as the operating system knows it."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
        import os, time
        from physgrad.files import own_folder
        with own_folder({str(tmp_path)!r}):
            fd = os.open({str(tmp_path / ".physgrad-job")!r}, os.O_WRONLY)
            os.pwrite(fd, b"pid 1 on elsewhere since then      ", 0)
            print("held", flush=True)
            time.sleep(60)
    """),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderOwned) as caught:
            with own_folder(tmp_path):
                pass
        message = str(caught.value)
        assert f"pid {holder.pid}" in message and "pid 1 on elsewhere" in message
        assert "\n" not in message
    finally:
        holder.kill()
        holder.wait()


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    from physgrad.experiment import run_experiment

    folder = tmp_path_factory.mktemp("two_runs")
    for optim in ("adam", "gd"):
        run_experiment(load("task=toy", f"optim={optim}", "trainer.iterations=3"), folder / optim)
    return folder


def test_a_full_disk_is_one_line_at_every_write_of_a_report(two_runs, tmp_path, capsys):
    """ENOSPC injected at the k-th file a report opens for writing (tables, figures), k = 0..N:
    every time exit 1 and one line that says what to do; the runs read are untouched."""
    import builtins

    from physgrad.cli import main

    before = {p: p.read_bytes() for p in two_runs.rglob("results.h5")}
    real_open = builtins.open
    opened = [0]
    outcomes = []
    for fail_at in range(12):
        opened[0] = 0

        def full_disk(file, mode="r", *args, fail_at=fail_at, **kwargs):
            if any(c in str(mode) for c in "wax+"):
                opened[0] += 1
                if opened[0] > fail_at:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))
            return real_open(file, mode, *args, **kwargs)

        builtins.open = full_disk
        try:
            code = main(["report", str(two_runs), "--out", str(tmp_path / f"out{fail_at}")])
        finally:
            builtins.open = real_open
        err = capsys.readouterr().err.strip()
        outcomes.append(code)
        if code != 0:
            assert code == 1 and "no space left writing" in err and "\n" not in err, err
    assert outcomes.count(1) >= 5  # the injection reached the report's writes many times
    assert {p: p.read_bytes() for p in two_runs.rglob("results.h5")} == before


def test_a_file_too_large_for_memory_is_left_out_and_the_rest_is_read(two_runs, monkeypatch):
    from physgrad import runs

    real = runs.read_run

    def huge(path):
        if "gd" in str(path):
            raise MemoryError
        return real(path)

    monkeypatch.setattr(runs, "read_run", huge)
    found, unreadable, _ = runs.collect([str(two_runs)])
    assert [r.attrs["optim"] for r in found] == ["adam"]
    assert len(unreadable) == 1 and "memory" in unreadable[0][1]
