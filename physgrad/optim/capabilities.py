"""What each update rule needs and allows, declared once and read by the rule builder, the runner's
checks and `physgrad compare` (a new rule is one entry here).

A rule is known by its factory (`_target_`), not by the name of its config file: a renamed copy of
adam.yaml is Adam. Capabilities:
- needs_jacobian: the step takes the network-through-physics Jacobian (Gauss-Newton, HIG,
  Levenberg-Marquardt, K-FAC), through the Jacobian pass of physgrad.gradients;
- elementwise: the rule acts on every parameter element on its own (or on global inner products), so
  on one flat vector it computes exactly what it computes on the network's tree, in one fused kernel
  instead of one per layer; every other rule is given the network's layers (Muon, Adafactor, LAMB,
  LARS, ...);
- needs_matrices: the rule has nothing to do without 2-D weight matrices (Muon);
- needs_layer_factors: the rule takes the Jacobian in layer factors (K-FAC's Kronecker factors),
  which a scene whose Jacobian is only available per sample cannot give;
- line_search: the step searches along its direction with a number of loss evaluations that varies
  from step to step (a zoom line search); trained together in one vectorised step, every member
  waits for the slowest member's evaluations (a vmapped while loop runs until all are done), so
  `physgrad compare` trains such a rule's trials and seeds one job each;
- search_range: the log-uniform learning-rate range `physgrad compare` tunes over, per family, each
  spanning the papers' presets by two decades or more on either side (docs/protocol.md).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Capabilities:
    family: str
    search_range: tuple[float, float]
    needs_jacobian: bool = False
    elementwise: bool = False
    needs_matrices: bool = False
    needs_layer_factors: bool = False
    line_search: bool = False


# mean-over-samples loss; presets 0.5 to 1
JACOBIAN = Capabilities("jacobian", (1e-3, 1e1), needs_jacobian=True)
# Adam and the other optax rules (presets 1e-4 to 1e-3)
ADAPTIVE = Capabilities("adaptive", (1e-5, 1e-1))
ADAPTIVE_ELEMENTWISE = Capabilities("adaptive", ADAPTIVE.search_range, elementwise=True)

RULES: dict[str, Capabilities] = {
    "physgrad.optim.spectral.spectral_rule": JACOBIAN,
    "physgrad.optim.spectral.marquardt_rule": JACOBIAN,
    "physgrad.optim.kfac.kfac": Capabilities(
        "jacobian", JACOBIAN.search_range, needs_jacobian=True, needs_layer_factors=True
    ),
    "optax.sgd": Capabilities("sgd", (1e-4, 1e1), elementwise=True),  # plain gradient descent
    "optax.lbfgs": Capabilities(
        "lbfgs", (1e-2, 1e1), elementwise=True, line_search=True
    ),  # scales the direction before its line search
    # a dense inverse Hessian over the flat vector, then the same zoom line search as L-BFGS
    "physgrad.optim.quasi_newton.self_scaled_broyden": Capabilities(
        "lbfgs", (1e-2, 1e1), elementwise=True, line_search=True
    ),
    "optax.contrib.muon": Capabilities("adaptive", ADAPTIVE.search_range, needs_matrices=True),
    # Adam in Shampoo's eigenbasis per weight matrix: given the layers, not one flat vector
    "physgrad.optim.soap.soap": Capabilities("adaptive", ADAPTIVE.search_range),
    # a Kronecker-factored preconditioner per weight matrix: given the layers, not one flat vector
    "physgrad.optim.psgd.psgd_kron": Capabilities("adaptive", ADAPTIVE.search_range),
    **{
        f"optax.{name}": ADAPTIVE_ELEMENTWISE
        for name in (
            "adam",
            "adamw",
            "adamax",
            "adamaxw",
            "nadam",
            "nadamw",
            "radam",
            "amsgrad",
            "adabelief",
            "adadelta",
            "adagrad",
            "adan",
            "lion",
            "rmsprop",
            "sign_sgd",
            "noisy_sgd",
            "yogi",
            "rprop",
        )
    },
}


def capabilities(optim_cfg: Mapping[str, Any]) -> Capabilities:
    """The capabilities of the rule an optim config builds (by its `_target_`); a factory not listed
    here is an adaptive rule given the network's layers."""
    return RULES.get(str(optim_cfg.get("_target_", "")), ADAPTIVE)
