"""Code the tests share (not tests themselves)."""

from physgrad.configs import compose


def load(*overrides: str):
    """The composed run config of `physgrad run` with these overrides (without Hydra's own node)."""
    return compose(overrides)
