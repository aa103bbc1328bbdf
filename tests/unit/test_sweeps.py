"""Unit layer of named sweeps and resuming: the claims plan in parts of at most 80 minutes, an
unknown experiment in one line, and a manifest that keeps an interpolated override as the job
folder does."""

import sys

import pytest
import yaml
from hydra import compose as hydra_compose

from physgrad.configs import check_overrides, initialized
from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))

import reproduce  # noqa: E402
import study_profiles  # noqa: E402


def test_the_claims_plan_lists_every_study_in_parts_of_at_most_80_minutes(capsys, monkeypatch):
    import studies as study_lists

    monkeypatch.setattr(study_profiles, "run_claims", lambda *a: pytest.fail("--plan ran a study"))
    assert reproduce.main(["--profile", "claims", "--plan"]) == 0
    text = capsys.readouterr().out
    for study in study_lists.PROFILES["claims"]:
        for piece in study_lists.slices(study):
            assert f"compare.dir=outputs/experiments/claims/{piece.folder} " in text
    parts = [
        int(line.split("about ")[1].split(" min")[0])
        for line in text.splitlines()
        if line.startswith("part ")
    ]
    assert max(parts) <= 80  # every part resumable within a 90-minute run
    hours = float(text.rsplit("expected total: about ", 1)[1].split(" h")[0])
    expected = sum(study.seconds() for study in study_lists.PROFILES["claims"]) / 3600
    # parts cover every study
    assert abs(hours - expected) <= 0.05 and abs(sum(parts) / 60 - expected) <= 0.1
    assert reproduce.main(["--profile", "claims-long", "--plan"]) == 0
    assert (
        "compare.dir=outputs/experiments/claims-long/quantum_control_5" in capsys.readouterr().out
    )
    assert reproduce.main(["--profile", "claims", "--part", "99"]) == 2
    assert "--part takes numbers from 1 to" in capsys.readouterr().err


def test_missing_experiment_is_a_one_line_error():
    with pytest.raises(
        Exception, match=r"unknown experiment 'nosuch' \(choose one of fig2_quantum"
    ):
        check_overrides(["+experiment=nosuch"], multirun=True)


def test_the_manifest_keeps_an_interpolated_override_as_the_job_folder_does(tmp_path):
    """Hydra writes `init_from=.../${seed}/...` into the job's overrides.yaml unresolved; the
    manifest must match it, or every job of a continuation sweep is reported as never started."""
    from physgrad.sweeps import expected_jobs, unfinished_jobs, write_manifest

    overrides = ["task=toy", "seed=1", "init_from='runs/seed=${seed}/results.h5'"]
    with initialized():
        cfg = hydra_compose("config", overrides, return_hydra_config=True)
    jobs = expected_jobs(cfg)
    assert jobs == [overrides]
    write_manifest(tmp_path, jobs)
    job = tmp_path / "job"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    assert unfinished_jobs(tmp_path) == [(",".join(overrides), "no results file")]
    (job / "results.h5").touch()
    assert unfinished_jobs(tmp_path) == []
