"""Integration layer of the oscillator scene through run_experiment: Adam trains with a 1024-step
unroll at the reference batch size, and the Jacobian rules take finite steps at the reference
settings."""

import numpy as np
import pytest

from tests.helpers import load


# the larger size (a 1024-step unroll at the reference batch): make test-long; make test keeps the
# oscillator trained through the runner at small sizes (test_configs.py's pairs oscillator-gd and
# oscillator task.closed_loop=true-muon)
@pytest.mark.long
def test_long_unroll_runs_for_adam(tmp_path):
    """unroll=1024 at the reference batch size (512) trains without exhausting memory."""
    from physgrad.experiment import run_experiment
    from physgrad.results import read_run

    cfg = load(
        "task=oscillator", "optim=adam", "unroll=1024", "trainer.iterations=2", "task.test_size=64"
    )
    outcome, path = run_experiment(cfg, tmp_path)
    assert outcome.status == "completed", outcome.reason
    assert read_run(path).attrs["unroll"] == 1024


# HIG in make test, Gauss-Newton (the same Jacobian pass, another direction) in make test-long
@pytest.mark.parametrize("optim", ["hig", pytest.param("gauss_newton", marks=pytest.mark.long)])
def test_jacobian_rules_take_finite_steps_at_the_reference_settings(optim, tmp_path):
    from physgrad.experiment import run_experiment
    from physgrad.results import read_run

    outcome, path = run_experiment(
        load("task=oscillator", f"optim={optim}", "trainer.iterations=3", "task.test_size=64"),
        tmp_path,
    )
    assert outcome.status == "completed", outcome.reason
    assert np.all(np.isfinite(read_run(path).train["update_norm"]))
