"""Unit layer of a study on a cluster: the jobs that did not finish are named with their scheduler
ids, and runs on another machine than the calibration are flagged."""

from __future__ import annotations

import pytest

from physgrad.errors import UserError
from physgrad.sweeps import record_job, write_manifest


def test_the_jobs_that_did_not_finish_are_named_with_their_scheduler_ids(tmp_path):
    from physgrad.comparison.jobs import _raise_unfinished

    sweep = tmp_path / "tune"
    names = ["tune_v0_t000", "tune_v1_t000", "tune_v2_t000", "tune_v3_t000"]
    write_manifest(sweep, [[f"+compare_job={n}"] for n in names])
    record_job(sweep, sweep / "a", ["+compare_job=tune_v0_t000"], "completed")
    (sweep / "a").mkdir()
    (sweep / "a" / "results.h5").write_bytes(b"")
    record_job(
        sweep,
        sweep / "b",
        ["+compare_job=tune_v1_t000"],
        "interrupted",
        "SIGTERM after 7 iterations",
        scheduler="4711_1",
    )
    (sweep / "b").mkdir()
    (sweep / "b" / "results.h5").write_bytes(b"")
    record_job(sweep, sweep / "c", ["+compare_job=tune_v2_t000"], "failed", "ValueError: x")
    jobs = dict.fromkeys(names, "")
    with pytest.raises(UserError) as raised:
        _raise_unfinished(sweep, "tune", jobs, tmp_path / "tune.log")
    message = str(raised.value)
    assert message.startswith("tune: 2 of 4 jobs did not finish (")
    assert "tune_v1_t000: interrupted: SIGTERM after 7 iterations (SLURM job 4711_1)" in message
    assert "tune_v3_t000: never started" in message
    assert "tune_v2" not in message and "tune_v0" not in message  # failed: an outcome; finished
    assert message.endswith("run the same command again to finish them")


def test_runs_on_another_machine_than_the_calibration_are_flagged():
    import pandas as pd

    from physgrad.comparison.clock_text import _calibration_lines
    from physgrad.comparison.spec import Variant

    machine = {"cpu_model": "AMD EPYC", "cpu_count": 2, "device": "cpu", "hostname": "login1"}
    calibration = {
        "quantile": 0.2,
        "load_start": 0.1,
        "load_end": 0.1,
        "machine": machine,
        "costs": {"adam": {"step_seconds": 1e-3, "median_seconds": 1e-3, "rounds": 30}},
    }
    variant = Variant("adam", ["optim=adam"], None, {})
    runs = pd.DataFrame(
        {
            "variant": ["adam"],
            "step_seconds_p50": [1e-4],
            "contended": [False],
            "machine": ["AMD EPYC (2 cores), gpu: NVIDIA H100"],
        }
    )
    text = "\n".join(_calibration_lines([variant], runs, calibration))
    assert (
        "calibrated on AMD EPYC (2 cores) (host login1), but runs ran on AMD EPYC (2 cores), gpu"
        in text
    )
    same = runs.assign(machine=["AMD EPYC (2 cores)"])
    assert "host login1" not in "\n".join(_calibration_lines([variant], same, calibration))
    # the measured step per seed: a step of 10 seeds trained together is a tenth of each
    assert "| 0.0001 s |" in text
    together = runs.assign(step_seconds_p50=[1e-3], wall_time_shared_by=[10])
    assert "| 0.0001 s |" in "\n".join(_calibration_lines([variant], together, calibration))
