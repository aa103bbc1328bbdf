"""The training loop: one compiled step, training-only timing, NaN/Inf guard, buffered HDF5 rows.

Timing contract: ``wall_time`` is the cumulative time of finished training steps (each step is timed
from dispatch until its outputs are ready). Compilation happens before the loop
(``compile_seconds``), and so does the one-off cost of the compiled step's first call
(``first_step_overhead_seconds``: how much longer the first step took than the second, 10 to 50 ms
on CPU whatever the step costs, which would otherwise be 10 to 200 times a fast step); evaluations,
HDF5 flushes, logging and the progress bar fall outside the timed intervals.

`train` runs a TrainingLoop in named steps: start (compile, first evaluation), iterate (step, count
its time, guard the rows, stop at a budget, evaluate, flush), end, and finish (the final files). The
compiled step itself and the seeds trained together are in physgrad.training, the check of each
step's rows in physgrad.guard, the seeds' results files in physgrad.writers, signals in
physgrad.interrupts.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import jax
import numpy as np

from physgrad.errors import ResultsWriteError, innermost_cause, scene_failed
from physgrad.guard import RowGuard
from physgrad.interrupts import (
    STALL_CPU_SECONDS,
    STALL_SECONDS,
    StepStalled,
    StopRequest,
    stop_on_signals,
)
from physgrad.machine import load_average, timing_attributes
from physgrad.optim import LINE_SEARCH_LOG, UpdateRule
from physgrad.progress import Progress
from physgrad.results import ResultsWriter
from physgrad.tasks import Scene
from physgrad.trainer_settings import TrainerSettings
from physgrad.training import CompiledTraining, Seeds, compile_training, ready
from physgrad.writers import SeedRun, Writers, finish_or_mark

log = logging.getLogger("physgrad")
clock = time.perf_counter  # every interval of the loop is read from this clock (tests replace it)
# a step at least this long runs in a helper thread, so that a second signal ends it
SLOW_STEP_SECONDS = 0.2
# the file is rewritten at most every 20 times what one write takes (<= 5 % of the time)
FLUSH_COST_FACTOR = 20


class CallbackFailureFilter(logging.Filter):
    """Drops JAX's log of a host callback that raised ("jax.pure_callback failed", with its
    traceback, before XLA re-raises the exception): the run records that failure itself, in one
    line (solver_failed; a failure elsewhere keeps its traceback in the job's error.txt)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not (message.startswith("jax.") and message.endswith("callback failed"))


def quiet_callback_failures() -> None:
    """CallbackFailureFilter on JAX's callback logger, once."""
    logger = logging.getLogger("jax._src.callback")
    if not any(isinstance(f, CallbackFailureFilter) for f in logger.filters):
        logger.addFilter(CallbackFailureFilter())


@dataclass(frozen=True)
class Outcome:
    status: str
    reason: str | None
    iterations: int
    train_seconds: float
    final_eval: dict
    stopped_by: str | None = None  # iterations | time_budget (completed runs)


class TrainingLoop:
    """One run of train(): the compiled step and evaluation, the seeds' parameters and state, the
    training clock, and when the files are written. Its steps, in order: start, iterate, end, then
    finish (or interrupted or failed first)."""

    def __init__(
        self,
        rule: UpdateRule,
        seeds: Seeds,
        writers: list[ResultsWriter],
        settings: TrainerSettings,
        stop: StopRequest,
        progress: Progress,
    ) -> None:
        self.rule, self.seeds, self.settings = rule, seeds, settings
        self.stop, self.progress = stop, progress
        self.runs = [SeedRun(writer) for writer in writers]
        self.writers = Writers(writers)
        self.compiled: CompiledTraining | None = None
        self.guard: RowGuard | None = None  # both set by start()
        self.params, self.opt_state = None, None
        self.done = 0  # iterations finished
        # line-search evaluations of the steps done (each step's most over the running seeds: a
        # vectorised line search runs until every seed's is done), charged by the calibrated clock
        self.evaluations = 0.0
        self.evaluations_at: int | None = None  # their column among the logs, where logged
        self.train_seconds = 0.0
        self.first_step_seconds = 0.0
        # every step's time but the first (compiling) call's: contention
        self.step_seconds: list[float] = []
        self.last_eval_seconds = 0.0
        self.stopped_by: str | None = None
        self.last_flush, self.flush_interval = 0.0, settings.flush_seconds

    def clock_times(self, iteration: int) -> dict:
        """The measured training seconds and, with a calibration, the calibrated ones
        (TrainerSettings.charged_seconds: iterations x step cost, a scheduled update at its expected
        cost)."""
        times = {"wall_time": self.train_seconds}
        if self.settings.step_cost is not None:
            times["calibrated_time"] = self.charged_seconds(iteration)
        return times

    def charged_seconds(self, iteration: int) -> float:
        """TrainerSettings.charged_seconds after `iteration` steps, with the line-search
        evaluations the steps so far made (self.evaluations)."""
        return self.settings.charged_seconds(iteration, self.evaluations)

    def budget_seconds(self, iteration: int) -> float:
        """The time the budget and eval_seconds read: the measured or the calibrated clock
        (trainer.clock)."""
        return (
            self.charged_seconds(iteration)
            if self.settings.clock == "calibrated"
            else self.train_seconds
        )

    def start(self, scene: Scene) -> None:
        """Compile (minutes, sometimes), set the files' columns, and evaluate the initial networks,
        written at once."""
        self.stop.raise_if_stopped()  # a signal during start-up
        settings, start = self.settings, clock()
        compiled = self.compiled = compile_training(
            scene, self.rule, self.seeds, settings.batch_size
        )
        self.params, self.opt_state = compiled.params, compiled.opt_state
        compile_seconds = clock() - start
        self.writers.set_attrs(compile_seconds=compile_seconds)
        self.progress.compiled(compile_seconds)
        clock_columns = (
            ("wall_time", "calibrated_time") if settings.step_cost is not None else ("wall_time",)
        )
        self.writers.set_columns("train", ("iteration", *clock_columns, *compiled.log_names))
        if settings.step_cost is not None:
            self.writers.set_attrs(step_cost=settings.step_cost, clock=settings.clock)
        if settings.update_cost is not None:
            self.writers.set_attrs(update_cost=settings.update_cost)
        self.guard = RowGuard(compiled.log_names, settings.divergence_factor)
        if settings.evaluation_cost is not None:  # the door let it through for a line search
            self.evaluations_at = compiled.log_names.index(LINE_SEARCH_LOG)
            self.writers.set_attrs(
                evaluation_cost=settings.evaluation_cost,
                step_evaluations=settings.step_evaluations,
            )
        self.stop.raise_if_stopped()
        self.record_eval(0)
        self.writers.flush()
        self.last_flush = clock()

    def iterate(self) -> None:
        """Train until trainer.iterations or the time budget (stopped_by), or until every seed
        diverged."""
        settings, running, seconds = self.settings, list(enumerate(self.runs)), 0.0
        while settings.iterations is None or self.done < settings.iterations:
            self.stop.raise_if_stopped()
            iteration = self.done
            logs, seconds = self.step(seconds)
            self.count_time(iteration, seconds)
            running = self.record_rows(running, logs, iteration)
            if not running:
                break
            self.stopped_by = self.budget_spent()
            if self.stopped_by is not None:
                break
            if self.evaluation_due():
                self.record_eval(self.done)
            self.flush_if_due(logs[running[0][0]][self.guard.loss_at])

    def step(self, previous_seconds: float) -> tuple[list, float]:
        """One step of every seed, timed from dispatch until its outputs are ready: the logged
        scalars (a row per seed) and its seconds. The first step, and any after a step of
        SLOW_STEP_SECONDS or more, run where a second signal ends the wait without their result
        (StopRequest.call)."""
        iteration, compiled = self.done, self.compiled
        tick = clock()
        arguments = (
            self.params,
            self.opt_state,
            np.int32(iteration),
            self.seeds.train_keys,
            self.seeds.train_sets,
        )
        if iteration == 0 or previous_seconds >= SLOW_STEP_SECONDS:
            # a stall is told by the CPU left unused: on an accelerator the host waits idle
            stall = STALL_SECONDS if jax.default_backend() == "cpu" else math.inf
            params, self.opt_state, logs = self.stop.call(
                ready(compiled.step),
                *arguments,
                stall_seconds=stall,
                stall_cpu_seconds=STALL_CPU_SECONDS,
            )
        else:
            params, self.opt_state, logs = compiled.step(*arguments)
        logs = np.asarray(logs).tolist()  # one transfer for every logged scalar of every seed
        jax.block_until_ready(params)
        seconds = clock() - tick
        self.train_seconds += seconds
        self.params, self.done = params, iteration + 1
        return logs, seconds

    def count_time(self, iteration: int, seconds: float) -> None:
        """Keep the step's seconds for the contention check; at the second step, take the first's
        one-off cost off the training clock."""
        if iteration == 0:
            self.first_step_seconds = seconds
        else:
            self.step_seconds.append(seconds)
        if iteration == 1:
            self.correct_first_step(max(0.0, self.first_step_seconds - seconds))

    def correct_first_step(self, overhead: float) -> None:
        """The first call's one-off cost (how much longer it took than the second) is start-up, not
        training: taken off the training clock and every time stamp since, which are all still in
        the buffers."""
        self.train_seconds -= overhead
        if self.settings.clock == "measured" and self.last_eval_seconds:
            self.last_eval_seconds = max(0.0, self.last_eval_seconds - overhead)
        self.writers.shift_buffered_time(-overhead)
        self.writers.set_attrs(first_step_overhead_seconds=overhead)

    def record_rows(self, running: list, logs: list, iteration: int) -> list:
        """Each running seed's row into its file, then guarded: a seed that diverged stops there
        (its status and reason set). Returns the (index, run) pairs still running: the same list
        unless one stopped."""
        diverged = False
        if self.evaluations_at is not None:
            self.evaluations += max(logs[index][self.evaluations_at] for index, _ in running)
        times = tuple(self.clock_times(self.done).values())
        for index, run in running:
            row = logs[index]
            run.writer.append_row("train", (iteration, *times, *row))
            reason = self.guard.check(run, row, iteration)
            if reason is not None:
                run.status, run.iterations, run.reason = "diverged", self.done, reason
                diverged = True
        return [(index, run) for index, run in running if run.running] if diverged else running

    def budget_spent(self) -> str | None:
        """time_budget or iterations if the steps done reached it (the time budget first), else
        None."""
        settings = self.settings
        if (
            settings.time_budget is not None
            and self.budget_seconds(self.done) >= settings.time_budget
        ):
            return "time_budget"
        return "iterations" if self.done == settings.iterations else None

    def evaluation_due(self) -> bool:
        """Every trainer.eval_every iterations, and whenever trainer.eval_seconds passed since the
        last one."""
        settings = self.settings
        return self.done % settings.eval_every == 0 or (
            settings.eval_seconds is not None
            and self.budget_seconds(self.done) - self.last_eval_seconds >= settings.eval_seconds
        )

    def evaluate(self) -> dict:
        """Every seed's held-out metrics (test sets, and validation sets if any), one list each."""
        compiled, seeds = self.compiled, self.seeds
        metrics = {
            k: np.asarray(v).tolist()
            for k, v in jax.device_get(compiled.evaluate(self.params, seeds.test_sets)).items()
        }
        if compiled.validate is not None:
            metrics["validation_loss"] = np.asarray(
                jax.device_get(compiled.validate(self.params, seeds.validation_sets)["loss"])
            ).tolist()
        return metrics

    def record_eval(self, iteration: int, metrics: dict | None = None) -> None:
        """Evaluate every seed (or take the metrics given); rows for the seeds still running,
        written with the next periodic flush: a flush per evaluation cost 2% of a fast scene's wall
        time."""
        metrics = self.evaluate() if metrics is None else metrics
        self.last_eval_seconds = self.budget_seconds(iteration)
        for index, run in enumerate(self.runs):
            if run.running:
                values = {k: v[index] for k, v in metrics.items()}
                run.writer.append(
                    "eval", {"iteration": iteration, **self.clock_times(iteration), **values}
                )
                run.latest_eval = {**values, "iteration": iteration}

    def flush_if_due(self, loss: float) -> None:
        """Write the files if trainer.flush_seconds passed since the last write (and the first-step
        correction is done); the whole file is rewritten each time, so as it grows at most every
        FLUSH_COST_FACTOR times what the last write took. The progress shown moves here too."""
        now = clock()
        if now - self.last_flush >= self.flush_interval and self.done > 1:
            self.writers.flush()
            self.last_flush = clock()
            self.flush_interval = max(
                self.settings.flush_seconds,
                FLUSH_COST_FACTOR * (self.last_flush - now) / len(self.runs),
            )
            self.progress.update(self.done, self.train_seconds, loss)

    def end(self) -> None:
        """The budget that stopped training, on the files of the seeds that did not diverge before,
        and a final evaluation where the last one is older than the last step."""
        for run in self.runs:
            if self.stopped_by is not None and run.running:
                run.writer.set_attrs(stopped_by=self.stopped_by)
        if any(run.running and run.latest_eval["iteration"] != self.done for run in self.runs):
            self.record_eval(self.done)

    def solver_failed(self, error: BaseException) -> None:
        """The scene's own code gave up inside a step (a solver's step limit, an equinox check):
        the variant failing on the scene, an endpoint like a divergence (the seeds still running
        end diverged, rows kept, the cause in one line), not a crash of the run."""
        reason = f"solver failed: {innermost_cause(error)}"
        for run in self.runs:
            if run.running:
                run.status, run.iterations, run.reason = "diverged", self.done, reason

    def interrupted(self, interrupt: KeyboardInterrupt) -> None:
        """The seeds still running end interrupted, with the signal and the iterations done as the
        reason, and, stopped between steps by one signal, a last evaluation of the networks they
        reached (computed where a second signal ends the wait without it)."""
        why = f"{interrupt.args[0] if interrupt.args else 'SIGINT'} after {self.done} iterations"
        stale = [r for r in self.runs if r.running and r.latest_eval.get("iteration") != self.done]
        if stale and self.compiled is not None and not self.stop.at_once:
            try:
                metrics = self.stop.call(self.evaluate)
            except (KeyboardInterrupt, StepStalled):
                why += "; a second signal came before its last evaluation"
            else:
                self.record_eval(self.done, metrics)
        for run in self.runs:
            if run.running:
                run.status, run.reason = "interrupted", why

    def failed(self, error: BaseException) -> None:
        """Every file ends failed with the error in one line (marked failed in place if it cannot be
        written)."""
        message = innermost_cause(error)
        if isinstance(error, ResultsWriteError):
            message = str(error)
        for run in self.runs:
            finish_or_mark(
                run.writer,
                "failed",
                message,
                iterations=run.iterations or self.done,
                train_seconds=self.train_seconds,
            )

    def finish(self) -> list[Outcome]:
        """The final files (each seed's network, unless it diverged) and one Outcome per seed;
        ResultsWriteError if a file could not be written."""
        outcomes, write_errors = [], []
        for index, run in enumerate(self.runs):
            flat = None if self.params is None else np.asarray(self.params[index])
            if flat is not None and run.status != "diverged" and np.isfinite(flat).all():
                run.writer.save_params(flat)  # init_from can use it
            iterations = run.iterations or self.done
            error = finish_or_mark(
                run.writer,
                run.status,
                run.reason,
                iterations=iterations,
                train_seconds=self.train_seconds,
            )
            if error:
                write_errors.append(error)
            outcomes.append(
                Outcome(
                    run.status,
                    run.reason,
                    iterations,
                    self.train_seconds,
                    run.latest_eval,
                    self.stopped_by if run.status == "completed" else None,
                )
            )
        if write_errors:
            raise ResultsWriteError(write_errors[0])
        return outcomes


def train(
    scene: Scene,
    rule: UpdateRule,
    seeds: Seeds,
    writers: list[ResultsWriter],
    settings: TrainerSettings,
    label: str = "",
    stop: StopRequest | None = None,
) -> list[Outcome]:
    """Compile, then iterate until trainer.iterations or trainer.time_budget (training seconds),
    whichever comes first, every seed in one vectorised step (writers: one per seed). The budget is
    checked after each step, so a run passes it by less than one step. Evaluations at the start,
    every trainer.eval_every iterations, whenever trainer.eval_seconds of training passed since the
    last one, and at the end. A seed whose output, loss, gradient or update turns non-finite ends
    with status diverged (its rows stop there) while the others go on; the wall time is the shared
    one. stop: the job's signal handler (installed here if None). A file that cannot be written ends
    the run failed (ResultsWriteError). Returns one Outcome per seed."""
    if stop is None:
        with stop_on_signals() as own:
            return train(scene, rule, seeds, writers, settings, label, own)
    quiet_callback_failures()
    progress = Progress(settings, label, clock)
    loop = TrainingLoop(rule, seeds, writers, settings, stop, progress)
    load_start = load_average()
    try:
        # compiling can take minutes: inside the guard, so a failure or an interrupt there is
        # recorded too
        try:
            loop.start(scene)  # compiling, and the evaluation at iteration 0
            loop.iterate()
            loop.end()
        except Exception as error:  # the scene's own code gave up in a step or an evaluation
            if not scene_failed(error):
                raise
            loop.solver_failed(error)
    except KeyboardInterrupt as interrupt:
        loop.interrupted(interrupt)
    except BaseException as error:
        loop.failed(error)
        raise
    finally:
        progress.close()
        # a line search (a rule given value_fn on the gradient pass: optax.lbfgs) costs what the
        # data ask for
        static_cost = rule.uses_jacobian or not getattr(rule.gradient, "with_value", False)
        loop.writers.set_attrs(
            **timing_attributes(loop.step_seconds, load_start, load_average(), static_cost)
        )
    return loop.finish()
