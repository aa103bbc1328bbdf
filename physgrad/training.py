"""The compiled training step: one update of every seed trained together, over flat parameter
vectors.

What differs between the seeds of one process (networks, minibatch keys, data) is stacked on a
leading axis (`Seeds`, `stack`) and the step and the evaluation are vectorised over it
(`over_seeds`); `compile_training` compiles both ahead of time, for the training loop
(physgrad.runner) and for `make bench`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from physgrad.optim import UpdateRule, on_tree, set_member_values, state_logs
from physgrad.optim.spectral import SEEDS_AXIS
from physgrad.tasks import Scene


def make_step(scene: Scene, rule: UpdateRule, batch_size: int) -> Callable[..., tuple]:
    """(params, opt_state, iteration, train_key, train_set) -> (params, opt_state, logs); the
    minibatch is drawn inside from fold_in(train_key, iteration) (out of train_set, if the scene has
    a fixed one), so every variant with the same seed and batch size sees the same batches. The
    rule's gradient pass gives the loss, the gradient, the rule's extra arguments and the pass's
    logs (physgrad.gradients); the rule's state may add logs of its own
    (physgrad.optim.state_logs)."""

    def step(
        params: Any, opt_state: Any, iteration: jax.Array, train_key: jax.Array, train_set: Any
    ) -> tuple[Any, Any, dict]:
        batch = scene.draw_batch(jax.random.fold_in(train_key, iteration), batch_size, train_set)
        loss, grads, extra, pass_logs = rule.gradient(scene, params, batch)
        updates, opt_state = rule.transform.update(grads, opt_state, params, **extra)
        logs = {
            "loss": loss,
            "grad_norm": optax.tree.norm(grads),
            "update_norm": optax.tree.norm(updates),
            **pass_logs,
            **state_logs(opt_state),
        }
        return optax.apply_updates(params, updates), opt_state, logs

    return step


def packed_logs(step: Callable[..., tuple], names: list[str]) -> Callable[..., tuple]:
    """The step with its logged scalars stacked into one vector (one device-to-host transfer per
    iteration instead of one per scalar); their names are stored into `names` when the step is
    traced."""

    def packed(*args: Any) -> tuple[Any, Any, jax.Array]:
        params, opt_state, logs = step(*args)
        names[:] = sorted(logs)
        dtype = logs["loss"].dtype
        return params, opt_state, jnp.stack([jnp.asarray(logs[name], dtype) for name in names])

    return packed


@dataclass(frozen=True)
class Seeds:
    """What differs between the seeds trained together in one process, stacked on a leading axis:
    initial
    networks, minibatch keys, fixed training sets (None if drawn fresh), test sets and validation
    sets (None when the run does not evaluate on validation data: trainer.validation=false)."""

    params: Any
    train_keys: jax.Array
    train_sets: Any
    test_sets: Any
    validation_sets: Any = None

    @property
    def count(self) -> int:
        return self.train_keys.shape[0]

    def network(self, index: int = 0) -> Any:
        """The initial network (parameter pytree) of one seed."""
        return jax.tree_util.tree_map(lambda leaf: leaf[index], self.params)


def stack(trees: list) -> Any:
    """Stack pytrees along a new leading axis (None stays None)."""
    if trees[0] is None:
        return None
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *trees)


def over_seeds(fn: Callable[..., Any], count: int, in_axes: tuple) -> Callable[..., Any]:
    """fn vectorised over the leading seed axis of the arguments marked 0 (jax.vmap); with one seed,
    the same function on that seed's slice, without vmap, so a single run compiles exactly its own
    computation."""
    if count > 1:  # the axis named, so that a rule can act on all seeds at once (any_seed)
        return jax.vmap(fn, in_axes=in_axes, axis_name=SEEDS_AXIS)

    def single(*args: Any) -> Any:
        args = [
            jax.tree_util.tree_map(lambda x: x[0], a) if axis == 0 else a
            for a, axis in zip(args, in_axes)
        ]
        return jax.tree_util.tree_map(lambda x: x[None], fn(*args))

    return single


def ready(step: Callable[..., Any]) -> Callable[..., Any]:
    """step, returning once its results are computed (what StopRequest.call runs in its helper
    thread)."""
    return lambda *args: jax.block_until_ready(step(*args))


@dataclass(frozen=True)
class CompiledTraining:
    """The compiled step and evaluation of a training run over flat parameter vectors (one row per
    seed), with the initial parameters and optimiser state they take and the names of the logged
    scalars."""

    step: Any
    evaluate: Any
    params: jax.Array
    opt_state: Any
    log_names: list
    # the held-out loss compiled for the validation sets (the loss only, no metrics)
    validate: Any = None
    # the step as lowered before compiling: its text is the program (a compiled step read from
    # JAX's compilation cache prints otherwise than one compiled anew)
    lowered_step: Any = None


def compile_training(
    scene: Scene, rule: UpdateRule, seeds: Seeds, batch_size: int
) -> CompiledTraining:
    """Flatten each seed's network into one vector (Scene.over_flat_params), then compile the
    vectorised step (params, opt_state, iteration, train_keys, train_sets) -> (params, opt_state,
    logs[seed, name]) and the evaluation (params, test_sets) -> {name: [seed]}, ahead of time (what
    `make bench` times, too)."""
    unravel = ravel_pytree(seeds.network())[1]
    flat_scene = scene.over_flat_params(unravel)
    params = jax.vmap(lambda tree: ravel_pytree(tree)[0])(seeds.params)
    if rule.on_layers:  # a rule that is not element-wise sees the network's layers (optim.on_tree)
        rule = rule._replace(transform=on_tree(rule.transform, unravel))
    count = seeds.count
    opt_state = over_seeds(rule.transform.init, count, (0,))(params)
    if rule.member_values:  # trials trained together: each member's own learning rate, ...
        opt_state = set_member_values(opt_state, rule.member_values)
    log_names: list[str] = []
    one_step = packed_logs(make_step(flat_scene, rule, batch_size), log_names)
    lowered_step = jax.jit(over_seeds(one_step, count, (0, 0, None, 0, 0))).lower(
        params, opt_state, np.int32(0), seeds.train_keys, seeds.train_sets
    )
    step = lowered_step.compile()
    evaluating = jax.jit(over_seeds(flat_scene.evaluate, count, (0, 0))).lower(
        params, seeds.test_sets
    )
    evaluate = evaluating.compile()
    validate = None
    if seeds.validation_sets is not None:
        same = jax.tree_util.tree_structure(seeds.validation_sets) == jax.tree_util.tree_structure(
            seeds.test_sets
        ) and all(
            a.shape == b.shape and a.dtype == b.dtype
            for a, b in zip(
                jax.tree_util.tree_leaves(seeds.validation_sets),
                jax.tree_util.tree_leaves(seeds.test_sets),
            )
        )
        if same and set(evaluating.out_info) == {"loss"}:  # no metrics: the test evaluation is it
            validate = evaluate
        # validation reads the loss only: its metrics (a KS stability rollout: 200 steps) are not
        # paid
        else:
            validate = (
                jax.jit(over_seeds(flat_scene.held_out_loss, count, (0, 0)))
                .lower(params, seeds.validation_sets)
                .compile()
            )
    return CompiledTraining(step, evaluate, params, opt_state, log_names, validate, lowered_step)
