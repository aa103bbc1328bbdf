"""Integration layer of studies on SLURM: a sweep's own refusal and a SLURM sweep that cannot start
are one line (sbatch's own words), submitit's SLURM launcher runs as physgrad's, and each launch
reads results from a submitit folder of its own, a planted or linked `.submitit` never."""

from __future__ import annotations

from pathlib import Path

import pytest

from physgrad.errors import UserError


def test_the_sweeps_own_refusal_is_said_in_one_line(tmp_path):
    from physgrad.comparison.jobs import _raise_unfinished

    log = tmp_path / "tune.log"
    log.write_text(
        "\n$ physgrad run -m a\nphysgrad: error: old refusal\n"
        "\n$ physgrad run -m b\nphysgrad: error: /x/tune is being written by pid 28452 on vm "
        "(another sweep)\n"
    )
    with pytest.raises(UserError, match=r"^tune: /x/tune is being written by pid 28452 on vm"):
        _raise_unfinished(tmp_path / "tune", "tune", {"tune_v0_t000": ""}, log)


def test_submitits_slurm_launcher_is_run_as_physgrads():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from omegaconf import OmegaConf

    from hydra_plugins.physgrad_launchers.slurm import (
        PHYSGRAD_SLURM,
        SUBMITIT_SLURM,
        use_physgrad_launcher,
    )

    config = OmegaConf.create(
        {"hydra": {"launcher": {"_target_": SUBMITIT_SLURM, "partition": "x"}}}
    )
    OmegaConf.set_readonly(config, True)
    use_physgrad_launcher(config)
    assert config.hydra.launcher._target_ == PHYSGRAD_SLURM
    assert config.hydra.launcher.partition == "x"
    other = OmegaConf.create({"hydra": {"launcher": {"_target_": "x.JoblibLauncher"}}})
    use_physgrad_launcher(other)
    assert other.hydra.launcher._target_ == "x.JoblibLauncher"


@pytest.mark.parametrize(
    "sbatch, said",
    [
        (None, 'Could not detect "srun"'),  # no SLURM on the PATH
        (
            "echo 'sbatch: error: Batch job submission failed: Invalid partition name' >&2; exit 1",
            "sbatch: error: Batch job submission failed: Invalid partition name",
        ),
        ("echo 'garbage here'", "Could not make sense of sbatch output"),
    ],
)
def test_a_slurm_sweep_that_cannot_start_is_one_line(tmp_path, monkeypatch, capsys, sbatch, said):
    """SLURM start-up failures (no SLURM client, sbatch refusing the array with its own message,
    an answer that names no job) end the command in one line that says sbatch's own words, exit code
    2; it was a traceback of 28 to 39 lines with the useful line buried. (sbatch hanging is not
    covered: submitit waits for it.)"""
    import os

    from physgrad.cli import main

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    if sbatch is not None:  # a SLURM client whose sbatch answers so
        for name, body in (("sbatch", sbatch), ("srun", "exit 0")):
            (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
            (bin_dir / name).chmod(0o755)
    python_dir = os.path.dirname(os.path.realpath(os.sys.executable))
    monkeypatch.setenv("PATH", f"{bin_dir}:{python_dir}")  # no other sbatch
    code = main(
        [
            "run",
            "-m",
            "task=toy",
            "trainer.iterations=2",
            "hydra/launcher=submitit_slurm",
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ]
    )
    error = [line for line in capsys.readouterr().err.splitlines() if "physgrad: error" in line]
    assert code == 2 and len(error) == 1, error
    assert "SLURM did not take the sweep's 1 jobs" in error[0] and said in error[0], error


def test_submitits_folder_is_this_launchs_own(tmp_path):
    """submitit unpickles each job's result from its folder: a sweep folder from someone else with
    pickles planted under `.submitit`, or `.submitit` a link, must not be where this launch's
    results are read from. Each launch gets a new folder of its own (0700); a linked `.submitit`
    is refused in one line."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from omegaconf import OmegaConf

    from hydra_plugins.physgrad_launchers.slurm import SUBMITIT_SLURM, use_physgrad_launcher
    from physgrad.cluster import own_submitit_folder
    from physgrad.errors import LauncherRefused

    sweep = tmp_path / "sweep"
    planted = sweep / ".submitit" / "4711"
    planted.mkdir(parents=True)
    (planted / "4711_0_result.pkl").write_bytes(b"planted")
    first, second = (own_submitit_folder(f"{sweep}/.submitit/%j") for _ in range(2))
    assert first != second and all(Path(f).name == "%j" for f in (first, second))
    for folder in (first, second):
        own = Path(folder).parent
        assert own.parent == sweep / ".submitit" and (own.stat().st_mode & 0o777) == 0o700
        assert not any(own.iterdir())
    config = OmegaConf.create(
        {"hydra": {"launcher": {"_target_": SUBMITIT_SLURM, "submitit_folder": f"{sweep}/%j"}}}
    )
    use_physgrad_launcher(config)
    assert Path(config.hydra.launcher.submitit_folder).parent.parent == sweep
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / ".submitit").symlink_to(elsewhere)
    with pytest.raises(LauncherRefused, match=r"\.submitit: submitit's folder is a link: refused"):
        own_submitit_folder(f"{linked}/.submitit/%j")
    assert not any(elsewhere.iterdir())


class _LostThenRequeued:
    """A submitit job whose accounting says NODE_FAIL `lost` times before its result arrives (the
    requeued run's), as sacct does while slurmctld requeues a job from a lost node."""

    def __init__(self, lost: int, state: str = "NODE_FAIL", outcome: Path | None = None):
        from types import SimpleNamespace

        self.job_id, self.state, self.lost, self.cleared = "7_1", state, lost, 0
        # submitit's result or error file: none where the job was killed
        self.paths = SimpleNamespace(result_pickle=outcome or Path("/nonexistent/result.pkl"))

        class Watcher:
            def clear(inner) -> None:
                self.cleared += 1

        self.watcher = Watcher()

    def results(self) -> list:
        if self.lost > 0:
            self.lost -= 1
            raise RuntimeError("Job 7_1 (task: 0) with path ... has not produced any output")
        return ["the requeued run's result"]


def _squeue_says(tmp_path, monkeypatch, *answers: str) -> Path:
    """A stub squeue on the PATH answering `answers` in turn (the last one from then on)."""
    script = tmp_path / "bin" / "squeue"
    script.parent.mkdir(exist_ok=True)
    count = tmp_path / "calls"
    count.write_text("0")
    cases = "\n".join(f"  {i}) echo '{a}' ;;" for i, a in enumerate(answers[:-1]))
    script.write_text(
        f"#!/bin/bash\nn=$(cat {count}); echo $((n + 1)) > {count}\n"
        f"case $n in\n{cases}\n  *) echo '{answers[-1]}' ;;\nesac\n"
    )
    script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{script.parent}:{Path('/usr/bin')}:{Path('/bin')}")
    return count


@pytest.mark.parametrize("lost", [1, 2, 5])
@pytest.mark.parametrize("answers", [("PENDING",), ("NODE_FAIL", "NODE_FAIL", "PENDING")])
def test_a_job_requeued_from_a_lost_node_is_waited_for(tmp_path, monkeypatch, lost, answers):
    """However many times the accounting says NODE_FAIL before the requeued run's result, and
    whether slurmctld shows the job queued again at once or after a while, the sweep gets the
    result and never records the job lost."""
    from physgrad.cluster import job_result

    _squeue_says(tmp_path, monkeypatch, *answers)
    job = _LostThenRequeued(lost)
    assert job_result(job, patience=30.0, poll=0.001) == "the requeued run's result"
    assert job.cleared == lost


@pytest.mark.parametrize("state, patience_used", [("FAILED", False), ("NODE_FAIL", True)])
def test_a_job_slurm_does_not_queue_again_is_lost(tmp_path, monkeypatch, state, patience_used):
    """A job that ended without a result and is not in slurmctld's queue (squeue says it ended):
    its error is returned, at once for a state no requeue follows, after the patience for one
    that a requeue may follow."""
    from physgrad.cluster import job_result

    calls = _squeue_says(tmp_path, monkeypatch, state)
    job = _LostThenRequeued(lost=100, state=state)
    outcome = job_result(job, patience=0.2, poll=0.02)
    assert isinstance(outcome, RuntimeError) and job.cleared == 0
    assert (int(calls.read_text()) > 1) == patience_used


@pytest.mark.parametrize("squeue", ["RUNNING", "COMPLETING", "PENDING"])
def test_a_job_that_wrote_its_own_error_is_not_waited_for(tmp_path, monkeypatch, squeue):
    """A job whose error submitit wrote (its code raised) has ended, whatever squeue shows while
    it winds down: its error at once, slurmctld not asked."""
    from physgrad.cluster import job_result

    calls = _squeue_says(tmp_path, monkeypatch, squeue)
    written = tmp_path / "7_1_0_result.pkl"
    written.write_bytes(b"error")
    job = _LostThenRequeued(lost=100, state="FAILED", outcome=written)
    assert isinstance(job_result(job, patience=5.0, poll=0.01), RuntimeError)
    assert int(calls.read_text()) == 0 and job.cleared == 0


def test_a_job_winding_down_is_not_taken_for_queued_again(tmp_path, monkeypatch):
    """squeue shows a job that ended as COMPLETING (or STAGE_OUT, SIGNALING) while it winds down:
    not queued again, so a job lost without a requeue is recorded after the patience."""
    from physgrad.cluster import job_result

    _squeue_says(tmp_path, monkeypatch, "COMPLETING", "STAGE_OUT", "SIGNALING")
    job = _LostThenRequeued(lost=100)
    assert isinstance(job_result(job, patience=0.2, poll=0.02), RuntimeError)
    assert job.cleared == 0
