"""Networks as plain pytrees: dense networks (a list of {"w": (in, out), "b": (out,)} layers), the
quantum controller's CNN and the Kuramoto-Sivashinsky scene's 1-D residual convolutional network."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:
    from jax.typing import DTypeLike

# For annotations: a network's parameters (a pytree of arrays), and any other pytree of arrays (a
# sample, a batch, a state)
Params = Any
Pytree = Any

ACTIVATIONS = {"tanh": jnp.tanh, "relu": jax.nn.relu, "linear": lambda z: z}

# Active layer taps, innermost last: while tracing under one, apply_mlp computes each layer's
# pre-activation as tap(layer, x) instead of x W + b (physgrad.jacobians records inputs and
# cotangents this way).
_TAPS: list = []


@contextmanager
def layer_tap(
    tap: Callable[[dict[str, jax.Array], jax.Array], jax.Array],
) -> Iterator[Callable[[dict[str, jax.Array], jax.Array], jax.Array]]:
    """Route every apply_mlp layer traced inside the block through tap(layer, x) ->
    pre-activation."""
    _TAPS.append(tap)
    try:
        yield tap
    finally:
        _TAPS.pop()


def init_mlp(
    key: jax.Array, sizes: Sequence[int], dtype: DTypeLike, zero_last: bool = False
) -> list[dict[str, jax.Array]]:
    """Glorot-uniform kernels and zero biases (the Keras defaults the reference code trains with).

    A kernel of shape (fan_in, fan_out) is drawn from U(-a, a) with a = sqrt(6 / (fan_in +
    fan_out)). zero_last zero-initialises the output layer, so the network starts with an output of
    exactly 0.
    """
    keys = jax.random.split(key, len(sizes) - 1)
    layers = []
    for index, (k, fan_in, fan_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        limit = (6.0 / (fan_in + fan_out)) ** 0.5
        w = jax.random.uniform(k, (fan_in, fan_out), dtype, -limit, limit)
        if zero_last and index == len(sizes) - 2:
            w = jnp.zeros_like(w)
        layers.append({"w": w, "b": jnp.zeros((fan_out,), dtype)})
    return layers


def apply_mlp(
    layers: Sequence[dict[str, jax.Array]], x: jax.Array, hidden: str, output: str = "linear"
) -> jax.Array:
    """z_{l+1} = act(z_l W_l + b_l) with act = hidden on every layer but the last, output on the
    last.

    Networks built with it get the layer-factorised Jacobian of the Gauss-Newton and HIG steps
    (physgrad.jacobians) when applied once per sample."""
    tap = _TAPS[-1] if _TAPS else None
    for index, layer in enumerate(layers):
        pre_activation = x @ layer["w"] + layer["b"] if tap is None else tap(layer, x)
        x = ACTIVATIONS[output if index == len(layers) - 1 else hidden](pre_activation)
    return x


def count_params(tree: Params) -> int:
    return sum(leaf.size for leaf in jax.tree_util.tree_leaves(tree))


def init_control_cnn(
    key: jax.Array, points: int, dtype: DTypeLike, filters: int = 60
) -> dict[str, dict[str, jax.Array]]:
    """The StableBPTT paper's quantum controller: psi as an (N, 2) image of (Re, Im) ->
    conv2d 60 filters k=(3, 2) stride 2 tanh -> conv1d 60 k=3 stride 2 tanh -> dense 1 (valid
    padding). 11,701 parameters at N = 32. Glorot-uniform kernels with Keras' fans (kernel size
    times channels)."""
    k1, k2, k3 = jax.random.split(key, 3)
    length = ((points - 3) // 2 + 1 - 3) // 2 + 1

    def glorot(k: jax.Array, shape: tuple[int, ...], fan_in: int, fan_out: int) -> jax.Array:
        limit = (6.0 / (fan_in + fan_out)) ** 0.5
        return jax.random.uniform(k, shape, dtype, -limit, limit)

    return {
        "conv1": {
            "w": glorot(k1, (3, 2, 1, filters), 6, 6 * filters),
            "b": jnp.zeros((filters,), dtype),
        },
        "conv2": {
            "w": glorot(k2, (3, filters, filters), 3 * filters, 3 * filters),
            "b": jnp.zeros((filters,), dtype),
        },
        "dense": {
            "w": glorot(k3, (length * filters, 1), length * filters, 1),
            "b": jnp.zeros((1,), dtype),
        },
    }


def apply_control_cnn(params: dict[str, dict[str, jax.Array]], image: jax.Array) -> jax.Array:
    """image: (N, 2) real array -> scalar control."""
    x = jax.lax.conv_general_dilated(
        image[None, :, :, None],
        params["conv1"]["w"],
        (2, 1),
        "VALID",
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
    )
    x = jnp.tanh(x[0, :, 0, :] + params["conv1"]["b"])  # (L1, filters)
    x = jax.lax.conv_general_dilated(
        x[None], params["conv2"]["w"], (2,), "VALID", dimension_numbers=("NWC", "WIO", "NWC")
    )
    x = jnp.tanh(x[0] + params["conv2"]["b"])  # (L2, filters)
    return (x.reshape(-1) @ params["dense"]["w"] + params["dense"]["b"])[0]


def init_resnet(
    key: jax.Array, channels: int, blocks: int, dtype: DTypeLike, zero_output: bool = False
) -> Params:
    """The unrolling study's 1-D convolutional ResNet: conv(2 -> C), `blocks` residual blocks of two
    convolutions (x <- leaky(conv(leaky(conv(x))) + x)), conv(C -> 1); kernel 3, circular padding,
    biases everywhere. PyTorch's default initialisation: weights and biases ~ U(-1/sqrt(3 C_in),
    1/sqrt(3 C_in)); zero_output sets the last convolution to 0 (the network starts with an output
    of exactly 0). 15,841 parameters at C = 16, 10 blocks. Layout: {"input", "blocks": {"first",
    "second"} (each leaf stacked over the blocks), "output"}, kernels (3, C_in, C_out)."""
    layers = {
        "input": ((), 2, channels),
        "first": ((blocks,), channels, channels),
        "second": ((blocks,), channels, channels),
        "output": ((), channels, 1),
    }
    shapes = [
        shape
        for leading, c_in, c_out in layers.values()
        for shape in ((*leading, 3, c_in, c_out), (*leading, c_out))
    ]
    # one random draw for the whole network, cut up on the host: a draw per layer would compile once
    # per shape
    draws = np.asarray(
        jax.random.uniform(key, (sum(math.prod(shape) for shape in shapes),), dtype, -1.0, 1.0)
    )
    offsets = np.cumsum([0] + [math.prod(shape) for shape in shapes])
    pieces = iter(draws[a:b].reshape(shape) for a, b, shape in zip(offsets, offsets[1:], shapes))
    built = {}
    for name, (_, c_in, _) in layers.items():
        bound = 0.0 if (zero_output and name == "output") else 1.0 / math.sqrt(3 * c_in)
        built[name] = {
            "w": jnp.asarray(next(pieces) * bound, dtype),
            "b": jnp.asarray(next(pieces) * bound, dtype),
        }
    return {
        "input": built["input"],
        "blocks": {"first": built["first"], "second": built["second"]},
        "output": built["output"],
    }


def circular_conv(x: jax.Array, layer: dict[str, jax.Array]) -> jax.Array:
    """out[i] = sum_k x[i + k - 1] w[k] + b on a periodic grid; x: (points, C_in) -> (points,
    C_out)."""
    taps = jnp.concatenate([jnp.roll(x, 1, axis=0), x, jnp.roll(x, -1, axis=0)], axis=1)
    return taps @ layer["w"].reshape(-1, layer["w"].shape[-1]) + layer["b"]


def leaky(z: jax.Array) -> jax.Array:
    """leaky_relu with slope 0.01 below 0 (PyTorch's default)."""
    return jax.nn.leaky_relu(z, 0.01)


def apply_resnet(params: Params, u: jax.Array, size: jax.Array | float) -> jax.Array:
    """f(u, size): (points,) -> (points,), the size factor as a constant second input channel."""
    x = circular_conv(jnp.stack([u, jnp.full_like(u, size)], axis=1), params["input"])

    first, second = params["blocks"]["first"], params["blocks"]["second"]
    for index in range(
        first["b"].shape[0]
    ):  # unrolled in Python rather than a scan over the blocks
        layer = jax.tree_util.tree_map(lambda leaf, index=index: leaf[index], (first, second))
        x = leaky(circular_conv(leaky(circular_conv(x, layer[0])), layer[1]) + x)
    return circular_conv(x, params["output"])[:, 0]
