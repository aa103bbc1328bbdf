"""Integration layer of the command line: settings refused before anything is built, and a report
threshold that is no loss, through the commands called in-process."""

import pytest


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("seeds=5000", "seeds=5000 is more than 1024 seeds in one process: sweep them instead"),
        (
            "init_from=",
            "init_from='' is not allowed: use the path of a results.h5, or leave init_from out",
        ),
    ],
)
def test_sizes_and_empty_paths_are_refused_before_anything_is_built(tmp_path, override, fragment):
    from physgrad.experiment import run_experiment
    from tests.helpers import load

    outcome, _ = run_experiment(load("task=toy", "trainer.iterations=2", override), tmp_path)
    assert outcome.status == "refused" and fragment in outcome.reason
    assert len(list(tmp_path.rglob("results.h5"))) <= 1


@pytest.mark.parametrize("threshold", ["0", "-1", "nan", "inf", "x"])
def test_a_report_threshold_that_is_no_loss_is_refused(tmp_path, threshold, capsys):
    from physgrad.cli import main

    with pytest.raises(SystemExit) as leaving:
        main(["report", str(tmp_path), "--threshold", threshold])
    err = capsys.readouterr().err
    assert leaving.value.code == 2 and "--threshold" in err
    assert "not a loss" in err or "not a number" in err
