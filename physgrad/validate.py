"""Config values checked with one-line messages that name the key and what is allowed."""

from __future__ import annotations

import numbers

from omegaconf import OmegaConf

from physgrad import UserError


def number(cfg, key: str, low=None, high=None, integer=False, optional=False, open_low=False, prefix: str = ""):
    """The value at ``key``, if it is a (whole) number within [low, high) (or (low, high) with open_low).
    ``prefix`` names the config section ``cfg`` stands for (e.g. "task"), for the message."""
    value = OmegaConf.select(cfg, key)
    if value is None and optional:
        return None
    ok = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, bool)
    if ok and low is not None:
        ok = value > low if open_low else value >= low
    if ok and high is not None:
        ok = value < high
    if not ok:
        bounds = []
        if low is not None:
            bounds.append(f"{'>' if open_low else '>='} {low}")
        if high is not None:
            bounds.append(f"< {high}")
        kind = "a whole number" if integer else "a number"
        extra = " or null" if optional else ""
        raise UserError(f"{_name(prefix, key)}={value!r} is not allowed: use {kind} {' and '.join(bounds)}".rstrip()
                        + extra)
    return value


def choice(cfg, key: str, choices, prefix: str = ""):
    value = OmegaConf.select(cfg, key)
    if value not in choices:
        raise UserError(f"{_name(prefix, key)}={value!r} is not allowed: choose one of {', '.join(map(str, choices))}")
    return value


def flag(cfg, key: str, prefix: str = "") -> bool:
    return choice(cfg, key, (False, True), prefix)


def layer_widths(cfg, key: str, prefix: str = "") -> list[int]:
    """A non-empty list of positive whole numbers (hidden layer widths)."""
    value = OmegaConf.select(cfg, key)
    widths = list(value) if OmegaConf.is_list(value) or isinstance(value, (list, tuple)) else None
    if not widths or not all(isinstance(w, int) and not isinstance(w, bool) and w > 0 for w in widths):
        raise UserError(f"{_name(prefix, key)}={value!r} is not allowed: use a list of positive layer widths, "
                        "e.g. [20, 20]")
    return widths


def _name(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key
