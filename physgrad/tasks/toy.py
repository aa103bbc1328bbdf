"""The badly scaled toy of the PBDL book's chapter on half-inverse gradients: learn
x -> yhat(x) = (sin 6x, cos 9x) for x in [-1, 1] through a loss that scales the network's second
output by lambda.

The network (one hidden layer of 7 tanh neurons, 1 -> 7 -> 2) outputs (y1, y2); the "physics" is
P(y1, y2) = (y1, lambda y2) and the per-sample loss is

    L = 1/2 (y1 - yhat1)^2 + 1/2 (lambda y2 - yhat2)^2,

the target NOT scaled: at lambda = 0.01 the network must output y2 = 100 cos 9x. The second
component then carries lambda^2 = 1e-4 of the first one's curvature: gradient methods crawl toward
the large output weights it needs, a full inversion (Gauss-Newton) takes steps of 1/lambda that
saturate the hidden neurons, and the half inversion of HIG balances the two.

Held-out metrics beside the loss: the error of each physical component (averaged over the test set);
the hidden neurons' activations h over a fixed grid of GRID inputs spanning [-1, 1] (the book's
middle panel): their mean magnitude, their spread (each neuron's standard deviation over the inputs,
averaged over neurons: 0 when every neuron gives one value whatever the input, the saturation the
book shows for Gauss-Newton) and the share of saturated values (|h| > SATURATED); and the physical
output at the fixed input x = PROBE (one sample's path in y-space, the book's third panel). The grid
and the probe do not depend on the test sample, so their average over the test set is their value
(and vmap computes them once).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.nets import ACTIVATIONS, apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.validate import layer_widths, number

if TYPE_CHECKING:
    from physgrad.nets import Params

# the input whose path in y-space the metrics follow (the book shows "a single but fairly
# representative" pair without naming it); yhat(0.3) = (0.97, -0.90)
PROBE = 0.3
# the inputs the activations' statistics are taken over
GRID = 64
# |h| above this counts as a saturated tanh neuron (its derivative is below 0.02)
SATURATED = 0.99


def targets(x: jax.Array) -> jax.Array:
    return jnp.stack([jnp.sin(6.0 * x), jnp.cos(9.0 * x)], axis=-1)


def hidden_activations(params: Params, x: jax.Array) -> jax.Array:
    """Every hidden neuron's tanh activation for one input, the layers' concatenated."""
    layers = []
    for layer in params[:-1]:
        x = ACTIVATIONS["tanh"](x @ layer["w"] + layer["b"])
        layers.append(x)
    return jnp.concatenate(layers)


def build(key: jax.Array, *, scale: float, hidden: Sequence[int], test_size: int) -> Scene:
    scale = number("task.scale", scale, 0, open_low=True)
    hidden = layer_widths("task.hidden", hidden)
    test_size = number("task.test_size", test_size, 1, integer=True)
    dtype = jnp.zeros(()).dtype
    physics = jnp.array([1.0, scale], dtype)

    def make_batch(k: jax.Array, count: int) -> dict[str, jax.Array]:
        x = jax.random.uniform(k, (count, 1), dtype, -1.0, 1.0)
        return {"x": x, "target": targets(x[:, 0])}

    def sample_output(params: Params, sample: dict[str, jax.Array]) -> jax.Array:
        return physics * apply_mlp(params, sample["x"], hidden="tanh")

    def sample_loss(y: jax.Array, sample: dict[str, jax.Array]) -> jax.Array:
        return 0.5 * jnp.sum((y - sample["target"]) ** 2)

    def sample_metrics(
        params: Params, sample: dict[str, jax.Array], y: jax.Array
    ) -> dict[str, jax.Array]:
        error = jnp.abs(y - sample["target"])
        grid = jnp.linspace(-1.0, 1.0, GRID, dtype=dtype)[:, None]
        h = jax.vmap(hidden_activations, (None, 0))(params, grid)  # (inputs, neurons)
        probe = physics * apply_mlp(params, jnp.full((1,), PROBE, dtype), hidden="tanh")
        return {
            "error_first": error[0],
            "error_second": error[1],
            "hidden_magnitude": jnp.mean(jnp.abs(h)),
            "hidden_spread": jnp.mean(jnp.std(h, axis=0)),
            "hidden_saturated": jnp.mean(jnp.abs(h) > SATURATED).astype(dtype),
            "probe_y1": probe[0],
            "probe_y2": probe[1],
        }

    return Scene(
        init_params=lambda k: init_mlp(k, [1, *hidden, 2], dtype),
        draw_batch=lambda k, count, train_set: make_batch(k, count),
        test_set=make_batch(key, test_size),
        sample_output=sample_output,
        sample_loss=sample_loss,
        sample_metrics=sample_metrics,
    )
