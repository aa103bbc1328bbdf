"""Dense networks as plain pytrees: a list of {"w": (in, out), "b": (out,)} layers."""

from collections.abc import Sequence

import jax
import jax.numpy as jnp

ACTIVATIONS = {"tanh": jnp.tanh, "relu": jax.nn.relu, "linear": lambda z: z}


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
    """z_{l+1} = act(z_l W_l + b_l) with act = hidden on every layer but the last, output on the last."""
    for layer in layers[:-1]:
        x = ACTIVATIONS[hidden](x @ layer["w"] + layer["b"])
    last = layers[-1]
    return ACTIVATIONS[output](x @ last["w"] + last["b"])


def count_params(tree) -> int:
    return sum(leaf.size for leaf in jax.tree_util.tree_leaves(tree))
