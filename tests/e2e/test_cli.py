"""End-to-end layer of the command line: the console script writes the results schema, sweeps then
reports, keeps Hydra's flags, renders a mistake in one line, leaves a killed run's file readable,
logs progress without a terminal, answers --help without JAX, and trains eight SOAP trials
together without wedging."""

import os
import signal
import subprocess
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgrad.results import read_run
from tests.helpers import PHYSGRAD
from tests.helpers import console as physgrad

SMALL = ["task.grid=4", "task.test_size=8", "trainer.batch_size=4"]


def test_short_run_writes_the_results_schema(tmp_path):
    physgrad(
        "run",
        "optim=hig",
        "trainer.iterations=20",
        "trainer.eval_every=5",
        *SMALL,
        f"hydra.run.dir={tmp_path}",
    )
    with h5py.File(tmp_path / "results.h5", "r") as f:
        attrs = dict(f.attrs)
        for key in (
            "task",
            "optim",
            "seed",
            "status",
            "config",
            "physgrad_version",
            "jax_version",
            "compile_seconds",
            "created",
        ):
            assert key in attrs, key
        assert "unroll" not in attrs and "reason" not in attrs
        assert (attrs["task"], attrs["optim"], attrs["seed"], attrs["status"]) == (
            "poisson",
            "hig",
            0,
            "completed",
        )
        assert "name: hig" in attrs["config"] and "iterations: 20" in attrs["config"]
        # the form of J the step used (physgrad.jacobians)
        assert attrs["jacobian"] == "layer-factorised"
        assert set(f["train"]) >= {
            "iteration",
            "wall_time",
            "loss",
            "grad_norm",
            "kept_singular_values",
        }
        assert 0 < f["train/kept_singular_values"][-1] <= 4 * 16  # at most m = batch x outputs
        assert set(f["eval"]) >= {"iteration", "wall_time", "loss", "field_error"}
        wall = f["train/wall_time"][()]
        assert wall.shape == (20,) and np.all(np.diff(wall) > 0) and wall[0] > 0
        assert f["eval/iteration"][()].tolist() == [0, 5, 10, 15, 20]
    assert (tmp_path / "loss.png").stat().st_size > 1000


def test_sweep_then_report(tmp_path):
    sweep = tmp_path / "sweep"
    result = physgrad(
        "run",
        "-m",
        # the toy: the cheapest scene to build and compile, and without time (bptt refused)
        "task=toy",
        "optim=adam,hig,bptt",
        "seed=0,1",
        "trainer.iterations=5",
        "trainer.eval_every=5",
        "task.test_size=4",
        "trainer.batch_size=2",
        "figures=false",  # the report's figures are checked, not each run's
        f"hydra.sweep.dir={sweep}",
    )
    assert "skipped: optim=bptt needs a closed-loop controller" in result.stderr + result.stdout
    files = sorted(sweep.rglob("results.h5"))
    assert len(files) == 6
    statuses = sorted(read_run(f).attrs["status"] for f in files)
    assert statuses == ["completed"] * 4 + ["refused"] * 2
    assert (
        f"sweep finished: 4 completed, 2 refused in {sweep}; next: physgrad report {sweep}"
        in result.stdout
    )
    out = physgrad("report", str(sweep)).stdout
    by_group, by_seed = out.split("Per seed:")
    groups = [line for line in by_group.splitlines() if line.startswith("| toy | ")]
    assert [line.split(" | ")[1:4] for line in groups] == [
        ["adam", "2", "2 completed"],
        ["bptt", "2", "2 refused"],
        ["hig", "2", "2 completed"],
    ]
    per_seed = [line for line in by_seed.splitlines() if line.startswith("| toy | ")]
    assert len(per_seed) == 6 and sum("refused" in line for line in per_seed) == 2
    assert (sweep / "report.md").read_text().count("| toy | ") == 9
    assert (sweep / "loss_vs_time.png").stat().st_size > 1000


def test_hydra_flags_keep_working(tmp_path):
    cfg = physgrad("run", "--cfg", "job", "optim=hig").stdout
    assert "name: hig" in cfg and "learning_rate: 0.64" in cfg and "iterations: null" in cfg
    assert "Configuration groups" in physgrad("run", "--help").stdout
    assert "physgrad run" in physgrad("--help").stdout


@pytest.mark.parametrize(
    "args, fragment",
    [
        # refused before a job starts (the others of this kind: tests/unit/test_cli.py)
        (["optim=hgi"], "unknown optim 'hgi': did you mean hig?"),
        # refused by the job, once its config is composed (tests/integration/test_configs.py)
        (["unroll=8"], "task=poisson has no time axis: remove unroll=8"),
        pytest.param(  # a second refusal by the job: make test-long
            ["optim=stable_bptt"],
            "optim=stable_bptt needs a closed-loop controller",
            marks=pytest.mark.long,
        ),
    ],
)
def test_a_user_mistake_is_one_line_on_the_console(args, fragment, tmp_path):
    """The rendering of a user's mistake by the console script: exit code 2, one line on stderr, no
    traceback."""
    result = physgrad("run", *args, f"hydra.run.dir={tmp_path}", check=False)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0], result.stderr
    assert "Traceback" not in result.stderr


def wait_for_rows(path: Path, rows: int, process, deadline=120.0):
    start = time.time()
    while time.time() - start < deadline:
        assert process.poll() is None, process.communicate()
        try:
            with h5py.File(path, "r", locking=False) as f:
                if "train/iteration" in f and f["train/iteration"].shape[0] >= rows:
                    return
        except (OSError, KeyError):
            pass  # not created yet, or caught mid-flush
        time.sleep(0.2)
    raise AssertionError(f"no {rows} rows in {path} after {deadline} s")


@pytest.mark.parametrize(
    "sig, status",
    [
        (signal.SIGKILL, "crashed"),
        (signal.SIGINT, "interrupted"),
        # the same handler as SIGINT: make test-long
        pytest.param(signal.SIGTERM, "interrupted", marks=pytest.mark.long),
    ],
)
def test_killed_or_interrupted_run_leaves_a_readable_file(sig, status, tmp_path):
    process = subprocess.Popen(
        [
            PHYSGRAD,
            "run",
            "trainer.iterations=100000000",
            "trainer.flush_seconds=0.1",
            "task=toy",  # the cheapest scene to start: what is tested is the stop
            f"hydra.run.dir={tmp_path}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for_rows(tmp_path / "results.h5", 100, process)
        os.kill(process.pid, sig)
        _, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
    run = read_run(tmp_path / "results.h5")
    assert run.attrs["status"] == status, stderr
    rows = run.train["iteration"]
    assert rows.size >= 100 and rows.tolist() == list(range(rows.size))
    assert np.all(np.diff(run.train["wall_time"]) > 0)
    if sig != signal.SIGKILL:
        assert process.returncode == 130
        assert f"after {rows.size} iterations" in run.attrs["reason"]


def test_without_a_terminal_progress_is_logged_and_the_run_ends_with_one_line(tmp_path):
    # 6 s: progress moves with the file's flushes, which space out to 20 times a write's cost as the
    # file grows (about 3 s apart here), so 3 s of training could see a single one
    result = physgrad(
        "run",
        "task=toy",
        "trainer.time_budget=6",
        "trainer.log_seconds=0.5",
        f"hydra.run.dir={tmp_path}",
    )
    lines = result.stdout.splitlines()
    assert any(" compiled in " in line for line in lines)
    progress = [line for line in lines if "toy/adam seed 0 iteration " in line]
    assert len(progress) >= 2 and all(
        ", loss " in line and " s of training" in line for line in progress
    )
    assert (
        "completed after" in lines[-1]
        and "(stopped by time budget), 6.0 s of training" in lines[-1]
    )


@pytest.mark.parametrize("command", ["report", "check"])
def test_help_starts_no_jax(command, tmp_path):
    """Help is text: a command's --help must not wait for JAX to import (about 1.5 s). A jax that
    cannot be imported proves it."""
    fake = tmp_path / "jax"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('help imported jax')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    done = subprocess.run([PHYSGRAD, command, "--help"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-500:]
    assert "usage" in done.stdout.lower() and "help imported jax" not in done.stderr


@pytest.mark.long
def test_eight_soap_trials_trained_together_on_the_oscillators_step_instead_of_wedging(tmp_path):
    """The case that wedged XLA's CPU client (SOAP, 8 members trained together on the oscillators:
    every thread idle after the compile, for ever): the console script trains it with the
    scheduler that does not wedge, in seconds; each member recorded with the flag."""
    physgrad(
        "run",
        "task=oscillator",
        "optim=soap",
        "+trial_values={learning_rate:[0.001,0.002,0.003,0.004,0.005,0.006,0.007,0.008]}",
        "trainer.iterations=5",
        "figures=false",
        f"hydra.run.dir={tmp_path}",
    )
    run = read_run(tmp_path / "trial=7" / "results.h5")
    assert run.attrs["status"] == "completed"
    assert "xla_cpu_enable_concurrency_optimized_scheduler=false" in run.attrs["thread_settings"]
