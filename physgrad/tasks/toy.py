"""The badly scaled toy of the HIG paper: learn x -> (sin 6x, cos 9x) through a "physics" that
scales its second component by lambda.

Input x ~ U(-1, 1); the network predicts (a, b); the physical output is y = P(a, b) = (a, lambda b)
and the per-sample loss is 1/2 |y - P(sin 6x, cos 9x)|^2. With lambda = 0.01 the second component
contributes 10^-4 of the curvature of the first: gradient methods neglect it, a full inversion
(Gauss-Newton) amplifies it by 1/lambda, and the half inversion of HIG balances the two.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.validate import layer_widths, number

if TYPE_CHECKING:
    from physgrad.nets import Params


def targets(x: jax.Array) -> jax.Array:
    return jnp.stack([jnp.sin(6.0 * x), jnp.cos(9.0 * x)], axis=-1)


def build(key: jax.Array, *, scale: float, hidden: Sequence[int], test_size: int) -> Scene:
    scale = number("task.scale", scale, 0, open_low=True)
    hidden = layer_widths("task.hidden", hidden)
    test_size = number("task.test_size", test_size, 1, integer=True)
    dtype = jnp.zeros(()).dtype
    physics = jnp.array([1.0, scale], dtype)

    def make_batch(k: jax.Array, count: int) -> dict[str, jax.Array]:
        x = jax.random.uniform(k, (count, 1), dtype, -1.0, 1.0)
        return {"x": x, "target": physics * targets(x[:, 0])}

    def sample_output(params: Params, sample: dict[str, jax.Array]) -> jax.Array:
        return physics * apply_mlp(params, sample["x"], hidden="tanh")

    def sample_loss(y: jax.Array, sample: dict[str, jax.Array]) -> jax.Array:
        return 0.5 * jnp.sum((y - sample["target"]) ** 2)

    def sample_metrics(
        params: Params, sample: dict[str, jax.Array], y: jax.Array
    ) -> dict[str, jax.Array]:
        # the error of each component of the network's prediction, before the physics scales it
        error = jnp.abs(apply_mlp(params, sample["x"], hidden="tanh") - targets(sample["x"][0]))
        return {"error_first": error[0], "error_second": error[1]}

    return Scene(
        init_params=lambda k: init_mlp(k, [1, *hidden, 2], dtype),
        draw_batch=lambda k, count, train_set: make_batch(k, count),
        test_set=make_batch(key, test_size),
        sample_output=sample_output,
        sample_loss=sample_loss,
        sample_metrics=sample_metrics,
    )
