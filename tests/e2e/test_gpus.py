"""End-to-end layer of one GPU per job, on a CPU machine: processes side by side claim different
GPUs (a fourth shares one, with a warning), a claim ends with its process however it ends, and the
jobs of a local parallel sweep each claim their own."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

CLAIM = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from physgrad.gpus import claim_gpu
    print(claim_gpu(int(sys.argv[1])), flush=True)
    release = Path(sys.argv[2])
    while not release.exists():
        time.sleep(0.02)
    """
)


def _claimers(tmp_path: Path, count: int, gpu_list: str) -> tuple[list, Path]:
    release = tmp_path / f"release-{time.monotonic_ns()}"
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpu_list, "XDG_RUNTIME_DIR": str(tmp_path)}
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", CLAIM, str(number), str(release)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for number in range(count)
    ]
    return processes, release


def _first_lines(processes: list) -> list[str]:
    return [p.stdout.readline().strip() for p in processes]


def test_processes_side_by_side_claim_different_gpus_and_a_fourth_shares_with_a_warning(tmp_path):
    processes, release = _claimers(tmp_path, 3, "0,1,2")
    try:
        claimed = _first_lines(processes)
        assert sorted(claimed) == ["0", "1", "2"]
        extra, extra_release = _claimers(tmp_path, 1, "0,1,2")
        assert _first_lines(extra) == ["0"]  # job number 0 -> the first GPU, shared
        extra_release.touch()
        assert "all 3 GPUs are held" in extra[0].communicate(timeout=30)[1]
    finally:
        release.touch()
        for p in processes:
            p.communicate(timeout=30)


def test_a_claim_ends_with_its_process_however_it_ends(tmp_path):
    """Killed (SIGKILL, at a random instant after its claim) or ended normally, a holder's GPU is
    free for the next process: the lock belongs to the process, not to a file left behind."""
    for round_number in range(4):
        processes, release = _claimers(tmp_path, 2, "0,1")
        claimed = _first_lines(processes)
        assert sorted(claimed) == ["0", "1"]
        victim = processes[round_number % 2]
        time.sleep(0.05 * round_number)
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=30)
        again, again_release = _claimers(tmp_path, 1, "0,1")
        assert _first_lines(again) == [claimed[round_number % 2]]
        again_release.touch()
        release.touch()
        for p in [*processes, *again]:
            p.communicate(timeout=30)


@pytest.mark.long
def test_jobs_of_a_local_parallel_sweep_each_claim_their_own_gpu(tmp_path):
    """Two jobs side by side (the joblib launcher) on a machine that names two GPUs: each job's log
    says which it got, and they differ."""
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "0,1", "XDG_RUNTIME_DIR": str(tmp_path)}
    sweep = tmp_path / "sweep"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "physgrad",
            "run",
            "-m",
            "task=toy",
            "optim=adam,gd",
            "trainer.iterations=3000",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            f"hydra.sweep.dir={sweep}",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    claimed = set()
    for log in sweep.glob("*/physgrad.log"):
        lines = [line for line in log.read_text().splitlines() if "for this job process" in line]
        assert len(lines) == 1, log
        claimed.add(lines[0].split("GPU ")[1].split(" ")[0])
    assert claimed == {"0", "1"}
