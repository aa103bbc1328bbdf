"""Unit layer (pure functions, no scene compiled) of the tests of:
Every task x optim pair composes from the configs and either runs or is refused with its
reason."""

import pytest

from tests.helpers import load


@pytest.mark.parametrize("optim, backprop", [("bptt", "R"), ("stable_bptt", "C")])
def test_bptt_presets(optim, backprop):
    assert (
        load("task=oscillator", "task.closed_loop=true", f"optim={optim}").optim.backprop
        == backprop
    )
