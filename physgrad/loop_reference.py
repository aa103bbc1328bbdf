"""The references physgrad's checks compare a scene against, for scene authors and tests alike: a
temporal scene's rollout as a plain Python loop (no lax.scan, no stop_gradient: a backprop mode's
stopped inputs are the forward states held constant), and a gradient against fourth-order central
finite differences along random directions."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.unroll import REGULAR, Backprop, Dynamics

if TYPE_CHECKING:
    from physgrad.nets import Params, Pytree

DIRECTIONS = 3  # random directions of the finite differences
FD_RTOL = 1e-5  # the fourth-order stencil in float64 agrees to about 1e-8 on smooth losses


def relative_error(a: Pytree, b: Pytree) -> float:
    """max |a - b| / max(max |b|, tiny) over every leaf of two pytrees."""
    a, b = ravel_pytree(a)[0], ravel_pytree(b)[0]
    scale = max(float(jnp.max(jnp.abs(b))) if b.size else 0.0, 1e-300)
    return float(jnp.max(jnp.abs(a - b))) / scale if a.size else 0.0


def loop_states(
    step: Callable[[Pytree, Pytree], Pytree],
    policy: Callable[[Pytree, int], Pytree],
    x0: Pytree,
    unroll: int,
    backprop: Backprop = REGULAR,
    frozen: list | None = None,
) -> tuple[list, list]:
    """(x_1 .. x_unroll, c_0 .. c_unroll-1) of c_k = policy(x_k, k), x_{k+1} = step(x_k, c_k) by a
    plain Python loop (no lax.scan, no stop_gradient): the inputs a mode stops are the constant
    forward states `frozen` (x_0 .. x_unroll at the parameters the gradient is taken at; None:
    computed here, as constants), so
    differentiating this gives that mode's gradient and finite differences of it check the same
    thing."""
    if frozen is None:
        frozen = forward_states(step, policy, x0, unroll)
    x, states, controls = x0, [], []
    for k in range(unroll):
        control = policy(frozen[k] if backprop.stop_policy_input else x, k)
        x = step(frozen[k] if backprop.stop_physics_input else x, control)
        states.append(x)
        controls.append(control)
    return states, controls


def forward_states(
    step: Callable[[Pytree, Pytree], Pytree],
    policy: Callable[[Pytree, int], Pytree],
    x0: Pytree,
    unroll: int,
) -> list:
    """x_0 .. x_unroll of the forward pass by a plain loop, as constants (stop_gradient): the values
    every mode shares."""
    states = [x0]
    for k in range(unroll):
        states.append(step(states[-1], policy(states[-1], k)))
    return [jax.lax.stop_gradient(state) for state in states]


def dynamics_forward_states(dynamics: Dynamics, params: Params, sample: Pytree) -> list:
    """forward_states of a scene's Dynamics for one sample."""
    return forward_states(
        dynamics.step, dynamics.policy(params, sample), dynamics.initial(sample), dynamics.unroll
    )


def loop_output(
    dynamics: Dynamics,
    params: Params,
    sample: Pytree,
    backprop: Backprop = REGULAR,
    frozen: list | None = None,
) -> jax.Array:
    """A temporal scene's output y for one sample by loop_states (frozen: dynamics_forward_states at
    the parameters the gradient is taken at)."""
    if frozen is None:
        frozen = dynamics_forward_states(dynamics, params, sample)
    states, controls = loop_states(
        dynamics.step,
        dynamics.policy(params, sample),
        dynamics.initial(sample),
        dynamics.unroll,
        backprop,
        frozen,
    )
    observed = None
    if dynamics.observe is not None and states:
        observed = jax.tree_util.tree_map(
            lambda *leaves: jnp.stack(leaves),
            *[dynamics.observe(x, c, sample) for x, c in zip(states, controls)],
        )
    return dynamics.readout(states[-1] if states else dynamics.initial(sample), observed, sample)


def finite_difference_check(
    loss: Callable[[Params], jax.Array],
    params: Params,
    gradient: Params,
    directions: int = DIRECTIONS,
    rtol: float = FD_RTOL,
    step_scale: float = 1.0,
) -> tuple[float, float]:
    """(worst relative mismatch, tolerance) of gradient . d against finite differences of loss along
    random unit directions d: the fourth-order central stencil (8 (L(h) - L(-h)) - (L(2h) - L(-2h)))
    / 12h with h = 1e-3 times the parameters' typical size, whose truncation (h^4) and round-off
    (eps |L| / h) errors both stay near 1e-12 in float64 where a plain central difference loses
    digits on small gradients. The mismatch is relative to max(|gradient . d|, 0.01 |gradient|): a
    wrong gradient is off by O(|gradient|) in a random direction."""
    flat, unravel = ravel_pytree(params)
    flat_gradient = ravel_pytree(gradient)[0]
    h = step_scale * 1e-3 * max(1.0, float(jnp.linalg.norm(flat)) / max(flat.size, 1) ** 0.5)
    worst = 0.0
    for i in range(directions):
        direction = jax.random.normal(jax.random.PRNGKey(100 + i), flat.shape, flat.dtype)
        direction = direction / jnp.linalg.norm(direction)
        at = {k: loss(unravel(flat + k * h * direction)) for k in (-2, -1, 1, 2)}
        estimate = (8 * (at[1] - at[-1]) - (at[2] - at[-2])) / (12 * h)
        exact = flat_gradient @ direction
        scale = max(float(jnp.abs(exact)), 0.01 * float(jnp.linalg.norm(flat_gradient)), 1e-300)
        worst = max(worst, float(jnp.abs(estimate - exact)) / scale)
    return worst, rtol
