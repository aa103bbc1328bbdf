"""Scenes: one module per physical setup behind the small `Scene` interface.

A task config names the function that builds its scene with ``_target_`` (built-in or a user's own,
e.g. ``_target_: mylab.pendulum.build``). physgrad calls it with the config's other keys as keyword
arguments plus ``key``, a PRNG key that seeds the scene's data (and nothing else). ``name`` and
``batch_size`` are read by physgrad itself; a temporal scene has an ``unroll`` key (its number of
time steps), which the top-level ``unroll=N`` replaces. docs/extending.md describes the interface
for authors of new scenes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.errors import UserError
from physgrad.unroll import REGULAR, Backprop, Dynamics
from physgrad.validate import call_target

if TYPE_CHECKING:
    from physgrad.nets import Params, Pytree

# task keys that physgrad reads itself and does not pass to the scene's build function
RESERVED_KEYS = ("name", "batch_size")


def draw_from(key: jax.Array, batch_size: int, train_set: Pytree) -> Pytree:
    """draw_batch for a fixed training set: batch_size samples drawn without replacement,
    independently at every iteration (from that iteration's key).

    The subset is the top batch_size of one uniform draw per sample (every subset equally likely),
    which costs far less than the full shuffle of jax.random.choice(replace=False)
    (docs/decisions.md)."""
    size = jax.tree_util.tree_leaves(train_set)[0].shape[0]
    index = jax.lax.top_k(jax.random.uniform(key, (size,)), batch_size)[1]
    return jax.tree_util.tree_map(lambda leaf: leaf[index], train_set)


def no_metrics(params: Params, sample: Pytree, y: jax.Array) -> dict:
    return {}


@dataclass(frozen=True)
class Scene:
    """A network-through-physics problem.

    init_params(key) -> params: the network's initial parameters (a pytree);
    sample_loss(y, sample) -> scalar: the per-sample loss L_i(y); the batch loss is their MEAN;
    test_set: the held-out samples (a pytree with a leading sample axis);
    sample_output(params, sample) -> y: the physical output of one sample (a flat vector of k
    components), for a scene without time; a temporal scene gives ``dynamics`` instead and
    sample_output follows from it; dynamics: the rollout of a temporal scene
    (physgrad.unroll.Dynamics); train_set: a fixed training set (None when every batch is drawn
    fresh by draw_batch); draw_batch(key, batch_size, train_set) -> batch: a training minibatch; by
    default drawn from train_set; sample_metrics(params, sample, y) -> {name: scalar}: extra
    held-out metrics, averaged over the test set; figure(params, test_set, path): a per-run figure
    of the trained network (e.g. trajectories of a few test samples), drawn after training into path
    (scene.png beside loss.png); optional; test_output(params, sample) -> y: the output the held-out
    loss is computed on, where it differs from the training output (e.g. a fixed rollout horizon
    whatever the training unroll); default: sample_output; validation_set: held-out samples for
    tuning and early decisions (same structure as test_set); default (None): the test set of the
    same scene built from another data key (physgrad.experiment.validation_set).
    """

    init_params: Callable[[Any], Any]
    sample_loss: Callable[[jax.Array, Any], jax.Array]
    test_set: Any
    sample_output: Callable[[Any, Any], jax.Array] | None = None
    dynamics: Dynamics | None = None
    train_set: Any = None
    draw_batch: Callable[[Any, int, Any], Any] = draw_from
    sample_metrics: Callable[[Any, Any, jax.Array], dict] = field(default=no_metrics)
    figure: Callable[[Any, Any, Any], None] | None = None
    test_output: Callable[[Any, Any], jax.Array] | None = None
    validation_set: Any = None

    def __post_init__(self) -> None:
        if (self.sample_output is None) == (self.dynamics is None):
            raise UserError(
                "a Scene takes sample_output (a scene without time) or dynamics (a temporal "
                "scene), exactly one of them"
            )
        if self.train_set is None and self.draw_batch is draw_from:
            raise UserError(
                "a Scene without a train_set needs draw_batch (a fresh batch every iteration)"
            )
        if self.dynamics is not None:
            object.__setattr__(self, "sample_output", self.dynamics.output(REGULAR))

    @property
    def time_axis(self) -> bool:
        return self.dynamics is not None

    @property
    def closed_loop(self) -> bool:
        """The network acts inside the rollout on the state it sees (the BPTT modes M, S and C
        apply)."""
        return self.dynamics is not None and self.dynamics.closed_loop

    @property
    def unroll(self) -> int | None:
        return None if self.dynamics is None else self.dynamics.unroll

    @property
    def train_size(self) -> int | None:
        return (
            None
            if self.train_set is None
            else jax.tree_util.tree_leaves(self.train_set)[0].shape[0]
        )

    def backprop_output(self, backprop: Backprop) -> Callable[[Any, Any], jax.Array]:
        """sample_output with the gradient stops of a backprop-through-time mode (temporal
        scenes)."""
        if self.dynamics is None:
            if backprop != REGULAR:
                raise ValueError("a scene without time has no backprop-through-time modes")
            return self.sample_output
        return self.dynamics.output(backprop)

    def over_flat_params(self, unravel: Callable[[jax.Array], Params]) -> "Scene":
        """This scene with the network's parameters as one flat vector (unravel: vector -> parameter
        pytree, from ravel_pytree): an optimiser then updates one array in one fused kernel instead
        of one per layer (docs/decisions.md)."""

        def flat(fn: Callable[..., Any]) -> Callable[..., Any]:
            return lambda flat_params, *args: fn(unravel(flat_params), *args)

        changes = {
            "init_params": lambda key: ravel_pytree(self.init_params(key))[0],
            "sample_metrics": flat(self.sample_metrics),
        }
        if self.test_output is not None:
            changes["test_output"] = flat(self.test_output)
        if self.dynamics is None:
            changes["sample_output"] = flat(self.sample_output)
        else:
            changes["sample_output"] = None  # follows from the new dynamics
            changes["dynamics"] = dataclasses.replace(
                self.dynamics, policy=flat(self.dynamics.policy)
            )
        return dataclasses.replace(self, **changes)

    def sample_train(self, key: jax.Array, batch_size: int) -> Pytree:
        return self.draw_batch(key, batch_size, self.train_set)

    def batch_output(self, params: Params, batch: Pytree) -> jax.Array:
        """y for a batch: shape (batch, k), sample major."""
        return jax.vmap(self.sample_output, in_axes=(None, 0))(params, batch)

    def batch_loss(self, y: jax.Array, batch: Pytree) -> jax.Array:
        """L(y) = mean_i L_i(y_i)."""
        return jnp.mean(jax.vmap(self.sample_loss)(y, batch))

    def evaluate(self, params: Params, batch: Pytree) -> dict:
        """Held-out loss and scene metrics, each a mean over the samples of ``batch`` (on
        test_output)."""
        y = self.held_out_output(params, batch)
        metrics = jax.vmap(self.sample_metrics, in_axes=(None, 0, 0))(params, batch, y)
        return {"loss": self.batch_loss(y, batch), **{k: jnp.mean(v) for k, v in metrics.items()}}

    def held_out_loss(self, params: Params, batch: Pytree) -> dict:
        """{"loss": the held-out loss of ``batch``} without the scene metrics: what validation reads
        (tuning and early choices need the loss only; a metric such as a long stability rollout can
        cost many times it)."""
        return {"loss": self.batch_loss(self.held_out_output(params, batch), batch)}

    def held_out_output(self, params: Params, batch: Pytree) -> jax.Array:
        """y for held-out samples: test_output where the scene has one, sample_output otherwise."""
        output = self.sample_output if self.test_output is None else self.test_output
        return jax.vmap(output, in_axes=(None, 0))(params, batch)


def build_scene(task_cfg: Mapping[str, Any], key: jax.Array, unroll: int | None = None) -> Scene:
    """The scene a task config names (``_target_``), seeded by ``key``; ``unroll`` replaces a
    temporal scene's number of time steps (task.unroll). UserError (one line) for a setting the
    build function does not take or refuses, and if the function does not return a Scene."""
    from omegaconf import OmegaConf

    node = (
        OmegaConf.to_container(task_cfg, resolve=True)
        if OmegaConf.is_config(task_cfg)
        else dict(task_cfg)
    )
    if unroll is not None:
        node["unroll"] = unroll
    scene = call_target("task", node, reserved=RESERVED_KEYS, key=key)
    if not isinstance(scene, Scene):
        raise UserError(
            f"task._target_={node.get('_target_')} returned {type(scene).__name__}, not a "
            "physgrad.tasks.Scene"
        )
    return scene
