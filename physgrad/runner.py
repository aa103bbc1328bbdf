"""The training loop: one compiled step, training-only timing, NaN/Inf guard, buffered HDF5 rows.

Timing contract: ``wall_time`` is the cumulative time of finished training steps (each step is timed from
dispatch until its outputs are ready). Compilation happens before the loop (``compile_seconds``);
evaluations, HDF5 flushes and the progress bar fall outside the timed intervals.
"""

from __future__ import annotations

import math
import signal
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from tqdm import tqdm

from physgrad.optim import UpdateRule
from physgrad.optim.spectral import output_and_jacobian
from physgrad.results import ResultsWriter
from physgrad.tasks import Scene
from physgrad.unroll import MODES, PHYSICS_ONLY, combine_signs


@dataclass(frozen=True)
class TrainerSettings:
    iterations: int
    time_budget: float | None
    eval_every: int
    batch_size: int
    flush_seconds: float


@dataclass(frozen=True)
class Outcome:
    status: str
    reason: str | None
    iterations: int
    train_seconds: float
    final_eval: dict


def make_step(scene: Scene, rule: UpdateRule, batch_size: int):
    """(params, opt_state, iteration, train_key, train_set) -> (params, opt_state, logs); the minibatch is drawn
    inside from fold_in(train_key, iteration) (out of train_set, if the scene has a fixed one), so every variant
    with the same seed and batch size sees the same batches.

    The gradient is the pullback of g = dL/dy through y = batch output: one forward, one backward. The BPTT
    modes M and S take it through the scene's output with those gradient stops; C takes R and M and keeps
    g_M where the signs agree (and logs cos(g_M, g_R) and the fraction of components it zeroes).
    Rules on the Jacobian route take y and J = dy/dtheta from one per-sample reverse pass instead; their
    gradient (logged as grad_norm) is J^T g, and they receive J and g as extra arguments.
    """

    def value_and_grads(params, batch, sample_output):
        y, pullback = jax.vjp(lambda p: jax.vmap(sample_output, in_axes=(None, 0))(p, batch), params)
        loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
        return loss, output_grad, pullback(output_grad)[0], jnp.max(jnp.abs(y))

    def step(params, opt_state, iteration, train_key, train_set):
        batch = scene.draw_batch(jax.random.fold_in(train_key, iteration), batch_size, train_set)
        logs, extra = {}, {}
        if rule.uses_jacobian:
            y, jac = output_and_jacobian(scene.sample_output, params, batch)
            loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
            grads = ravel_pytree(params)[1](jac.T @ output_grad.reshape(-1).astype(jac.dtype))
            state_max = jnp.max(jnp.abs(y))
            extra = {"jacobian": jac, "output_grad": output_grad}
        elif rule.backprop == "C":
            loss, output_grad, g_regular, state_max = value_and_grads(params, batch, scene.sample_output)
            _, _, g_physics, _ = value_and_grads(params, batch, scene.backprop_output(PHYSICS_ONLY))
            grads = combine_signs(g_physics, g_regular)
            logs["cos_physics_regular"] = tree_cosine(g_physics, g_regular)
            logs["zeroed_fraction"] = sign_disagreement(g_physics, g_regular)
        else:
            output = scene.sample_output if rule.backprop in (None, "R") else scene.backprop_output(
                MODES[rule.backprop])
            loss, output_grad, grads, state_max = value_and_grads(params, batch, output)
        updates, opt_state = rule.transform.update(grads, opt_state, params, **extra)
        if rule.uses_jacobian:
            logs["svd_failures"] = optax.tree.get(opt_state, "failures")
        logs = {"loss": loss, "grad_norm": optax.tree.norm(grads), "update_norm": optax.tree.norm(updates),
                "state_max_abs": state_max, **logs}
        return optax.apply_updates(params, updates), opt_state, logs

    return step


# checked for NaN/Inf after every step, in causal order: the physical output (the simulated state: a blow-up
# of the physics shows here first), the loss, the gradient, the update; the first non-finite one is the reason
GUARDED = ("state_max_abs", "loss", "grad_norm", "update_norm")
QUANTITY = {"state_max_abs": "state", "loss": "loss", "grad_norm": "gradient", "update_norm": "update"}


def divergence_reason(quantity: str, logs: dict, iteration: int, svd_failures_before: float) -> str:
    """One line: which quantity went non-finite first, its value, the iteration, and a failed factorisation if
    that is what happened at this step."""
    reason = f"{QUANTITY[quantity]} became {logs[quantity]} at iteration {iteration} ({quantity})"
    if logs.get("svd_failures", 0.0) > svd_failures_before:
        reason += ("; the SVD/eigh of the Jacobian did not converge (optim.retry_float64=true retries it in "
                   "float64, precision=64 runs everything in float64)")
    return reason


def packed_logs(step, names: list[str]):
    """The step with its logged scalars stacked into one vector (one device-to-host transfer per iteration
    instead of one per scalar); their names are stored into `names` when the step is traced."""

    def packed(*args):
        params, opt_state, logs = step(*args)
        names[:] = sorted(logs)
        dtype = logs["loss"].dtype
        return params, opt_state, jnp.stack([jnp.asarray(logs[name], dtype) for name in names])

    return packed


def tree_cosine(a, b) -> jax.Array:
    """<a, b> / (|a| |b|) over whole pytrees; 0 where either is the zero vector (the angle is undefined)."""
    dot = sum(jnp.vdot(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    norms = optax.tree.norm(a) * optax.tree.norm(b)
    return jnp.where(norms > 0, dot / jnp.where(norms > 0, norms, 1.0), 0.0)


def sign_disagreement(a, b) -> jax.Array:
    """Fraction of components where sign(a) != sign(b): the ones the combined gradient sets to zero."""
    leaves = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    differ = sum(jnp.sum(jnp.sign(x) != jnp.sign(y)) for x, y in leaves)
    return differ / sum(x.size for x in jax.tree_util.tree_leaves(a))


class StopRequest:
    """Signal handler for SIGINT and SIGTERM: the first signal asks the loop to stop after the current step
    (checked between steps, so no write is ever cut in half and no library frame swallows the interrupt);
    a second one stops at once."""

    def __init__(self):
        self.signal_name: str | None = None

    def __call__(self, signum, frame):
        name = signal.Signals(signum).name
        if self.signal_name is not None:
            raise KeyboardInterrupt(name)
        self.signal_name = name


@contextmanager
def stop_on_signals():
    request = StopRequest()
    try:
        previous = {sig: signal.signal(sig, request) for sig in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: leave signals alone
        yield request
        return
    try:
        yield request
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@dataclass(frozen=True)
class Seeds:
    """What differs between the seeds trained together in one process, stacked on a leading axis: initial
    networks, minibatch keys, fixed training sets (None if drawn fresh) and test sets."""

    params: Any
    train_keys: jax.Array
    train_sets: Any
    test_sets: Any

    @property
    def count(self) -> int:
        return self.train_keys.shape[0]

    def network(self, index: int = 0):
        """The initial network (parameter pytree) of one seed."""
        return jax.tree_util.tree_map(lambda leaf: leaf[index], self.params)


def stack(trees: list):
    """Stack pytrees along a new leading axis (None stays None)."""
    if trees[0] is None:
        return None
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *trees)


def over_seeds(fn, count: int, in_axes: tuple):
    """fn vectorised over the leading seed axis of the arguments marked 0 (jax.vmap); with one seed, the same
    function on that seed's slice, without vmap, so a single run compiles exactly its own computation."""
    if count > 1:
        return jax.vmap(fn, in_axes=in_axes)

    def single(*args):
        args = [jax.tree_util.tree_map(lambda x: x[0], a) if axis == 0 else a for a, axis in zip(args, in_axes)]
        return jax.tree_util.tree_map(lambda x: x[None], fn(*args))

    return single


@dataclass(frozen=True)
class CompiledTraining:
    """The compiled step and evaluation of a training run over flat parameter vectors (one row per seed),
    with the initial parameters and optimiser state they take and the names of the logged scalars."""

    step: Any
    evaluate: Any
    params: jax.Array
    opt_state: Any
    log_names: list


def compile_training(scene: Scene, rule: UpdateRule, seeds: Seeds, batch_size: int) -> CompiledTraining:
    """Flatten each seed's network into one vector (Scene.over_flat_params), then compile the vectorised step
    (params, opt_state, iteration, train_keys, train_sets) -> (params, opt_state, logs[seed, name]) and the
    evaluation (params, test_sets) -> {name: [seed]}, ahead of time (what `make bench` times, too)."""
    unravel = ravel_pytree(seeds.network())[1]
    flat_scene = scene.over_flat_params(unravel)
    params = jax.vmap(lambda tree: ravel_pytree(tree)[0])(seeds.params)
    count = seeds.count
    opt_state = over_seeds(rule.transform.init, count, (0,))(params)
    log_names: list[str] = []
    one_step = packed_logs(make_step(flat_scene, rule, batch_size), log_names)
    step = jax.jit(over_seeds(one_step, count, (0, 0, None, 0, 0))).lower(
        params, opt_state, np.int32(0), seeds.train_keys, seeds.train_sets).compile()
    evaluate = jax.jit(over_seeds(flat_scene.evaluate, count, (0, 0))).lower(params, seeds.test_sets).compile()
    return CompiledTraining(step, evaluate, params, opt_state, log_names)


def train(scene: Scene, rule: UpdateRule, seeds: Seeds, writers: list[ResultsWriter], settings: TrainerSettings,
          label: str = "") -> list[Outcome]:
    """Compile, then iterate until trainer.iterations or trainer.time_budget (training seconds), whichever
    comes first, every seed in one vectorised step (writers: one per seed). A seed whose state, loss, gradient
    or update turns non-finite ends with status diverged (its rows stop there) while the others go on; the
    wall time is the shared one. Returns one Outcome per seed."""
    count = seeds.count
    train_seconds, done = 0.0, 0
    status, reason = ["completed"] * count, [None] * count
    finished_at = [None] * count  # iterations done when a seed diverged
    latest_eval = [{} for _ in range(count)]
    params = None

    def record_eval(iteration):
        # written with the next periodic flush: a flush per evaluation cost 2% of a fast scene's wall time
        metrics = {k: np.asarray(v).tolist() for k, v in jax.device_get(evaluate(params, seeds.test_sets)).items()}
        for index, writer in enumerate(writers):
            if status[index] == "completed":
                values = {k: v[index] for k, v in metrics.items()}
                writer.append("eval", {"iteration": iteration, "wall_time": train_seconds, **values})
                latest_eval[index] = {**values, "iteration": iteration}

    def flush_all():
        for writer in writers:
            writer.flush()

    bar = tqdm(total=settings.iterations, desc=label, mininterval=0.5, disable=None, leave=False)
    try:
        with stop_on_signals() as stop:
            # compiling can take minutes: inside the guard, so a failure or an interrupt here is recorded too
            start = time.perf_counter()
            compiled = compile_training(scene, rule, seeds, settings.batch_size)
            step, evaluate, log_names = compiled.step, compiled.evaluate, compiled.log_names
            params, opt_state = compiled.params, compiled.opt_state
            for writer in writers:
                writer.set_attrs(compile_seconds=time.perf_counter() - start)
                writer.set_columns("train", ("iteration", "wall_time", *log_names))
            guarded = [log_names.index(name) for name in GUARDED]
            svd_at = log_names.index("svd_failures") if "svd_failures" in log_names else None
            svd_failures = [0.0] * count
            running = list(range(count))
            record_eval(0)
            flush_all()
            last_flush = time.perf_counter()
            for iteration in range(settings.iterations):
                if stop.signal_name is not None:
                    raise KeyboardInterrupt(stop.signal_name)
                tick = time.perf_counter()
                new_params, opt_state, logs = step(params, opt_state, np.int32(iteration), seeds.train_keys,
                                                   seeds.train_sets)
                logs = np.asarray(logs).tolist()  # one transfer for every logged scalar of every seed
                jax.block_until_ready(new_params)
                train_seconds += time.perf_counter() - tick
                params, done = new_params, iteration + 1
                diverged = False
                for index in running:
                    row = logs[index]
                    writers[index].append_row("train", (iteration, train_seconds, *row))
                    bad = next((log_names[i] for i in guarded if not math.isfinite(row[i])), None)
                    if bad is not None:
                        status[index], finished_at[index], diverged = "diverged", done, True
                        reason[index] = divergence_reason(bad, dict(zip(log_names, row)), iteration,
                                                          svd_failures[index])
                    elif svd_at is not None:
                        svd_failures[index] = row[svd_at]
                if diverged:  # the running list changes only here, not at every step
                    running = [index for index in running if status[index] == "completed"]
                    if not running:
                        break
                if done % settings.eval_every == 0 and done < settings.iterations:
                    record_eval(done)
                if settings.time_budget is not None and train_seconds >= settings.time_budget:
                    for writer in writers:
                        writer.set_attrs(stopped_by="time_budget")
                    break
                now = time.perf_counter()
                if now - last_flush >= settings.flush_seconds:
                    flush_all()
                    last_flush = now
                    bar.set_postfix(loss=f"{logs[running[0]][guarded[1]]:.3e}", refresh=False)
                    bar.update(done - bar.n)
            else:
                for writer in writers:
                    writer.set_attrs(stopped_by="iterations")
            if any(s == "completed" and latest_eval[i]["iteration"] != done for i, s in enumerate(status)):
                record_eval(done)
    except KeyboardInterrupt as interrupt:
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} after {done} iterations"
        status = ["interrupted" if s == "completed" else s for s in status]
        reason = [why if s == "interrupted" else r for s, r in zip(status, reason)]
    except BaseException as error:
        message = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
        for index, writer in enumerate(writers):
            writer.finish("failed", message, iterations=finished_at[index] or done, train_seconds=train_seconds)
        raise
    finally:
        bar.close()
    outcomes = []
    for index, writer in enumerate(writers):
        flat = None if params is None else np.asarray(params[index])
        if flat is not None and status[index] != "diverged" and np.isfinite(flat).all():  # a later run can start from it (init_from)
            writer.save_params(flat)
        iterations = finished_at[index] or done
        writer.finish(status[index], reason[index], iterations=iterations, train_seconds=train_seconds)
        outcomes.append(Outcome(status[index], reason[index], iterations, train_seconds, latest_eval[index]))
    return outcomes
