"""The training loop: one compiled step, training-only timing, NaN/Inf guard, buffered HDF5 rows.

Timing contract: ``wall_time`` is the cumulative time of finished training steps (each step is timed from
dispatch until its outputs are ready). Compilation happens before the loop (``compile_seconds``), and so does
the one-off cost of the compiled step's first call (``first_step_overhead_seconds``: how much longer the first
step took than the second, 10 to 50 ms on CPU whatever the step costs, which would otherwise be 10 to 200
times a fast step); evaluations, HDF5 flushes, logging and the progress bar fall outside the timed intervals.
"""

from __future__ import annotations

import logging
import math
import signal
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from tqdm import tqdm

from physgrad.interrupts import take_lost
from physgrad.optim import UpdateRule, on_tree, state_logs
from physgrad.errors import ResultsWriteError
from physgrad.results import ResultsWriter
from physgrad.tasks import Scene
from physgrad.errors import UserError
from physgrad.machine import contention, cpu_count, load_average, step_statistics
from physgrad.validate import choice, number
from physgrad.verdict import DIVERGENCE_FACTOR

log = logging.getLogger("physgrad")
clock = time.perf_counter  # every interval of the loop is read from this clock (tests replace it)
DEFAULT_ITERATIONS = 2000  # trainer.iterations=null without a time budget
CLOCKS = ("measured", "calibrated")
EVALUATIONS_PER_BUDGET = 20  # trainer.eval_seconds=null with a time budget: an evaluation every budget / 20
SLOW_STEP_SECONDS = 0.2  # a step at least this long runs in a helper thread, so that a second signal ends it
WAKE_SECONDS = 0.05  # how often the waiting thread looks at signals
# steps left computing after a second signal: the command line ends with os._exit while one is alive, since a
# daemon thread that returns from XLA into a finalising interpreter aborts the process
ABANDONED: list[threading.Thread] = []
FLUSH_COST_FACTOR = 20  # the file is rewritten at most every 20 times what one write takes (<= 5 % of the time)


@dataclass(frozen=True)
class TrainerSettings:
    """The `trainer` config section: when to stop, evaluate, write and log. iterations is None for no limit
    (a time budget alone ends the run); eval_seconds None for evaluations by iteration only."""

    iterations: int | None
    time_budget: float | None
    eval_every: int
    eval_seconds: float | None
    batch_size: int
    flush_seconds: float
    log_seconds: float
    divergence_factor: float | None = DIVERGENCE_FACTOR
    step_cost: float | None = None  # seconds per step from a calibration (physgrad.calibration), or None
    clock: str = "measured"  # which clock the time budget and eval_seconds read: measured | calibrated

    @classmethod
    def from_config(cls, trainer_cfg) -> "TrainerSettings":
        """trainer.iterations=null means 2000 without a time budget and no limit with one; trainer.eval_seconds=
        null means time_budget / 20 with a budget (so that a slow variant still gets a curve) and none without."""
        budget = number("trainer.time_budget", trainer_cfg.get("time_budget"), 0, optional=True, open_low=True)
        iterations = number("trainer.iterations", trainer_cfg.get("iterations"), 1, integer=True, optional=True)
        eval_seconds = number("trainer.eval_seconds", trainer_cfg.get("eval_seconds"), 0, optional=True,
                              open_low=True)
        step_cost = number("trainer.step_cost", trainer_cfg.get("step_cost"), 0, optional=True, open_low=True)
        clock = choice("trainer.clock", trainer_cfg.get("clock", "measured"), CLOCKS)
        if clock == "calibrated" and step_cost is None:
            raise UserError("trainer.clock=calibrated needs trainer.step_cost (seconds per step from a calibration: "
                            "physgrad compare measures it) or trainer.clock=measured")
        return cls(
            iterations=iterations if iterations is not None or budget is not None else DEFAULT_ITERATIONS,
            time_budget=budget,
            eval_every=number("trainer.eval_every", trainer_cfg.get("eval_every"), 1, integer=True),
            eval_seconds=eval_seconds if eval_seconds is not None or budget is None
            else budget / EVALUATIONS_PER_BUDGET,
            batch_size=number("trainer.batch_size", trainer_cfg.get("batch_size"), 1, integer=True),
            flush_seconds=number("trainer.flush_seconds", trainer_cfg.get("flush_seconds"), 0, open_low=True),
            log_seconds=number("trainer.log_seconds", trainer_cfg.get("log_seconds", 30.0), 0, open_low=True),
            divergence_factor=number("trainer.divergence_factor", trainer_cfg.get("divergence_factor",
                                     DIVERGENCE_FACTOR), 1, optional=True, open_low=True),
            step_cost=step_cost,
            clock=clock,
        )


@dataclass(frozen=True)
class Outcome:
    status: str
    reason: str | None
    iterations: int
    train_seconds: float
    final_eval: dict
    stopped_by: str | None = None  # iterations | time_budget (completed runs)


def make_step(scene: Scene, rule: UpdateRule, batch_size: int):
    """(params, opt_state, iteration, train_key, train_set) -> (params, opt_state, logs); the minibatch is drawn
    inside from fold_in(train_key, iteration) (out of train_set, if the scene has a fixed one), so every variant
    with the same seed and batch size sees the same batches. The rule's gradient route gives the loss, the
    gradient, the rule's extra arguments and the route's logs (physgrad.gradients); the rule's state may add
    logs of its own (physgrad.optim.state_logs)."""

    def step(params, opt_state, iteration, train_key, train_set):
        batch = scene.draw_batch(jax.random.fold_in(train_key, iteration), batch_size, train_set)
        loss, grads, extra, route_logs = rule.gradient(scene, params, batch)
        updates, opt_state = rule.transform.update(grads, opt_state, params, **extra)
        logs = {"loss": loss, "grad_norm": optax.tree.norm(grads), "update_norm": optax.tree.norm(updates),
                **route_logs, **state_logs(opt_state)}
        return optax.apply_updates(params, updates), opt_state, logs

    return step


# checked for NaN/Inf after every step, in causal order: the physical output (the simulated state or what is
# read out of it: a blow-up of the physics shows here first), the loss, the gradient, the update; the first
# non-finite one is the reason
GUARDED = ("output_max_abs", "loss", "grad_norm", "update_norm")
QUANTITY = {"output_max_abs": "output", "loss": "loss", "grad_norm": "gradient", "update_norm": "update"}


def divergence_reason(quantity: str, logs: dict, iteration: int, svd_failures_before: float) -> str:
    """One line: which quantity went non-finite first, its value, the iteration, and a failed factorisation if
    that is what happened at this step."""
    reason = f"{QUANTITY[quantity]} became {logs[quantity]} at iteration {iteration} ({quantity})"
    if logs.get("svd_failures", 0.0) > svd_failures_before:
        reason += ("; the SVD/eigh of the Jacobian did not converge (optim.retry_float64=true retries it in "
                   "float64, precision=64 runs everything in float64)")
    return reason


def blew_up(loss: float, first_loss: float | None, factor: float | None) -> bool:
    """A finite training loss past factor times the first step's (a blow-up that has not reached NaN yet); never
    when the first loss is 0 or the bound is off (factor None)."""
    return factor is not None and first_loss is not None and first_loss > 0 and loss > factor * first_loss


def packed_logs(step, names: list[str]):
    """The step with its logged scalars stacked into one vector (one device-to-host transfer per iteration
    instead of one per scalar); their names are stored into `names` when the step is traced."""

    def packed(*args):
        params, opt_state, logs = step(*args)
        names[:] = sorted(logs)
        dtype = logs["loss"].dtype
        return params, opt_state, jnp.stack([jnp.asarray(logs[name], dtype) for name in names])

    return packed


class StopRequest:
    """Signal handler for SIGINT and SIGTERM, installed for the whole job (start-up, training and writing the
    final file). The first signal asks the loop to stop after the current step; a second one ends the wait for
    a step still computing (a 20 s step stops within 0.1 s; the step's result is dropped). The handler
    never raises: the loop acts on it between steps and in that wait, so no exception can land inside a write,
    and signals that arrive while the final file is written are only counted. `on_first` is called with the
    signal's name at the first one (a sweep records there that it is being stopped)."""

    def __init__(self, on_first=None):
        self.signal_name: str | None = None
        self.at_once = False
        self.received = 0
        self.on_first = on_first
        self.raising = False  # set-up (no step running, no file half written): a signal raises at once
        self._waiting: threading.Event | None = None

    def __call__(self, signum, frame):
        self.received += 1
        self.request(signal.Signals(signum).name, at_once=self.signal_name is not None)
        if self.raising:
            self.raising = False  # one exception; what handles it writes the files
            raise StopInterrupt(self.signal_name)

    def raise_if_stopped(self) -> None:
        if self.signal_name is not None:
            raise KeyboardInterrupt(self.signal_name)

    def request(self, name: str, at_once: bool = False) -> None:
        """Ask the run to stop after the current step (at_once: without waiting for it); also called by a
        sweep's watcher thread."""
        if self.signal_name is None:
            self.signal_name = name
            if self.on_first is not None:
                self.on_first(name)
        if at_once:
            self.at_once = True
            waiting = self._waiting
            if waiting is not None:
                waiting.set()

    def call(self, fn, *args):
        """fn(*args) with its results ready, computed in a helper thread (XLA's CPU client runs a computation in
        the thread that calls it), while this thread waits in slices so that the signal handler runs; raises
        KeyboardInterrupt if a second signal came first (the computation is left to finish unseen)."""
        ready, result = threading.Event(), []

        def compute():
            try:
                result.append(jax.block_until_ready(fn(*args)))
            except BaseException as error:  # noqa: BLE001 - handed to the waiting thread
                result.append(error)
            ready.set()

        self._waiting = ready
        thread = threading.Thread(target=compute, daemon=True, name="physgrad-step")
        thread.start()
        try:
            # a signal delivered to another thread (XLA's) wakes nobody: its handler runs when this thread is
            # back in Python, which the slices ensure
            while not self.at_once and not ready.wait(WAKE_SECONDS):
                pass
        finally:
            self._waiting = None
        if not result:  # woken by the second signal
            ABANDONED.append(thread)
            raise KeyboardInterrupt(self.signal_name)
        if isinstance(result[0], BaseException):
            raise result[0]
        return result[0]


class StopInterrupt(KeyboardInterrupt):
    """What StopRequest raises during set-up. Raised inside code the interpreter runs on its own (a garbage
    collector callback, a finaliser) it cannot propagate: it is then dropped without a traceback (the
    unraisable hook below), the stop stays requested and the job's next check (raise_if_stopped, the training
    loop's first) acts on it."""


@contextmanager
def stop_on_signals(on_first=None):
    request = StopRequest(on_first)
    try:
        previous = {sig: signal.signal(sig, request) for sig in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: leave signals alone
        yield request
        return
    lost = take_lost()  # a signal before the job whose interrupt the interpreter dropped (physgrad.interrupts)
    if lost is not None:
        request.request(lost)
    previous_hook = sys.unraisablehook

    def unraisable(info):
        if not isinstance(info.exc_value, StopInterrupt):
            previous_hook(info)

    sys.unraisablehook = unraisable
    try:
        yield request
    finally:
        sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@dataclass(frozen=True)
class Seeds:
    """What differs between the seeds trained together in one process, stacked on a leading axis: initial
    networks, minibatch keys, fixed training sets (None if drawn fresh), test sets and validation sets (None
    when the run does not evaluate on validation data: trainer.validation=false)."""

    params: Any
    train_keys: jax.Array
    train_sets: Any
    test_sets: Any
    validation_sets: Any = None

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
    validate: Any = None  # the held-out loss compiled for the validation sets (the loss only, no metrics)


def compile_training(scene: Scene, rule: UpdateRule, seeds: Seeds, batch_size: int) -> CompiledTraining:
    """Flatten each seed's network into one vector (Scene.over_flat_params), then compile the vectorised step
    (params, opt_state, iteration, train_keys, train_sets) -> (params, opt_state, logs[seed, name]) and the
    evaluation (params, test_sets) -> {name: [seed]}, ahead of time (what `make bench` times, too)."""
    unravel = ravel_pytree(seeds.network())[1]
    flat_scene = scene.over_flat_params(unravel)
    params = jax.vmap(lambda tree: ravel_pytree(tree)[0])(seeds.params)
    if rule.on_layers:  # a rule that is not element-wise sees the network's layers (physgrad.optim.on_tree)
        rule = rule._replace(transform=on_tree(rule.transform, unravel))
    count = seeds.count
    opt_state = over_seeds(rule.transform.init, count, (0,))(params)
    log_names: list[str] = []
    one_step = packed_logs(make_step(flat_scene, rule, batch_size), log_names)
    step = jax.jit(over_seeds(one_step, count, (0, 0, None, 0, 0))).lower(
        params, opt_state, np.int32(0), seeds.train_keys, seeds.train_sets).compile()
    evaluating = jax.jit(over_seeds(flat_scene.evaluate, count, (0, 0))).lower(params, seeds.test_sets)
    evaluate = evaluating.compile()
    validate = None
    if seeds.validation_sets is not None:
        same = jax.tree_util.tree_structure(seeds.validation_sets) == jax.tree_util.tree_structure(seeds.test_sets) \
            and all(a.shape == b.shape and a.dtype == b.dtype for a, b in zip(
                jax.tree_util.tree_leaves(seeds.validation_sets), jax.tree_util.tree_leaves(seeds.test_sets)))
        if same and set(evaluating.out_info) == {"loss"}:  # no metrics: the test evaluation is the loss
            validate = evaluate
        else:  # validation reads the loss only: its metrics (a KS stability rollout: 200 steps) are not paid
            validate = jax.jit(over_seeds(flat_scene.held_out_loss, count, (0, 0))).lower(
                params, seeds.validation_sets).compile()
    return CompiledTraining(step, evaluate, params, opt_state, log_names, validate)


def timing_attributes(step_seconds: list[float], load_start: float, load_end: float, static_cost: bool = True) -> dict:
    """The step-time percentiles, the load average at the start and the end, and the contention flag with its
    reason (physgrad.machine.contention)."""
    statistics = step_statistics(step_seconds)
    cores = cpu_count()
    why = contention(statistics, len(step_seconds), load_start, load_end, cores, static_cost)
    attrs = {**statistics, "load_start": load_start, "load_end": load_end, "contended": int(bool(why))}
    if why:
        attrs["contention"] = why
    return attrs


@dataclass
class SeedRun:
    """What the loop tracks for one seed: its results file, how it ended so far, its last evaluation, and the
    factorisation failures counted before the current step (to name them in a divergence reason)."""

    writer: ResultsWriter
    status: str = "completed"
    reason: str | None = None
    iterations: int | None = None  # set when the seed stops before the others (diverged)
    latest_eval: dict = field(default_factory=dict)
    svd_failures: float = 0.0
    first_loss: float | None = None  # the training loss of the first step: the scale of the blow-up bound

    @property
    def running(self) -> bool:
        return self.status == "completed"


class Progress:
    """What the user sees while a run trains. On a terminal, a bar over the iterations, or over the training
    seconds when a time budget is set (its ETA is then the budget's), that says when it is compiling; without
    one (a batch job, nohup), a log line every trainer.log_seconds of wall-clock with iteration, loss and
    elapsed training time."""

    def __init__(self, settings: TrainerSettings, label: str):
        self.settings, self.label = settings, label
        self.by_time = settings.time_budget is not None
        total = settings.time_budget if self.by_time else settings.iterations
        self.bar = tqdm(total=total, desc=f"{label} compiling", mininterval=0.5, disable=None, leave=False,
                        unit="s" if self.by_time else "it",
                        bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
                        if self.by_time else None)
        self.logging = self.bar.disable
        self.last_log = clock()

    def compiled(self, seconds: float) -> None:
        self.bar.set_description(self.label)
        if self.logging:
            log.info("%s compiled in %.1f s", self.label, seconds)

    def update(self, iteration: int, train_seconds: float, loss: float) -> None:
        """Called at every flush (at most every trainer.flush_seconds), not at every step."""
        if not self.bar.disable:
            self.bar.set_postfix_str(f"it {iteration}, loss {loss:.3e}", refresh=False)
            self.bar.update((min(train_seconds, self.bar.total) if self.by_time else iteration) - self.bar.n)
        elif clock() - self.last_log >= self.settings.log_seconds:
            self.last_log = clock()
            log.info("%s iteration %d, loss %.4g, %.1f s of training", self.label, iteration, loss, train_seconds)

    def close(self) -> None:
        self.bar.close()




def finish_or_mark(writer: ResultsWriter, status: str, reason: str | None, **attrs) -> str | None:
    """writer.finish(), and if the file cannot be written (disk full) status failed set on the file as it is;
    returns the write error as one line, or None."""
    try:
        writer.finish(status, reason, **attrs)
        return None
    except ResultsWriteError as error:
        writer.mark_failed_in_place(f"{error}; the run ended {status}" + (f" ({reason})" if reason else ""))
        return str(error)


def train(scene: Scene, rule: UpdateRule, seeds: Seeds, writers: list[ResultsWriter], settings: TrainerSettings,
          label: str = "", stop: StopRequest | None = None) -> list[Outcome]:
    """Compile, then iterate until trainer.iterations or trainer.time_budget (training seconds), whichever
    comes first, every seed in one vectorised step (writers: one per seed). The budget is checked after each
    step, so a run passes it by less than one step. Evaluations at the start, every trainer.eval_every
    iterations, whenever trainer.eval_seconds of training passed since the last one, and at the end. A seed
    whose output, loss, gradient or update turns non-finite ends with status diverged (its rows stop there)
    while the others go on; the wall time is the shared one. stop: the job's signal handler (installed here
    if None). A file that cannot be written ends the run failed (ResultsWriteError). Returns one Outcome per
    seed."""
    if stop is None:
        with stop_on_signals() as own:
            return train(scene, rule, seeds, writers, settings, label, own)
    runs = [SeedRun(writer) for writer in writers]
    train_seconds, done, stopped_by = 0.0, 0, None
    params = None
    validate = None
    last_eval_seconds = 0.0

    def clock_times(iteration) -> dict:
        """The measured training seconds and, with a calibration, the calibrated ones (iterations x step cost)."""
        times = {"wall_time": train_seconds}
        if settings.step_cost is not None:
            times["calibrated_time"] = iteration * settings.step_cost
        return times

    def budget_seconds(iteration) -> float:
        """The time the budget and eval_seconds read: the measured or the calibrated clock (trainer.clock)."""
        return iteration * settings.step_cost if settings.clock == "calibrated" else train_seconds

    def record_eval(iteration):
        nonlocal last_eval_seconds
        # written with the next periodic flush: a flush per evaluation cost 2% of a fast scene's wall time
        metrics = {k: np.asarray(v).tolist() for k, v in jax.device_get(evaluate(params, seeds.test_sets)).items()}
        if validate is not None:
            metrics["validation_loss"] = np.asarray(jax.device_get(validate(params, seeds.validation_sets)["loss"])).tolist()
        last_eval_seconds = budget_seconds(iteration)
        for index, run in enumerate(runs):
            if run.running:
                values = {k: v[index] for k, v in metrics.items()}
                run.writer.append("eval", {"iteration": iteration, **clock_times(iteration), **values})
                run.latest_eval = {**values, "iteration": iteration}

    def for_every_writer(method: str, *args, **kwargs):
        for run in runs:
            getattr(run.writer, method)(*args, **kwargs)

    def stop_requested():
        if stop.signal_name is not None:
            raise KeyboardInterrupt(stop.signal_name)

    progress = Progress(settings, label)
    step_seconds: list[float] = []  # every step's time but the first (compiling) call's: contention
    load_start = load_average()
    try:
        stop_requested()  # a signal during start-up
        # compiling can take minutes: inside the guard, so a failure or an interrupt here is recorded too
        start = clock()
        compiled = compile_training(scene, rule, seeds, settings.batch_size)
        step, evaluate, log_names = compiled.step, compiled.evaluate, compiled.log_names
        validate = compiled.validate
        params, opt_state = compiled.params, compiled.opt_state
        compile_seconds = clock() - start
        for_every_writer("set_attrs", compile_seconds=compile_seconds)
        progress.compiled(compile_seconds)
        clock_columns = ("wall_time", "calibrated_time") if settings.step_cost is not None else ("wall_time",)
        for_every_writer("set_columns", "train", ("iteration", *clock_columns, *log_names))
        if settings.step_cost is not None:
            for_every_writer("set_attrs", step_cost=settings.step_cost, clock=settings.clock)
        guarded = [log_names.index(name) for name in GUARDED]
        loss_at = log_names.index("loss")
        svd_at = log_names.index("svd_failures") if "svd_failures" in log_names else None
        running = list(enumerate(runs))
        stop_requested()
        record_eval(0)
        for_every_writer("flush")
        last_flush = clock()
        flush_interval = settings.flush_seconds
        first_step_seconds, seconds = 0.0, 0.0
        iteration = 0
        while settings.iterations is None or iteration < settings.iterations:
            stop_requested()
            tick = clock()
            arguments = (params, opt_state, np.int32(iteration), seeds.train_keys, seeds.train_sets)
            if iteration == 0 or seconds >= SLOW_STEP_SECONDS:  # a second signal ends it without its result
                new_params, opt_state, logs = stop.call(step, *arguments)
            else:
                new_params, opt_state, logs = step(*arguments)
            logs = np.asarray(logs).tolist()  # one transfer for every logged scalar of every seed
            jax.block_until_ready(new_params)
            seconds = clock() - tick
            train_seconds += seconds
            params, done = new_params, iteration + 1
            if iteration == 0:
                first_step_seconds = seconds
            else:
                step_seconds.append(seconds)
            if iteration == 1:
                # the first call's one-off cost (how much longer it took than the second) is start-up, not
                # training: taken off every time stamp since, which are all still in the buffers
                overhead = max(0.0, first_step_seconds - seconds)
                train_seconds -= overhead
                if settings.clock == "measured" and last_eval_seconds:
                    last_eval_seconds = max(0.0, last_eval_seconds - overhead)
                for_every_writer("shift_buffered_time", -overhead)
                for_every_writer("set_attrs", first_step_overhead_seconds=overhead)
            diverged = False
            for index, run in running:
                row = logs[index]
                run.writer.append_row("train", (iteration, *clock_times(done).values(), *row))
                bad = next((log_names[i] for i in guarded if not math.isfinite(row[i])), None)
                if run.first_loss is None:
                    run.first_loss = row[loss_at]
                if bad is not None:
                    run.status, run.iterations, diverged = "diverged", done, True
                    run.reason = divergence_reason(bad, dict(zip(log_names, row)), iteration, run.svd_failures)
                elif blew_up(row[loss_at], run.first_loss, settings.divergence_factor):
                    run.status, run.iterations, diverged = "diverged", done, True
                    run.reason = (f"loss grew to {row[loss_at]:.4g} at iteration {iteration}, more than "
                                  f"trainer.divergence_factor={settings.divergence_factor:g} times its first value "
                                  f"{run.first_loss:.4g} (a blow-up without NaN)")
                elif svd_at is not None:
                    run.svd_failures = row[svd_at]
            if diverged:  # the running list changes only here, not at every step
                running = [(index, run) for index, run in running if run.running]
                if not running:
                    break
            iteration = done
            if settings.time_budget is not None and budget_seconds(done) >= settings.time_budget:
                stopped_by = "time_budget"
                break
            if done == settings.iterations:
                stopped_by = "iterations"
                break
            if done % settings.eval_every == 0 or (
                    settings.eval_seconds is not None
                    and budget_seconds(done) - last_eval_seconds >= settings.eval_seconds):
                record_eval(done)
            now = clock()
            if now - last_flush >= flush_interval and done > 1:  # after the first-step correction
                for_every_writer("flush")
                last_flush = clock()
                # the whole file is rewritten at each flush: as it grows, flush less often
                flush_interval = max(settings.flush_seconds, FLUSH_COST_FACTOR * (last_flush - now) / len(runs))
                progress.update(done, train_seconds, logs[running[0][0]][guarded[1]])
        if stopped_by is not None:  # not in the files of seeds that diverged before
            for run in runs:
                if run.running:
                    run.writer.set_attrs(stopped_by=stopped_by)
        if any(run.running and run.latest_eval["iteration"] != done for run in runs):
            record_eval(done)
    except KeyboardInterrupt as interrupt:
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} after {done} iterations"
        for run in runs:
            if run.running:
                run.status, run.reason = "interrupted", why
    except BaseException as error:
        message = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
        if isinstance(error, ResultsWriteError):
            message = str(error)
        for run in runs:
            finish_or_mark(run.writer, "failed", message, iterations=run.iterations or done,
                           train_seconds=train_seconds)
        raise
    finally:
        progress.close()
        # a line search (a rule given value_fn on the gradient route: optax.lbfgs) costs what the data ask for
        static_cost = rule.uses_jacobian or not getattr(rule.gradient, "with_value", False)
        for_every_writer("set_attrs", **timing_attributes(step_seconds, load_start, load_average(), static_cost))
    outcomes, write_errors = [], []
    for index, run in enumerate(runs):
        flat = None if params is None else np.asarray(params[index])
        if flat is not None and run.status != "diverged" and np.isfinite(flat).all():  # a later run can start from it (init_from)
            run.writer.save_params(flat)
        iterations = run.iterations or done
        error = finish_or_mark(run.writer, run.status, run.reason, iterations=iterations, train_seconds=train_seconds)
        if error:
            write_errors.append(error)
        outcomes.append(Outcome(run.status, run.reason, iterations, train_seconds, run.latest_eval,
                                stopped_by if run.status == "completed" else None))
    if write_errors:
        raise ResultsWriteError(write_errors[0])
    return outcomes
