"""Dense networks as plain pytrees: a list of {"w": (in, out), "b": (out,)} layers."""

from collections.abc import Sequence
from contextlib import contextmanager

import jax
import jax.numpy as jnp

ACTIVATIONS = {"tanh": jnp.tanh, "relu": jax.nn.relu, "linear": lambda z: z}

# Active layer taps, innermost last: while tracing under one, apply_mlp computes each layer's pre-activation as
# tap(layer, x) instead of x W + b (physgrad.jacobians records inputs and cotangents this way).
_TAPS: list = []


@contextmanager
def layer_tap(tap):
    """Route every apply_mlp layer traced inside the block through tap(layer, x) -> pre-activation."""
    _TAPS.append(tap)
    try:
        yield tap
    finally:
        _TAPS.pop()


def init_mlp(key, sizes: Sequence[int], dtype, zero_last: bool = False):
    """Glorot-uniform kernels and zero biases (the Keras defaults the reference code trains with).

    A kernel of shape (fan_in, fan_out) is drawn from U(-a, a) with a = sqrt(6 / (fan_in + fan_out)).
    zero_last zero-initialises the output layer, so the network starts with an output of exactly 0.
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


def apply_mlp(layers, x, hidden: str, output: str = "linear"):
    """z_{l+1} = act(z_l W_l + b_l) with act = hidden on every layer but the last, output on the last.

    Networks built with it get the layer-factorised Jacobian of the Gauss-Newton and HIG steps
    (physgrad.jacobians) when applied once per sample."""
    tap = _TAPS[-1] if _TAPS else None
    for index, layer in enumerate(layers):
        pre_activation = x @ layer["w"] + layer["b"] if tap is None else tap(layer, x)
        x = ACTIVATIONS[output if index == len(layers) - 1 else hidden](pre_activation)
    return x


def count_params(tree) -> int:
    return sum(leaf.size for leaf in jax.tree_util.tree_leaves(tree))


def init_control_cnn(key, points: int, dtype, filters: int = 60):
    """The StableBPTT paper's quantum controller: psi as an (N, 2) image of (Re, Im) ->
    conv2d 60 filters k=(3, 2) stride 2 tanh -> conv1d 60 k=3 stride 2 tanh -> dense 1 (valid padding).
    11,701 parameters at N = 32. Glorot-uniform kernels with Keras' fans (kernel size times channels)."""
    k1, k2, k3 = jax.random.split(key, 3)
    length = ((points - 3) // 2 + 1 - 3) // 2 + 1

    def glorot(k, shape, fan_in, fan_out):
        limit = (6.0 / (fan_in + fan_out)) ** 0.5
        return jax.random.uniform(k, shape, dtype, -limit, limit)

    return {
        "conv1": {"w": glorot(k1, (3, 2, 1, filters), 6, 6 * filters), "b": jnp.zeros((filters,), dtype)},
        "conv2": {"w": glorot(k2, (3, filters, filters), 3 * filters, 3 * filters), "b": jnp.zeros((filters,), dtype)},
        "dense": {"w": glorot(k3, (length * filters, 1), length * filters, 1), "b": jnp.zeros((1,), dtype)},
    }


def apply_control_cnn(params, image):
    """image: (N, 2) real array -> scalar control."""
    x = jax.lax.conv_general_dilated(image[None, :, :, None], params["conv1"]["w"], (2, 1), "VALID",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    x = jnp.tanh(x[0, :, 0, :] + params["conv1"]["b"])  # (L1, filters)
    x = jax.lax.conv_general_dilated(x[None], params["conv2"]["w"], (2,), "VALID",
                                     dimension_numbers=("NWC", "WIO", "NWC"))
    x = jnp.tanh(x[0] + params["conv2"]["b"])  # (L2, filters)
    return (x.reshape(-1) @ params["dense"]["w"] + params["dense"]["b"])[0]
