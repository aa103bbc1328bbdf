"""Integration layer of faults in-process: signals in bursts or inside a gc callback, a completed
file replaced only by a completed one, damaged files set aside, unwritable job folders and full
disks failing alone in one line, links never written through, and remote writers judged by their
heartbeat."""

import dataclasses
import errno
import os
import random
import signal
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgrad.files import own_folder
from physgrad.results import ResultsWriter, read_run
from tests.helpers import load
from tests.unit.test_faults import (
    REPEATS,
)


def run_experiment_in(folder, *overrides):
    from physgrad.experiment import run_experiment

    return run_experiment(load("task=toy", "trainer.iterations=3", *overrides), folder)


@pytest.mark.long
def test_signals_in_bursts_at_random_instants_always_end_interrupted(tmp_path):
    """Two to four signals a few milliseconds apart, at random instants of a run (compile, steps,
    flushes); the process stays alive, the file is final and consistent."""
    from physgrad.experiment import prepare
    from physgrad.interrupts import stop_on_signals
    from physgrad.job_spec import checked
    from physgrad.runner import train
    from physgrad.trainer_settings import TrainerSettings

    rng = random.Random(2)
    cfg = load("task=toy", "trainer.flush_seconds=0.001")
    settings = TrainerSettings.from_config(cfg.trainer)
    settings = dataclasses.replace(settings, iterations=None, time_budget=30.0)
    for trial in range(4 * REPEATS):
        scene, rule, seeds = prepare(checked(cfg), [0])
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


def test_a_run_stopped_by_one_signal_keeps_the_held_out_loss_it_reached(tmp_path):
    """Ctrl-C between evaluations (one every 10^6 iterations here): the run ends interrupted with
    a last evaluation at the iteration it stopped at, so its held-out loss is not the one of its
    start."""
    from physgrad.experiment import prepare
    from physgrad.interrupts import stop_on_signals
    from physgrad.job_spec import checked
    from physgrad.runner import train
    from physgrad.trainer_settings import TrainerSettings

    cfg = load("task=toy", "trainer.eval_every=1000000")
    settings = TrainerSettings.from_config(cfg.trainer)
    settings = dataclasses.replace(settings, iterations=None, time_budget=60.0)
    scene, rule, seeds = prepare(checked(cfg), [0])

    class SignalledAtRow(ResultsWriter):
        """Sends the process SIGINT once, as it buffers its 50th training row: after 50 steps
        however long compiling took on a loaded machine (a timer could fire before the first)."""

        rows = 0

        def append_row(self, group: str, values: tuple) -> None:
            super().append_row(group, values)
            self.rows += group == "train"
            if self.rows == 50:
                os.kill(os.getpid(), signal.SIGINT)

    writer = SignalledAtRow(tmp_path / "results.h5", {"task": "toy", "optim": "adam", "seed": 0})
    with stop_on_signals() as stop:
        (outcome,) = train(scene, rule, seeds, [writer], settings, stop=stop)
    run = read_run(writer.path)
    assert outcome.status == run.attrs["status"] == "interrupted"
    evaluated = run.eval["iteration"].tolist()
    assert evaluated[-1] == outcome.iterations == outcome.final_eval["iteration"]
    assert outcome.iterations > 10 and evaluated == [0, outcome.iterations]
    assert np.isfinite(run.eval["loss"][-1]) and run.eval["loss"][-1] < run.eval["loss"][0]


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


def test_an_interrupted_report_leaves_the_previous_tables(
    tmp_path, monkeypatch, report_figures_skipped
):
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


# the first file in make test, the other two in make test-long
@pytest.mark.parametrize(
    "name",
    [
        "config.yaml",
        pytest.param("hydra.yaml", marks=pytest.mark.long),
        pytest.param("overrides.yaml", marks=pytest.mark.long),
    ],
)
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


# pytest takes over sys.unraisablehook and turns what reaches it into a warning: an error here, so
# that an interrupt the hook below it did not drop fails the test instead of passing as a warning
@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
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
                # the youngest generation: its callbacks run as a full collection's do, without
                # a full collection's walk of every object of the test process (most of a second)
                gc.collect(0)
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

    from physgrad.sweep_hooks import JobLogFile

    outside = tmp_path / "outside"
    outside.write_text("theirs\n")
    job = tmp_path / "job"
    job.mkdir()
    (job / ".physgrad-job").symlink_to(outside)
    with pytest.raises(OSError, match=r"\.physgrad-job: a link: refused"):
        with own_folder(job):
            pass
    (job / "physgrad.log").symlink_to(outside)
    handler = JobLogFile(job / "physgrad.log")
    handler.emit(logging.LogRecord("physgrad", logging.INFO, __file__, 1, "a line", None, None))
    handler.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot be written" in err[0] and "logging to the terminal" in err[0]
    assert outside.read_text() == "theirs\n"


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    from physgrad.experiment import run_experiment

    folder = tmp_path_factory.mktemp("two_runs")
    for optim in ("adam", "gd"):
        run_experiment(load("task=toy", f"optim={optim}", "trainer.iterations=3"), folder / optim)
    return folder


# make test-long and make test-faults: ENOSPC at every write of a report
@pytest.mark.long
def test_a_full_disk_is_one_line_at_every_write_of_a_report(two_runs, tmp_path, capsys):
    """ENOSPC injected at the k-th file a report opens for writing (tables, figures), k = 0..N:
    every time exit 1 and one line that says what to do; the runs read are untouched."""
    import builtins

    from physgrad.cli import main

    before = {p: p.read_bytes() for p in two_runs.rglob("results.h5")}
    real_open, real_os_open = builtins.open, os.open
    opened = [0]
    outcomes = []
    for fail_at in range(12):
        opened[0] = 0

        def writing(file, fail_at=fail_at):
            opened[0] += 1
            if opened[0] > fail_at:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))

        def full_disk(file, mode="r", *args, **kwargs):
            if any(c in str(mode) for c in "wax+"):
                writing(file)
            return real_open(file, mode, *args, **kwargs)

        def full_disk_os(file, flags, *args, **kwargs):  # files opened for writing by os.open
            if flags & (os.O_WRONLY | os.O_RDWR):
                writing(file)
            return real_os_open(file, flags, *args, **kwargs)

        builtins.open, os.open = full_disk, full_disk_os
        try:
            code = main(["report", str(two_runs), "--out", str(tmp_path / f"out{fail_at}")])
        finally:
            builtins.open, os.open = real_open, real_os_open
        err = capsys.readouterr().err.strip()
        outcomes.append(code)
        if code != 0:
            assert code == 1 and "no space left writing" in err and "\n" not in err, err
    assert outcomes.count(1) >= 5  # the injection reached the report's writes many times
    assert {p: p.read_bytes() for p in two_runs.rglob("results.h5")} == before


def test_a_file_too_large_for_memory_is_left_out_and_the_rest_is_read(two_runs, monkeypatch):
    from physgrad import runs

    real = runs.read_run

    def huge(path, **options):
        if "gd" in str(path):
            raise MemoryError
        return real(path, **options)

    monkeypatch.setattr(runs, "read_run", huge)
    found, unreadable, _ = runs.collect([str(two_runs)])
    assert [r.attrs["optim"] for r in found] == ["adam"]
    assert len(unreadable) == 1 and "memory" in unreadable[0][1]


def test_a_signal_while_composing_is_kept_and_raised_where_physgrad_resumes(tmp_path):
    """Inside composing() a signal is kept, not raised (library code runs there); physgrad's own
    code inside (raising_interrupts) leaves a kept one to the job's first check (stop_on_signals)
    and raises new ones as they come; leaving composing raises one kept and not taken; a sweep's
    launcher takes a kept one as its first stop."""
    from physgrad.interrupts import (
        SignalInterrupt,
        composing,
        handling_signals,
        raise_interrupt,
        raising_interrupts,
        stop_on_signals,
    )
    from physgrad.sweeps import launcher_signals, stop_count

    def kill_and_run(sig=signal.SIGTERM):
        os.kill(os.getpid(), sig)
        for _ in range(10_000):  # Python bytecode: the handler runs in here
            pass

    with handling_signals(raise_interrupt):
        with pytest.raises(SignalInterrupt, match="SIGTERM"), composing():
            kill_and_run()  # kept: nothing raised here
            with raising_interrupts():
                pass
        with composing():
            kill_and_run()
            with raising_interrupts(), stop_on_signals() as stop:  # the job's first check
                assert stop.signal_name == "SIGTERM"
        with pytest.raises(SignalInterrupt, match="SIGINT"), composing():
            with raising_interrupts():
                kill_and_run(signal.SIGINT)  # raised at once
                pytest.fail("a signal in physgrad's own code was not raised")
        with pytest.raises(SignalInterrupt, match="SIGTERM"), composing():
            with raising_interrupts():
                pass
            kill_and_run()  # kept, raised on leaving
        with composing():
            kill_and_run()
            with launcher_signals(tmp_path):
                assert stop_count(tmp_path) == ("SIGTERM", 1)
    assert signal.getsignal(signal.SIGINT) is not raise_interrupt


@pytest.mark.long
def test_a_signal_at_many_instants_of_composing_a_run_ends_it_in_one_line(tmp_path, monkeypatch):
    """`physgrad run` as the console script runs it, its job past the door replaced by a stub:
    SIGTERM at 60 instants spread over every OmegaConf call of the run (the overrides' check, Hydra
    composing, the job's config read up to its door, Hydra after the job). An interrupt raised
    inside OmegaConf leaves half-built nodes whose cleanup then fails: the run ended with a config
    error (exit 1), an AttributeError or no stop at all in about 1 of 20 such instants. Here every
    one ends with 130 and one line, and a signal before the job is waiting for the job's first check
    (LOST: the job ends interrupted before training)."""
    import contextlib
    import io
    import sys

    from hydra.core.global_hydra import GlobalHydra

    import physgrad.app as app
    from physgrad import cli
    from physgrad.interrupts import LOST, handling_signals, raise_interrupt

    calls = {"count": 0, "at": -1, "job_at": None, "waiting": None}

    def job_body(spec, this, cfg, hydra_cfg):
        calls.update(job_at=calls["count"], waiting=list(LOST))

    monkeypatch.setattr(app, "checked_job", job_body)

    def profile(frame, event, arg):
        if event == "call" and "omegaconf" in frame.f_code.co_filename:
            calls["count"] += 1
            if calls["count"] == calls["at"]:
                os.kill(os.getpid(), signal.SIGTERM)

    def run(at):
        calls.update(count=0, at=at, job_at=None, waiting=None)
        GlobalHydra.instance().clear()
        err = io.StringIO()
        monkeypatch.setattr(sys, "argv", ["physgrad", "run"])
        args = ["run", "task=toy", f"hydra.run.dir={tmp_path / str(at)}"]
        with handling_signals(raise_interrupt), contextlib.redirect_stderr(err):
            sys.setprofile(profile)
            try:
                code = cli._main(args)
            except SystemExit as leaving:
                code = leaving.code
            finally:
                sys.setprofile(None)
        return code, err.getvalue()

    run(-1)  # Hydra's caches filled: later runs make the same calls
    code, err = run(-1)
    total = calls["count"]
    assert code == 0 and calls["job_at"] is not None and total > 10_000, (code, err)
    rng = random.Random(0)
    instants = [rng.randrange(total * i // 60, total * (i + 1) // 60) + 1 for i in range(60)]
    for at in instants:
        code, err = run(at)
        assert calls["count"] >= at, (at, calls["count"])
        assert code == 130 and err == "physgrad: stopped by SIGTERM\n", (at, code, err[-2000:])
        before_job = calls["job_at"] >= at
        assert calls["waiting"] == (["SIGTERM"] if before_job else []), (at, calls)
