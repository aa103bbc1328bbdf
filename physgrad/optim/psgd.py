"""PSGD Kron (Li, "Preconditioned stochastic gradient descent", IEEE TNNLS 2018, arXiv 1512.04202;
"Preconditioner on matrix Lie group for SGD", ICLR 2019, arXiv 1809.10232): stochastic gradient
descent preconditioned per weight matrix by a Kronecker product fitted online, from the `psgdax`
package (a JAX translation of Li's reference code, psgd_torch), as an optax rule.

For a weight matrix with gradient G (m x n) the preconditioner is P = (Q_L^T Q_L) (x) (Q_R^T Q_R),
applied as Q_L^T Q_L G Q_R^T Q_R (Q_L, Q_R triangular; diagonal for a side longer than
`max_size_triangular` or whose size squared exceeds m n; vectors such as biases get a diagonal Q).
In the whitening form used here Q is fitted, by a step of size `preconditioner_lr` on the matrix
Lie group, to the criterion

    E[h^T P h + v^T P^-1 v],   h the gradient, v ~ N(0, I),

whose minimiser P = E[h h^T]^(-1/2) whitens the gradient (P E[h h^T] P = I): Adam's diagonal
1 / sqrt(v) made a Kronecker-factored matrix. Q is updated with probability p_t at step t (1 for
the first 500 steps, then decaying to 0.03; `preconditioner_update_probability` fixes it), starts at
a scale set from the first gradient, scale = (max over leaves of mean |g|^4)^(-1/8), and the step is

    m <- beta_t m + (1 - beta_t) g,   beta_t = min(t / (t + 1), b1),   update = -lr clip(P m),

with t the steps taken before (the first m is g), and clip scaling each leaf's step down to an RMS
of at most `grad_clip_max_amp`. With Q never updated (probability 0) and a given init scale s,
P = s^2 I: momentum gradient descent at the rate lr s^2 (tests/numerics/test_psgd.py).

physgrad calls psgdax.kron with these arguments and changes nothing in what it computes, with two
repairs of how psgdax keeps its state: the Lipschitz estimates it keeps for each Q (which psgdax
0.1.1 makes float32 whatever the parameters' precision, so that a float64 run stops at its first
step with a dtype mismatch) are kept in the parameters' precision, and its note of the
preconditioner's size, printed when the state is made, is kept off the console.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import optax

from physgrad.optim.capabilities import ScheduledUpdate

if TYPE_CHECKING:
    import numpy as np

    from physgrad.optim.capabilities import ScheduledUpdate

# psgdax's annealed schedule (precond_update_prob_schedule's defaults): p_t at step t = 1, 2, ...
ANNEALED = {"max_prob": 1.0, "min_prob": 0.03, "decay": 0.001, "flat_start": 500}


def annealed_probability(steps: np.ndarray) -> np.ndarray:
    """p_t = clip(exp(-decay (t - flat_start)), min_prob, max_prob), psgdax's schedule, in float64
    (psgdax evaluates it at the step counter after the increment: t = 1 at the first step)."""
    import numpy as np

    t = np.asarray(steps, np.float64)
    decayed = ANNEALED["max_prob"] * np.exp(-ANNEALED["decay"] * (t - ANNEALED["flat_start"]))
    return np.clip(decayed, ANNEALED["min_prob"], ANNEALED["max_prob"])


def at_step(opt_state: Any, steps: int) -> Any:
    """opt_state with PSGD Kron's step counter set to `steps` (its preconditioners, momentum and
    key unchanged), in whatever tree holds it (a state per seed: the counter's shape is kept)."""
    import psgdax

    def pin(part: Any) -> Any:
        if isinstance(part, psgdax.psgd.KronState):
            return part._replace(count=jnp.full_like(part.count, steps))
        return part

    return jax.tree.map(pin, opt_state, is_leaf=lambda x: isinstance(x, psgdax.psgd.KronState))


def scheduled_update(optim_cfg: Mapping[str, Any]) -> ScheduledUpdate | None:
    """The ScheduledUpdate (physgrad.optim.capabilities) of a psgd_kron config: psgdax's annealed
    schedule (1 for the first flat_start steps, at min_prob from floor_step on), or None where it
    fixes preconditioner_update_probability (every step then costs the same on average)."""
    if optim_cfg.get("preconditioner_update_probability") is not None:
        return None
    floor_step = (
        ANNEALED["flat_start"]
        + math.log(ANNEALED["max_prob"] / ANNEALED["min_prob"]) / (ANNEALED["decay"])
    )
    return ScheduledUpdate(
        probability=annealed_probability,
        full_steps=ANNEALED["flat_start"],
        floor_step=math.ceil(floor_step),
        at_step=at_step,
    )


def psgd_kron(
    learning_rate: optax.ScalarOrSchedule,
    b1: float = 0.9,
    preconditioner_lr: float = 0.1,
    preconditioner_update_probability: float | None = None,
    preconditioner_init_scale: float | None = None,
    max_size_triangular: int = 8192,
    grad_clip_max_amp: float = 1.0,
    whiten_grad: bool = True,
) -> optax.GradientTransformationExtraArgs:
    """PSGD Kron as in the module docstring. preconditioner_update_probability: None anneals it
    (psgdax's schedule, as the reference code), a number fixes it; preconditioner_init_scale: None
    sets it from the first gradient; whiten_grad: false whitens the momentum instead of the
    gradient."""
    import psgdax

    if not 0 <= b1 < 1:
        raise ValueError(f"b1={b1}: give a momentum in [0, 1)")
    if not whiten_grad and b1 <= 0:
        raise ValueError("whiten_grad=false whitens the momentum: give b1 > 0")
    if preconditioner_update_probability is not None and not (
        0 <= preconditioner_update_probability <= 1
    ):
        raise ValueError(
            f"preconditioner_update_probability={preconditioner_update_probability}: give a "
            "probability in [0, 1], or null for the annealed schedule"
        )
    probability = (
        psgdax.psgd.precond_update_prob_schedule()
        if preconditioner_update_probability is None
        else float(preconditioner_update_probability)
    )
    rule = psgdax.kron(
        learning_rate=learning_rate,
        b1=b1,
        preconditioner_update_probability=probability,
        max_size_triangular=int(max_size_triangular),
        whiten_grad=whiten_grad,
        preconditioner_lr=preconditioner_lr,
        preconditioner_init_scale=preconditioner_init_scale,
        grad_clip_max_amp=grad_clip_max_amp,
    )

    def init(params: optax.Params) -> optax.OptState:
        with contextlib.redirect_stdout(io.StringIO()):  # psgdax prints the state's size
            state = rule.init(params)
        dtype = jnp.result_type(*jax.tree.leaves(params))

        def in_precision(part: object) -> object:
            if isinstance(part, psgdax.psgd.KronState) and part.Ls_lipschitz is not None:
                lipschitz = jax.tree.map(lambda x: x.astype(dtype), part.Ls_lipschitz)
                return part._replace(Ls_lipschitz=lipschitz)
            return part

        return tuple(in_precision(part) for part in state)

    return optax.GradientTransformationExtraArgs(init, rule.update)
