"""End-to-end layer of faults on the console script: writers killed at random instants, readers with
HDF5's default locking, a second owner or an intruder refused, a file size limit, stopped sweeps,
signals at any instant or inside a gc callback, and folder locks without flock (random instants in
`make test-long`, repeated many more times in `make test-faults`)."""

import errno
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgrad.errors import FolderOwned
from physgrad.files import own_folder
from physgrad.results import read_run
from tests.helpers import PHYSGRAD
from tests.integration.test_faults import (
    run_experiment_in,
)
from tests.unit.test_faults import (
    REPEATS,
)

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


STEPPER = textwrap.dedent("""
    import sys, time
    from physgrad.interrupts import StopRequest

    def busy(seconds):  # a step that computes: the process's CPU time grows
        end, total = time.perf_counter() + seconds, 0
        while time.perf_counter() < end:
            total += 1
        return total

    print("ready", flush=True)
    StopRequest().call(busy, float(sys.argv[1]), stall_seconds=1.0, stall_cpu_seconds=0.05)
    print("returned", flush=True)
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


@pytest.mark.long
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


@pytest.mark.long
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


@pytest.mark.long  # repeated reads for seconds: make test-faults repeats it further
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


@pytest.mark.long
@pytest.mark.parametrize("seeds", [1, 300])
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


@pytest.mark.long
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


# make test-long and make test-faults
@pytest.mark.long
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


@pytest.mark.long
def test_a_process_stopped_at_random_instants_of_a_step_is_not_stalled():
    """SIGSTOP for longer than the stall window (1 s) and the pause threshold, at random instants
    of a step that computes, then SIGCONT: the step returns instead of being abandoned as wedged."""
    rng = random.Random(7)
    for trial in range(REPEATS):
        process = subprocess.Popen(
            [sys.executable, "-c", STEPPER, "3.0"], stdout=subprocess.PIPE, text=True
        )
        assert process.stdout.readline().strip() == "ready"
        for _ in range(2):
            time.sleep(rng.uniform(0.1, 1.2))
            process.send_signal(signal.SIGSTOP)
            time.sleep(2.5)
            process.send_signal(signal.SIGCONT)
        out, _ = process.communicate(timeout=30)
        assert (process.returncode, out.strip()) == (0, "returned"), (trial, out)
