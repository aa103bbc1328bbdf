"""End-to-end layer of sweeps through the console script: a failed job neither stops the sweep nor
goes unrecorded in any of its seeds' files, and a submitit local sweep resumes by skipping its
finished jobs."""

import sys
from pathlib import Path

import pytest

from physgrad.results import read_run
from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))


from tests.integration.test_sweeps import (
    TINY,
)


def test_a_failed_job_does_not_stop_the_sweep(tmp_path, monkeypatch):
    import physgrad.experiment
    from physgrad.cli import main

    real = physgrad.experiment.build_rule

    def broken_for_gd(optim_cfg, member_values=None):
        if optim_cfg["name"] == "gd":
            raise RuntimeError("simulated crash")
        return real(optim_cfg, member_values)

    monkeypatch.setattr(physgrad.experiment, "build_rule", broken_for_gd)
    # the sweep goes on, and exits 1 because a job failed
    assert (
        main(
            [
                "run",
                "-m",
                "optim=gd,adam",
                "trainer.iterations=2",
                *TINY[1:],
                f"hydra.sweep.dir={tmp_path}",
            ]
        )
        == 1
    )
    statuses = {read_run(p).attrs["optim"]: read_run(p) for p in tmp_path.rglob("results.h5")}
    assert statuses["gd"].attrs["status"] == "failed"
    assert statuses["gd"].attrs["reason"] == "RuntimeError: simulated crash"
    assert statuses["adam"].attrs["status"] == "completed"
    assert sorted(p.parent.name for p in tmp_path.rglob("results.h5")) == [
        "optim=adam,task.grid=4,task.test_size=8,trainer.batch_size=4,trainer.eval_every=5,trainer.iterations=2",
        "optim=gd,task.grid=4,task.test_size=8,trainer.batch_size=4,trainer.eval_every=5,trainer.iterations=2",
    ]


def test_a_failed_job_of_several_seeds_records_the_failure_in_every_seed_file(
    tmp_path, monkeypatch
):
    import physgrad.experiment
    from physgrad.cli import main

    def broken(optim_cfg, member_values=None):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(physgrad.experiment, "build_rule", broken)
    assert (
        main(
            [
                "run",
                "-m",
                "seeds=2",
                "trainer.iterations=2",
                *TINY[1:],
                f"hydra.sweep.dir={tmp_path}",
            ]
        )
        == 1
    )
    files = sorted(tmp_path.rglob("results.h5"))
    assert [p.parent.name for p in files] == ["seed=0", "seed=1"]  # no stray file beside them
    for seed, path in enumerate(files):
        run = read_run(path)
        assert (run.attrs["status"], run.attrs["seed"], run.attrs["reason"]) == (
            "failed",
            seed,
            "RuntimeError: simulated crash",
        )


# make test-long: a launcher of its own (the basic one and joblib run in make test)
@pytest.mark.long
def test_submitit_local_sweep_and_resume(tmp_path):
    """The SLURM path through Hydra's submitit launcher, with its local executor; a second call
    skips both jobs."""
    from tests.helpers import console as physgrad

    args = [
        "run",
        "-m",
        "hydra/launcher=submitit_local",
        "optim=adam,gd",
        "trainer.iterations=3",
        *TINY[1:],
        f"hydra.sweep.dir={tmp_path}",
    ]
    physgrad(*args)
    files = sorted(tmp_path.rglob("results.h5"))
    assert len(files) == 2 and all(read_run(f).attrs["status"] == "completed" for f in files)
    finished = [read_run(f).attrs["finished"] for f in files]
    physgrad(*args)
    assert [read_run(f).attrs["finished"] for f in files] == finished
    assert Path(tmp_path / ".submitit").is_dir()
