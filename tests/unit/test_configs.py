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
