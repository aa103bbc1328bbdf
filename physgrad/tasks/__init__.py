"""Scenes: one module per physical setup behind the small `Scene` interface.

A scene module provides
- ``traits(task_cfg) -> Traits``: cheap, static facts the runner uses to refuse combinations that do not apply;
- ``build(task_cfg, key, unroll=None) -> Scene``: data, network and differentiable physics, all seeded from
  ``key``; ``unroll`` (temporal scenes only) replaces the scene's reference number of time steps.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad import UserError

TASK_MODULES = {
    "oscillator": "physgrad.tasks.oscillator",
    "multicart": "physgrad.tasks.multicart",
    "poisson": "physgrad.tasks.poisson",
    "quantum": "physgrad.tasks.quantum",
    "quantum_control": "physgrad.tasks.quantum",  # the StableBPTT preset of the same scene
    "toy": "physgrad.tasks.toy",
}


@dataclass(frozen=True)
class Traits:
    """time_axis: the physics is rolled out in time (an unroll length applies).
    controller: "open" (network -> whole control sequence), "closed" (network inside the loop) or None."""

    time_axis: bool
    controller: str | None = None


@dataclass(frozen=True)
class Scene:
    """A network-through-physics problem.

    sample_output(params, sample) -> y: the physical output of one sample (a flat vector of k components);
    sample_loss(y, sample) -> scalar: the per-sample loss L_i(y); the batch loss is their MEAN;
    sample_metrics(params, sample, y) -> {name: scalar}: extra held-out metrics (y = sample_output), averaged
    over the test set;
    draw_batch(key, batch_size, train_set) -> batch: a training minibatch (pytree with a leading batch axis),
    from the fixed train_set or drawn fresh (train_set None); sample_train(key, batch_size) draws from the
    scene's own train_set. The set is an argument so that runs over several seeds can stack it;
    backprop_output(Backprop) -> sample_output with the gradient stops of that BPTT mode (temporal scenes);
    steps: the number of time steps of a temporal scene (None without a time axis);
    train_set: the fixed training set (None when every batch is drawn fresh).
    """

    name: str
    traits: Traits
    init_params: Callable[[Any], Any]
    draw_batch: Callable[[Any, int, Any], Any]
    test_set: Any
    sample_output: Callable[[Any, Any], jax.Array]
    sample_loss: Callable[[jax.Array, Any], jax.Array]
    sample_metrics: Callable[[Any, Any, jax.Array], dict] = field(default=lambda params, sample, y: {})
    backprop_output: Callable[[Any], Callable] | None = None
    steps: int | None = None
    train_set: Any = None

    @property
    def train_size(self) -> int | None:
        return None if self.train_set is None else jax.tree_util.tree_leaves(self.train_set)[0].shape[0]

    def over_flat_params(self, unravel) -> "Scene":
        """This scene with the network's parameters as one flat vector (unravel: vector -> parameter pytree,
        from ravel_pytree): an optimiser then updates one array in one fused kernel instead of one per layer
        (Adam on the Poisson network: 0.11 ms against 0.21 ms per update on the CI machine)."""

        def flat(fn):
            return lambda flat_params, *args: fn(unravel(flat_params), *args)

        return dataclasses.replace(
            self, init_params=lambda key: ravel_pytree(self.init_params(key))[0],
            sample_output=flat(self.sample_output), sample_metrics=flat(self.sample_metrics),
            backprop_output=None if self.backprop_output is None else lambda mode: flat(self.backprop_output(mode)))

    def sample_train(self, key, batch_size: int):
        return self.draw_batch(key, batch_size, self.train_set)

    def batch_output(self, params, batch) -> jax.Array:
        """y for a batch: shape (batch, k), sample major."""
        return jax.vmap(self.sample_output, in_axes=(None, 0))(params, batch)

    def batch_loss(self, y, batch) -> jax.Array:
        """L(y) = mean_i L_i(y_i)."""
        return jnp.mean(jax.vmap(self.sample_loss)(y, batch))

    def evaluate(self, params, batch) -> dict:
        """Held-out loss and scene metrics, each a mean over the samples of ``batch``."""
        y = self.batch_output(params, batch)
        metrics = jax.vmap(self.sample_metrics, in_axes=(None, 0, 0))(params, batch, y)
        return {"loss": self.batch_loss(y, batch), **{k: jnp.mean(v) for k, v in metrics.items()}}


def draw_from(key, batch_size: int, train_set):
    """draw_batch for a fixed training set: batch_size samples drawn without replacement, independently at
    every iteration (from that iteration's key).

    The subset is the top batch_size of one uniform draw per sample (every subset equally likely): 0.17 ms for
    512 of 4096 on the CI machine, where jax.random.choice(replace=False) shuffles all of them (1.9 ms, as much
    as the oscillator's whole loss and gradient)."""
    size = jax.tree_util.tree_leaves(train_set)[0].shape[0]
    index = jax.lax.top_k(jax.random.uniform(key, (size,)), batch_size)[1]
    return jax.tree_util.tree_map(lambda leaf: leaf[index], train_set)


def task_module(name: str):
    if name not in TASK_MODULES:
        raise UserError(f"unknown task '{name}': choose one of {', '.join(sorted(TASK_MODULES))}")
    return importlib.import_module(TASK_MODULES[name])


def traits(task_cfg) -> Traits:
    return task_module(task_cfg.name).traits(task_cfg)


def build_scene(task_cfg, key, unroll: int | None = None) -> Scene:
    return task_module(task_cfg.name).build(task_cfg, key, unroll)
