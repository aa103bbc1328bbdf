"""Rollouts over lax.scan with the backprop-through-time modes of the StableBPTT paper.

A closed loop runs c_k = policy(x_k), x_{k+1} = step(x_k, c_k) for k = 0..unroll-1. The forward
values are the same in every mode; the mode decides where gradients are stopped, at every step:

| mode | policy input | physics input | meaning                                                   |
|------|--------------|---------------|-----------------------------------------------------------|
| R    | x_k          | x_k           | regular backpropagation through time                      |
| M    | sg(x_k)      | x_k           | gradients travel back in time only through the physics    |
| S    | sg(x_k)      | sg(x_k)       | no long-range backprop: a control sees its one-step effect |

C (the stabilised gradient) is built on top from the M and R gradients:
`physgrad.gradients.Combined`.
A temporal scene describes its rollout once as `Dynamics`; `Dynamics.output(mode)` is its physical
output y(params, sample) with that mode's gradient stops.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

if TYPE_CHECKING:
    from physgrad.nets import Params, Pytree


class Backprop(NamedTuple):
    """Where a rollout stops gradients: before the policy's input, before the physics' input."""

    stop_policy_input: bool
    stop_physics_input: bool


REGULAR = Backprop(False, False)
PHYSICS_ONLY = Backprop(True, False)
STOPPED = Backprop(True, True)
MODES = {"R": REGULAR, "M": PHYSICS_ONLY, "S": STOPPED}


def rollout(
    step: Callable,
    policy: Callable,
    x0: Pytree,
    unroll: int,
    backprop: Backprop = REGULAR,
    observe: Callable | None = None,
    checkpoint: bool = False,
) -> tuple[Pytree, Pytree]:
    """Scan x_{k+1} = step(x_k', policy(x_k'', k)) for k = 0..unroll-1, with x_k' and x_k'' the
    state or its stopped copy as ``backprop`` says. Returns (x_unroll, stacked observe(x_{k+1},
    c_k)) where observe defaults to None (nothing stacked).

    The scan keeps lax.scan's own `unroll=1` (no loop unrolling: under grad, XLA's compile time on
    CPU grows steeply with it). checkpoint=True rematerialises each step's internals in the backward
    pass (jax.checkpoint on the scan body): memory then grows with the number of steps times the
    state only.
    """

    def body(x: Pytree, k: jax.Array) -> tuple[Pytree, Pytree]:
        policy_input = lax.stop_gradient(x) if backprop.stop_policy_input else x
        physics_input = lax.stop_gradient(x) if backprop.stop_physics_input else x
        control = policy(policy_input, k)
        x_next = step(physics_input, control)
        return x_next, (None if observe is None else observe(x_next, control))

    if checkpoint:
        body = jax.checkpoint(body)
    return lax.scan(body, x0, jnp.arange(unroll))


def final_state(final: Pytree, observed: Pytree, sample: Pytree) -> Pytree:
    """The default readout: y = x_unroll."""
    return final


@dataclass(frozen=True)
class Dynamics:
    """A temporal scene's rollout, from which every backprop mode's output is built:
        x_0 = initial(sample),  c_k = policy(params, sample)(x_k, k),  x_{k+1} = step(x_k, c_k),
        y = readout(x_unroll, observed, sample),  observed = [observe(x_{k+1}, c_k, sample) for each
        k] (or None).

    policy(params, sample) returns the controller of one sample: a closed-loop one
    (closed_loop=True) uses the state it is given; an open-loop one may compute every control up
    front (it is called once, outside the loop) and only index them by k. Only a closed loop has a
    policy input for the modes M and S to stop. checkpoint: rematerialise every step in the backward
    pass (memory for long unrolls).
    """

    step: Callable[[Any, Any], Any]
    policy: Callable[[Any, Any], Callable[[Any, jax.Array], Any]]
    initial: Callable[[Any], Any]
    unroll: int
    closed_loop: bool
    readout: Callable[[Any, Any, Any], jax.Array] = final_state
    observe: Callable[[Any, Any, Any], Any] | None = None
    checkpoint: bool = False

    def output(self, backprop: Backprop = REGULAR) -> Callable[[Any, Any], jax.Array]:
        """y(params, sample) with the gradient stops of ``backprop``."""

        def sample_output(params: Params, sample: Pytree) -> jax.Array:
            observe = None if self.observe is None else (lambda x, c: self.observe(x, c, sample))
            final, observed = rollout(
                self.step,
                self.policy(params, sample),
                self.initial(sample),
                self.unroll,
                backprop,
                observe=observe,
                checkpoint=self.checkpoint,
            )
            return self.readout(final, observed, sample)

        return sample_output
