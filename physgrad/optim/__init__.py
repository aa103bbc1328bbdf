"""Update rules, each an optax GradientTransformation, built from the `optim` config group."""

from __future__ import annotations

from typing import NamedTuple

import optax

from physgrad import UserError
from physgrad.optim.spectral import spectral_rule

OPTIMS = ("adam", "gd", "gauss_newton", "hig", "bptt", "stable_bptt")
CLIPPING = ("none", "value", "norm")
# Only the time-axis variants need a backprop mode (the StableBPTT paper's modes, physgrad/unroll.py).
BACKPROP_MODES = ("R", "M", "S", "C")


class UpdateRule(NamedTuple):
    """transform: the optax transformation; uses_jacobian: it needs the per-sample Jacobian J and
    output_grad g = dL/dy as extra arguments (so the step builds J every step); backprop: mode for temporal
    scenes, or None."""

    transform: optax.GradientTransformation
    uses_jacobian: bool
    backprop: str | None = None


def clipping(kind: str) -> optax.GradientTransformation:
    """Clip before Adam: element-wise to [-1, 1] (value), global norm to 1 (norm), or not at all."""
    return {"none": optax.identity, "value": lambda: optax.clip(1.0), "norm": lambda: optax.clip_by_global_norm(1.0)}[
        kind
    ]()


def build_rule(optim_cfg) -> UpdateRule:
    name = optim_cfg.name
    lr = float(optim_cfg.lr)
    if name == "adam":
        return UpdateRule(optax.adam(lr, b1=optim_cfg.b1, b2=optim_cfg.b2, eps=optim_cfg.eps), False)
    if name == "gd":
        return UpdateRule(optax.sgd(lr), False)
    if name in ("hig", "gauss_newton"):
        return UpdateRule(spectral_rule(lr, float(optim_cfg.kappa), float(optim_cfg.tau), optim_cfg.route,
                                        bool(optim_cfg.retry_float64)), True)
    if name in ("bptt", "stable_bptt"):
        adam = optax.adam(lr, b1=optim_cfg.b1, b2=optim_cfg.b2, eps=optim_cfg.eps)
        return UpdateRule(optax.chain(clipping(optim_cfg.clip), adam), False, optim_cfg.backprop)
    raise UserError(f"unknown optim '{name}': choose one of {', '.join(OPTIMS)}")
