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

import jax
import numpy as np
import optax
from tqdm import tqdm

from physgrad.optim import UpdateRule
from physgrad.results import ResultsWriter
from physgrad.tasks import Scene


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


def make_step(scene: Scene, rule: UpdateRule, batch_size: int, train_key):
    """(params, opt_state, iteration) -> (params, opt_state, logs); the minibatch is drawn inside from
    fold_in(train_key, iteration), so every variant with the same seed and batch size sees the same batches.

    The gradient is the pullback of g = dL/dy through y = batch_output(params): one forward, one backward.
    Rules on the Jacobian route receive the per-sample output function, the batch and g as extra arguments.
    """

    def step(params, opt_state, iteration):
        batch = scene.sample_train(jax.random.fold_in(train_key, iteration), batch_size)
        y, pullback = jax.vjp(lambda p: scene.batch_output(p, batch), params)
        loss, output_grad = jax.value_and_grad(scene.batch_loss)(y, batch)
        (grads,) = pullback(output_grad)
        extra = {"sample_output": scene.sample_output, "batch": batch, "output_grad": output_grad}
        updates, opt_state = rule.transform.update(grads, opt_state, params, **(extra if rule.uses_jacobian else {}))
        logs = {"loss": loss, "grad_norm": optax.tree.norm(grads), "update_norm": optax.tree.norm(updates)}
        return optax.apply_updates(params, updates), opt_state, logs

    return step


@contextmanager
def sigterm_as_interrupt():
    """SIGTERM (a scheduler's pre-emption, `kill`) ends the run like Ctrl-C: status interrupted, rows kept."""

    def handler(signum, frame):
        raise KeyboardInterrupt("SIGTERM")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def train(scene: Scene, rule: UpdateRule, params, settings: TrainerSettings, writer: ResultsWriter, train_key,
          label: str = "") -> Outcome:
    """Compile, then iterate from params until trainer.iterations or trainer.time_budget (training seconds),
    whichever comes first. A non-finite loss, gradient norm or update norm ends the run with status diverged."""
    opt_state = rule.transform.init(params)

    start = time.perf_counter()
    step = jax.jit(make_step(scene, rule, settings.batch_size, train_key)).lower(
        params, opt_state, np.int32(0)).compile()
    evaluate = jax.jit(scene.evaluate).lower(params, scene.test_set).compile()
    writer.set_attrs(compile_seconds=time.perf_counter() - start)

    train_seconds, done = 0.0, 0
    status, reason = "completed", None
    latest_eval = {}

    def record_eval(iteration):
        metrics = {k: float(v) for k, v in jax.device_get(evaluate(params, scene.test_set)).items()}
        writer.append("eval", {"iteration": iteration, "wall_time": train_seconds, **metrics})
        writer.flush()
        latest_eval.clear()
        latest_eval.update(metrics, iteration=iteration)

    bar = tqdm(total=settings.iterations, desc=label, mininterval=0.5, disable=None, leave=False)
    try:
        with sigterm_as_interrupt():
            record_eval(0)
            last_flush = time.perf_counter()
            for iteration in range(settings.iterations):
                tick = time.perf_counter()
                new_params, opt_state, logs = step(params, opt_state, np.int32(iteration))
                logs = jax.device_get(logs)
                jax.block_until_ready(new_params)
                train_seconds += time.perf_counter() - tick
                params, done = new_params, iteration + 1
                writer.append("train", {"iteration": iteration, "wall_time": train_seconds,
                                        **{k: float(v) for k, v in logs.items()}})
                bad = next((k for k in ("loss", "grad_norm", "update_norm") if not math.isfinite(logs[k])), None)
                if bad is not None:
                    status = "diverged"
                    reason = f"{bad} became {float(logs[bad])} at iteration {iteration}"
                    break
                if done % settings.eval_every == 0 and done < settings.iterations:
                    record_eval(done)
                if settings.time_budget is not None and train_seconds >= settings.time_budget:
                    writer.set_attrs(stopped_by="time_budget")
                    break
                now = time.perf_counter()
                if now - last_flush >= settings.flush_seconds:
                    writer.flush()
                    last_flush = now
                    bar.set_postfix(loss=f"{float(logs['loss']):.3e}", refresh=False)
                bar.update(done - bar.n)
            else:
                writer.set_attrs(stopped_by="iterations")
            if status == "completed" and latest_eval["iteration"] != done:
                record_eval(done)
    except KeyboardInterrupt as interrupt:
        status = "interrupted"
        reason = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} after {done} iterations"
    except BaseException as error:
        writer.finish("failed", f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}",
                      iterations=done, train_seconds=train_seconds)
        raise
    finally:
        bar.close()
    writer.finish(status, reason, iterations=done, train_seconds=train_seconds)
    return Outcome(status, reason, done, train_seconds, dict(latest_eval))
