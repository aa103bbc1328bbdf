"""Rollouts over lax.scan with the backprop-through-time modes of the StableBPTT paper.

A closed loop runs c_k = policy(x_k), x_{k+1} = step(x_k, c_k) for k = 0..n-1. The forward values are the same
in every mode; the mode decides where gradients are stopped, at every step:

| mode | policy input | physics input | meaning                                                       |
|------|--------------|---------------|---------------------------------------------------------------|
| R    | x_k          | x_k           | regular backpropagation through time                          |
| M    | sg(x_k)      | x_k           | gradients travel back in time only through the physics        |
| S    | sg(x_k)      | sg(x_k)       | no long-range backprop: each control sees its one-step effect |

C (the stabilised gradient) is built on top from the M and R gradients: `combine_signs`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax


class Backprop(NamedTuple):
    """Where a rollout stops gradients: before the policy's input, before the physics' input."""

    stop_policy_input: bool
    stop_physics_input: bool


REGULAR = Backprop(False, False)
PHYSICS_ONLY = Backprop(True, False)
STOPPED = Backprop(True, True)
MODES = {"R": REGULAR, "M": PHYSICS_ONLY, "S": STOPPED}


def rollout(step: Callable, policy: Callable, x0, length: int, backprop: Backprop = REGULAR,
            observe: Callable | None = None, checkpoint: bool = False):
    """Scan x_{k+1} = step(x_k', policy(x_k'', k)) for k = 0..length-1, with x_k' and x_k'' the state or its
    stopped copy as ``backprop`` says. Returns (x_length, stacked observe(x_{k+1}, c_k)) where observe defaults
    to None (nothing stacked).

    checkpoint=True rematerialises each step's internals in the backward pass (jax.checkpoint on the scan
    body): memory then grows with the number of steps times the state only, not times the step's internals.
    """

    def body(x, k):
        policy_input = lax.stop_gradient(x) if backprop.stop_policy_input else x
        physics_input = lax.stop_gradient(x) if backprop.stop_physics_input else x
        control = policy(policy_input, k)
        x_next = step(physics_input, control)
        return x_next, (None if observe is None else observe(x_next, control))

    if checkpoint:
        body = jax.checkpoint(body)
    return lax.scan(body, x0, jnp.arange(length))


def combine_signs(g_physics, g_regular):
    """C = g_M where sign(g_M) == sign(g_R), else 0, per parameter element (its magnitude is always g_M's)."""
    return jax.tree_util.tree_map(lambda m, r: jnp.where(jnp.sign(m) == jnp.sign(r), m, jnp.zeros_like(m)),
                                  g_physics, g_regular)
