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
- scheduled_update: the factory (a dotted path) of the rule's ScheduledUpdate: a step that does an
  expensive part (PSGD Kron's preconditioner fit) with a probability p_t falling along the run, so
  that the calibrated clock charges step t its expected cost c + p_t u (ScheduledUpdate) rather
  than the cost of the first steps, where p_t = 1;
- search_range: the log-uniform learning-rate range `physgrad compare` tunes over, per family, each
  spanning the papers' presets by two decades or more on either side (docs/protocol.md);
- knobs: (key, low, high) of the rule's other settings its authors tune, each log-uniform over a
  range spanning physgrad's preset by two decades or more on either side where the setting allows
  (a probability step stops at 1), tuned beside the learning rate with compare.knobs=true: Adam's
  eps, the Jacobian rules' truncation tau (Gauss-Newton, HIG) or damping (Levenberg-Marquardt,
  K-FAC), PSGD Kron's preconditioner step, Muon's Adam step for the non-matrix parameters, and
  two whole numbers, searched log-uniformly over whole numbers: L-BFGS's memory [2, 100] (the
  curvature pairs it keeps; preset 10) and SOAP's preconditioning frequency [1, 100] (the steps
  between recomputations of its eigenbasis; preset 10). SSBFGS and SSBroyden have none: they keep
  no memory (a dense matrix), and their line search's step cap is a safeguard, not a setting
  their authors tune;
- cost_knob: (key, shape) of the setting that changes what the rule's step costs, so that a tuned
  value is charged its own cost (knob_cost, below): "inverse" for a
  period f (a step costs c + u / f: SOAP's eigenbasis every f steps), "linear" for a count m (a
  step costs a + b m: L-BFGS's two-loop recursion over m curvature pairs), "floor" for a value
  that picks the computation (the Jacobian rules' truncation tau: the thin SVD of J below
  GRAM_MIN_TAU, the float64 Gram eigendecomposition at or above it where J is wide, up to 5x
  cheaper on the oscillators); cost_breaks: the values inside the range where the cost changes at
  once, calibrated besides the range's ends.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from physgrad.errors import UserError

if TYPE_CHECKING:
    import numpy as np


@dataclass(frozen=True)
class Capabilities:
    family: str
    search_range: tuple[float, float]
    needs_jacobian: bool = False
    elementwise: bool = False
    needs_matrices: bool = False
    needs_layer_factors: bool = False
    line_search: bool = False
    scheduled_update: str | None = None
    knobs: tuple[tuple[str, float, float], ...] = ()  # ints for a whole-number knob
    cost_knob: tuple[str, str] | None = None  # (key, "inverse", "linear" or "floor")
    cost_breaks: tuple[float, ...] = ()  # where a "floor" cost changes at once


# the smallest truncation the float64 Gram route resolves (physgrad.optim.spectral.route_for):
# below it the Jacobian rules factorise J by its thin SVD, a step that costs several times more
GRAM_MIN_TAU = 1e-6


# mean-over-samples loss; presets 0.5 to 1; the truncation tau around its preset 1e-6, the
# relative damping around its preset 1e-3
TRUNCATION, DAMPING = ("tau", 1e-9, 1e-3), ("damping", 1e-6, 1.0)
JACOBIAN = Capabilities("jacobian", (1e-3, 1e1), needs_jacobian=True)
# Adam and the other optax rules (presets 1e-4 to 1e-3)
ADAPTIVE = Capabilities("adaptive", (1e-5, 1e-1))
ADAPTIVE_ELEMENTWISE = Capabilities("adaptive", ADAPTIVE.search_range, elementwise=True)

RULES: dict[str, Capabilities] = {
    "physgrad.optim.spectral.spectral_rule": replace(
        JACOBIAN, knobs=(TRUNCATION,), cost_knob=("tau", "floor"), cost_breaks=(GRAM_MIN_TAU,)
    ),
    "physgrad.optim.spectral.marquardt_rule": replace(JACOBIAN, knobs=(DAMPING,)),
    "physgrad.optim.kfac.kfac": Capabilities(
        "jacobian",
        JACOBIAN.search_range,
        needs_jacobian=True,
        needs_layer_factors=True,
        knobs=(DAMPING,),
    ),
    "optax.sgd": Capabilities("sgd", (1e-4, 1e1), elementwise=True),  # plain gradient descent
    # the rate scales the direction before its line search
    "optax.lbfgs": Capabilities(
        "lbfgs",
        (1e-2, 1e1),
        elementwise=True,
        line_search=True,
        knobs=(("memory_size", 2, 100),),
        cost_knob=("memory_size", "linear"),
    ),
    # a dense inverse Hessian over the flat vector, then the same zoom line search as L-BFGS
    "physgrad.optim.quasi_newton.self_scaled_broyden": Capabilities(
        "lbfgs", (1e-2, 1e1), elementwise=True, line_search=True
    ),
    # the biases' and gains' Adam step, over Adam's range
    "optax.contrib.muon": Capabilities(
        "adaptive",
        ADAPTIVE.search_range,
        needs_matrices=True,
        knobs=(("adam_learning_rate", *ADAPTIVE.search_range),),
    ),
    # Adam in Shampoo's eigenbasis per weight matrix: given the layers, not one flat vector
    "physgrad.optim.soap.soap": Capabilities(
        "adaptive",
        ADAPTIVE.search_range,
        knobs=(("precondition_frequency", 1, 100),),
        cost_knob=("precondition_frequency", "inverse"),
    ),
    # a Kronecker-factored preconditioner per weight matrix: given the layers, not one flat vector
    # the preconditioner's step on its Lie group: preset 0.1, at most 1
    "physgrad.optim.psgd.psgd_kron": Capabilities(
        "adaptive",
        ADAPTIVE.search_range,
        scheduled_update="physgrad.optim.psgd.scheduled_update",
        knobs=(("preconditioner_lr", 1e-3, 1.0),),
    ),
    **{
        f"optax.{name}": ADAPTIVE_ELEMENTWISE
        for name in (
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
    # eps around physgrad's preset 1e-7 (Keras's; PyTorch's 1e-8)
    "optax.adam": replace(ADAPTIVE_ELEMENTWISE, knobs=(("eps", 1e-10, 1e-4),)),
}


def capabilities(optim_cfg: Mapping[str, Any]) -> Capabilities:
    """The capabilities of the rule an optim config builds (by its `_target_`); a factory not listed
    here is an adaptive rule given the network's layers."""
    return RULES.get(str(optim_cfg.get("_target_", "")), ADAPTIVE)


# each rule's settings and the values they take, checked where the rule is built, before any job
# (check_settings): a mistake in a config is refused in one line, not reported as a failed run.
# key: (low, high, what) with what "decay" [0, 1), "positive" (0, inf), "count" an integer >= 1,
# "probability" (0, 1]; null (None) passes where the rule's default takes over.
_DECAY, _POSITIVE, _COUNT, _PROBABILITY = "decay", "positive", "count", "probability"
SETTINGS: dict[str, dict[str, str]] = {
    "optax.adam": {"b1": _DECAY, "b2": _DECAY, "eps": _POSITIVE},
    "optax.adamw": {"b1": _DECAY, "b2": _DECAY, "eps": _POSITIVE},
    "physgrad.optim.soap.soap": {
        "b1": _DECAY,
        "b2": _DECAY,
        "shampoo_b2": _DECAY,
        "eps": _POSITIVE,
        "precondition_frequency": _COUNT,
        "max_precondition_dim": _COUNT,
    },
    "physgrad.optim.psgd.psgd_kron": {
        "b1": _DECAY,
        "preconditioner_lr": _POSITIVE,
        "preconditioner_update_probability": _PROBABILITY,
        "preconditioner_init_scale": _POSITIVE,
        "max_size_triangular": _COUNT,
        "grad_clip_max_amp": _POSITIVE,
    },
}
_SAID = {
    _DECAY: "a number in [0, 1)",
    _POSITIVE: "a number above 0",
    _COUNT: "a whole number of 1 or more",
    _PROBABILITY: "a probability in (0, 1]",
}


def check_settings(optim_cfg: Mapping[str, Any]) -> None:
    """Every declared setting of the rule (SETTINGS) that the config gives, within its values;
    UserError (one line) naming the key and what it takes otherwise."""
    for key, kind in SETTINGS.get(str(optim_cfg.get("_target_", "")), {}).items():
        value = optim_cfg.get(key)
        if value is None:
            continue
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = number and math.isfinite(value)
        if ok and kind == _DECAY:
            ok = 0 <= value < 1
        elif ok and kind == _POSITIVE:
            ok = value > 0
        elif ok and kind == _COUNT:
            ok = float(value).is_integer() and value >= 1
        elif ok and kind == _PROBABILITY:
            ok = 0 < value <= 1
        if not ok:
            raise UserError(
                f"optim.{key}={value} is not allowed for optim={optim_cfg.get('name')}: give "
                f"{_SAID[kind]}"
            )


@dataclass(eq=False)  # one schedule is itself (its cumulative sum is a cache)
class ScheduledUpdate:
    """A step whose expensive part runs with probability p_t at step t (t = 1, 2, ...), so that
    step t costs c + p_t u on average and n steps cost

        charged(n) = n c + u sum_{t <= n} p_t = n (s - u) + u expected_updates(n),

    with s = c + u the cost of a step that updates (the first steps, p_t = 1). probability(t) gives
    p_t for an array of steps; full_steps: the steps from the first on with p_t = 1 (a calibration
    times the updating step there); floor_step: a step from which p_t stays at its lowest value
    (where it times the other); at_step(opt_state, t): the state as if t steps had been taken (the
    step counter set, nothing else), so that the next step draws with p_{t+1}."""

    probability: Callable[[np.ndarray], np.ndarray]
    full_steps: int
    floor_step: int
    at_step: Callable[[Any, int], Any]
    _cumulative: Any = field(default=None, repr=False)  # sum_{t <= n} p_t for n = 0, 1, ...

    @property
    def floor(self) -> float:
        """p_t from floor_step on."""
        import numpy as np

        return float(self.probability(np.array([self.floor_step]))[0])

    def expected_updates(self, steps: int) -> float:
        """sum_{t <= steps} p_t: up to floor_step from a cumulative sum kept and doubled as runs
        grow (the clock reads it at every step), beyond it in closed form, p_t being the floor
        there."""
        import numpy as np

        if steps > self.floor_step:
            return self.expected_updates(self.floor_step) + (steps - self.floor_step) * self.floor
        known = 0 if self._cumulative is None else self._cumulative.size
        if steps >= known:
            size = max(2 * known, steps + 1, 1024)
            p = np.asarray(self.probability(np.arange(1, size, dtype=np.int64)), np.float64)
            self._cumulative = np.concatenate([[0.0], np.cumsum(p)])
        return float(self._cumulative[steps])

    def charged_seconds(self, steps: int, step_cost: float, update_cost: float) -> float:
        """charged(steps) above: step_cost is s, an updating step's cost, and update_cost is u."""
        return steps * (step_cost - update_cost) + update_cost * self.expected_updates(steps)


def scheduled_update(optim_cfg: Mapping[str, Any]) -> ScheduledUpdate | None:
    """The ScheduledUpdate of the rule an optim config builds with its arguments, or None for a step
    of one cost (every rule but PSGD Kron with its annealed schedule)."""
    factory = capabilities(optim_cfg).scheduled_update
    if factory is None:
        return None
    module, name = factory.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)(optim_cfg)


def knob_cost(
    shape: str, value: float, low: float, low_cost: float, high: float, high_cost: float
) -> float:
    """A step's cost at a setting's value, from its costs calibrated at the range's ends: for a
    period f ("inverse": an expensive part every f steps) c + u / f, for a count m ("linear")
    a + b m, each through the two ends, so a value between them costs between their costs:

        cost = low_cost + t (high_cost - low_cost),
        t = (1/f - 1/low) / (1/high - 1/low)  or  (m - low) / (high - low);

    for a value that picks the computation ("floor", calibrated at each break) the cost of the
    point at or below it: low_cost for low <= value < high, high_cost at high."""
    if shape == "floor":
        return high_cost if value >= high else low_cost
    if high == low:
        return low_cost
    if shape == "inverse":
        t = (1 / value - 1 / low) / (1 / high - 1 / low)
    elif shape == "linear":
        t = (value - low) / (high - low)
    else:
        raise ValueError(f"cost_knob shape {shape!r}: give inverse, linear or floor")
    return low_cost + t * (high_cost - low_cost)


def knob_step_cost(cost_knob: tuple, value: float, evaluations: float = 0.0) -> float:
    """A step's cost at a cost-shaping setting's value (Variant.cost_knob: (key, shape, ((value,
    own seconds), ...)) at the calibrated points, the range's ends and the preset): its own part
    through the two points around the value (knob_cost; a value outside them taken at the nearer
    end), plus the line-search evaluations a step is charged besides (seconds)."""
    _, shape, points = cost_knob
    value = min(max(value, points[0][0]), points[-1][0])
    upper = max(next(i for i, (v, _) in enumerate(points) if v >= value), 1)
    (low, low_cost), (high, high_cost) = points[upper - 1], points[upper]
    return max(knob_cost(shape, value, low, low_cost, high, high_cost), 0.0) + evaluations


def cost_points(kind: Capabilities, low: float, high: float) -> tuple[float, ...]:
    """The values a cost-shaping setting tuned over [low, high] is calibrated at: the range's ends
    and the rule's breaks inside it (Capabilities.cost_breaks)."""
    return (low, *(b for b in kind.cost_breaks if low < b < high), high)
