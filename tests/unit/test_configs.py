"""Unit layer of the configs: the bptt and stable_bptt presets compose to their backprop modes (R
and C)."""

import pytest

from tests.helpers import load


@pytest.mark.parametrize("optim, backprop", [("bptt", "R"), ("stable_bptt", "C")])
def test_bptt_presets(optim, backprop):
    assert (
        load("task=oscillator", "task.closed_loop=true", f"optim={optim}").optim.backprop
        == backprop
    )


def test_a_sweep_s_first_job_is_composed_from_each_sweep_s_first_value():
    """The overrides of a sweep's first job (where its hydra section is checked): a list, a range
    and a choice by their first value, a glob (which needs Hydra's loader) left out, the rest
    as given."""
    from physgrad.configs import first_of_sweeps

    overrides = ["task=toy", "seed=3,1", "optim=glob(*)", "lr=range(2,5)", "+x=choice(a,b)", "y=1"]
    assert first_of_sweeps(overrides) == ["task=toy", "seed=3", "lr=2", "+x=a", "y=1"]
