"""SIGINT and SIGTERM: how physgrad is stopped, in every phase of a command, without losing a
signal.

Two handlers, one per phase. Before a job (the console script's start-up, a sweep's launcher) a
signal raises at once: `raise_interrupt` turns it into a SignalInterrupt naming the signal; while
Hydra and OmegaConf compose a config (`composing`), where an exception leaves half-built config
nodes behind, it is kept for the next check (the job's start, the command's end). During a job
(start-up, training and writing the final files) the job's `StopRequest` handles it: the first
signal asks the training loop to stop after the current step, a second one ends the wait for a step
still computing; it raises only while the job is setting up (StopInterrupt), where nothing is half
done. `handling_signals` installs a handler for both signals, `stop_on_signals` the job's (which
also takes a scheduler's warning signal, SIGUSR2, as a stop: a job ends `interrupted` before its
time limit, its rows kept).

A signal handler's exception is raised in whatever Python code runs when the signal arrives. If that
code is one the interpreter runs on its own (a garbage-collector callback such as jaxlib's, a
finaliser, a weakref callback), the exception cannot propagate: Python prints "Exception ignored in
..." with a traceback and goes on as if no signal had come. Inside `keeping_lost_interrupts` (the
one unraisable hook) such an interrupt is dropped without a traceback and kept: a SignalInterrupt's
signal in `LOST`, where the next place that checks (a job's start, the end of a command) acts on it
as if it had been raised there; a StopInterrupt's stop stays requested on its StopRequest, which the
job's next check acts on. This module imports nothing heavy: the console script installs it before
JAX is loaded.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any, NoReturn

# what stops physgrad: Ctrl-C, and kill's or a scheduler's TERM
INTERRUPTS = (signal.SIGINT, signal.SIGTERM)
# what also stops a job: a scheduler's warning that its time is nearly up or that it is preempted
# (SLURM's --signal, USR2 as submitit asks for it; SUBMITIT_PREEMPT_SIGNAL names another)
WARNING_SIGNAL = getattr(
    signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2").upper(), signal.SIGUSR2
)
JOB_SIGNALS = (*INTERRUPTS, WARNING_SIGNAL)


def signal_label(signum: int) -> str:
    """The signal's name, with what it means where that is not plain (the scheduler's warning)."""
    name = signal.Signals(signum).name
    if signum == WARNING_SIGNAL and signum not in INTERRUPTS:
        return f"{name} (the scheduler's warning: time limit or preemption)"
    return name


# what signal.signal installs: a function of the signal number and the frame, or SIG_DFL / SIG_IGN
SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None
WAKE_SECONDS = 0.05  # how often a thread waiting for a step looks at signals
# steps left computing after a second signal: the command line ends with os._exit while one is
# alive, since a daemon thread that returns from XLA into a finalising interpreter aborts the
# process
ABANDONED: list[threading.Thread] = []
# a step whose process has used less than STALL_CPU_SECONDS of CPU in STALL_SECONDS has stalled,
# not computed: XLA's CPU client can wedge on a step of members trained together (its worker
# threads all idle, the step's result never ready; physgrad.machine.MEMBERS_XLA_FLAG avoids it)
STALL_SECONDS = 300.0
STALL_CPU_SECONDS = 1.0
# a wait of one WAKE_SECONDS slice that returns this much later found the whole process stopped
# (SIGSTOP, Ctrl-Z, a suspended machine): no thread computed, so that gap is no evidence of a stall
PAUSED_SECONDS = 2.0
STALL_HINT = (
    "XLA's CPU scheduler wedged (seen with steps of several members trained together); run again "
    "with XLA_FLAGS=--xla_cpu_enable_concurrency_optimized_scheduler=false"
)


class StepStalled(RuntimeError):
    """A step that stopped computing without returning (StopRequest.call)."""


class SignalInterrupt(KeyboardInterrupt):
    """KeyboardInterrupt raised by a handler here; args[0] is the signal's name ('SIGINT',
    'SIGTERM')."""


# names of signals whose SignalInterrupt was dropped by the interpreter, oldest first
LOST: list[str] = []


def raise_interrupt(signum: int, frame: FrameType | None) -> NoReturn:
    """Signal handler: SIGINT and SIGTERM both as a (Signal)KeyboardInterrupt naming the signal."""
    raise SignalInterrupt(signal.Signals(signum).name)


def keep_interrupt(signum: int, frame: FrameType | None) -> None:
    """Signal handler while Hydra and OmegaConf compose a config (`composing`): the signal is kept
    in LOST, not raised. An exception raised inside OmegaConf can leave a node half built, and the
    `finally` blocks that restore its flags then fail on it: the interrupt comes out as an unrelated
    config error (exit 1), or is swallowed. The next check acts on it."""
    LOST.append(signal.Signals(signum).name)


def take_lost() -> str | None:
    """The first lost signal's name, forgetting all of them (one stop acts on every signal before
    it)."""
    name = LOST[0] if LOST else None
    LOST.clear()
    return name


def install(handler: SignalHandler, signals: tuple = INTERRUPTS) -> dict:
    """handler for signals (SIGINT and SIGTERM); returns the handlers it replaced. ValueError
    outside the main thread."""
    return {sig: signal.signal(sig, handler) for sig in signals}


@contextmanager
def handling_signals(handler: SignalHandler, signals: tuple = INTERRUPTS) -> Iterator[bool]:
    """While inside: signals (SIGINT and SIGTERM) go to handler, and the previous handlers are back
    after. Yields whether it was installed: not in a thread other than the main one, where signals
    are left alone."""
    try:
        previous = install(handler, signals)
    except ValueError:  # not the main thread
        previous = None
    if previous is None:
        yield False
        return
    try:
        yield True
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextmanager
def composing() -> Iterator[None]:
    """While inside, where signals would raise (raise_interrupt: before a job): SIGINT and SIGTERM
    are kept (keep_interrupt) while library code composes configs, and one kept meanwhile is raised
    on leaving; physgrad's own code inside raises again (`raising_interrupts`). Where another
    handler is installed (a job's StopRequest, a sweep's LauncherSignals, which do not raise) or
    outside the main thread, nothing changes."""
    if signal.getsignal(signal.SIGINT) is not raise_interrupt:
        yield
        return
    with handling_signals(keep_interrupt):
        yield
    lost = take_lost()
    if lost is not None:
        raise SignalInterrupt(lost)


@contextmanager
def raising_interrupts() -> Iterator[None]:
    """physgrad's own code inside `composing` (a job's task function, which Hydra calls after
    composing): new signals raise again (raise_interrupt); one kept while composing stays in LOST
    for the job's first check (stop_on_signals: the job ends interrupted, its files saying so, as
    for any signal before training); on leaving, signals are kept again."""
    if signal.getsignal(signal.SIGINT) is not keep_interrupt:
        yield
        return
    with handling_signals(raise_interrupt):
        yield


@contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back (blocked) while inside; one that came meanwhile is handled on
    leaving."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, set(INTERRUPTS))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


class StopRequest:
    """Signal handler for SIGINT and SIGTERM, installed for the whole job (start-up, training and
    writing the final file). The first signal asks the loop to stop after the current step; a second
    one ends the wait for a step still computing (a 20 s step stops within 0.1 s; the step's result
    is dropped). The handler never raises: the loop acts on it between steps and in that wait, so no
    exception can land inside a write, and signals that arrive while the final file is written are
    only counted. `on_first` is called with the signal's name at the first one (a sweep records
    there that it is being stopped)."""

    def __init__(self, on_first: Callable[[str], None] | None = None) -> None:
        self.signal_name: str | None = None
        self.at_once = False
        self.received = 0
        self.on_first = on_first
        # set-up (no step running, no file half written): a signal raises at once
        self.raising = False
        self._waiting: threading.Event | None = None

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.received += 1
        self.request(signal_label(signum), at_once=self.signal_name is not None)
        if self.raising:
            self.raising = False  # one exception; what handles it writes the files
            raise StopInterrupt(self.signal_name)

    def raise_if_stopped(self) -> None:
        if self.signal_name is not None:
            raise KeyboardInterrupt(self.signal_name)

    def request(self, name: str, at_once: bool = False) -> None:
        """Ask the run to stop after the current step (at_once: without waiting for it); also called
        by a sweep's watcher thread."""
        if self.signal_name is None:
            self.signal_name = name
            if self.on_first is not None:
                self.on_first(name)
        if at_once:
            self.at_once = True
            waiting = self._waiting
            if waiting is not None:
                waiting.set()

    def call(
        self,
        fn: Callable[..., Any],
        *args: Any,
        stall_seconds: float = STALL_SECONDS,
        stall_cpu_seconds: float = STALL_CPU_SECONDS,
    ) -> Any:
        """fn(*args), computed in a helper thread (XLA's CPU client runs a computation in the thread
        that calls it; fn returns once its results are ready), while this thread waits in slices so
        that the signal handler runs; raises KeyboardInterrupt if a second signal came first, and
        StepStalled if the process used less than stall_cpu_seconds of CPU in stall_seconds without
        fn returning (either way the computation is left unseen). A slice that returns more than
        PAUSED_SECONDS late restarts that window: the whole process was stopped, not the step."""
        ready, result = threading.Event(), []

        def compute() -> None:
            try:
                result.append(fn(*args))
            except BaseException as error:  # noqa: BLE001 - handed to the waiting thread
                result.append(error)
            ready.set()

        self._waiting = ready
        thread = threading.Thread(target=compute, daemon=True, name="physgrad-step")
        thread.start()
        # the process's CPU time since the last look that found it computing (or found it resumed)
        since, cpu = time.monotonic(), time.process_time()
        woke, stalled = since, False
        try:
            # a signal delivered to another thread (XLA's) wakes nobody: its handler runs when this
            # thread is back in Python, which the slices ensure
            while not self.at_once and not ready.wait(WAKE_SECONDS):
                now = time.monotonic()
                paused, woke = now - woke > PAUSED_SECONDS, now
                if paused or time.process_time() - cpu >= stall_cpu_seconds:
                    since, cpu = now, time.process_time()
                elif now - since > stall_seconds:
                    stalled = True
                    break
        finally:
            self._waiting = None
        if not result:  # woken by the second signal, or stalled
            ABANDONED.append(thread)
            if stalled:
                raise StepStalled(
                    f"the step used no CPU for {stall_seconds:.0f} s without returning: "
                    + STALL_HINT
                )
            raise KeyboardInterrupt(self.signal_name)
        if isinstance(result[0], BaseException):
            raise result[0]
        return result[0]


class StopInterrupt(KeyboardInterrupt):
    """What StopRequest raises during set-up. Raised inside code the interpreter runs on its own (a
    garbage collector callback, a finaliser) it cannot propagate: it is then dropped without a
    traceback (the unraisable hook below), the stop stays requested and the job's next check
    (raise_if_stopped, the training loop's first) acts on it."""


@contextmanager
def keeping_lost_interrupts() -> Iterator[None]:
    """While inside: an interrupt the interpreter cannot raise is kept, silently, for the next check
    (a StopInterrupt's stop is already requested on its StopRequest; a SignalInterrupt's signal goes
    to LOST); any other unraisable exception is reported as before. Inside another one (the console
    script's, around a job's) it changes nothing: this is the only unraisable hook."""
    previous = sys.unraisablehook
    if getattr(previous, "keeps_interrupts", False):
        yield
        return

    def unraisable(info: Any) -> None:  # sys.UnraisableHookArgs
        if isinstance(info.exc_value, StopInterrupt):
            # the stop stays requested: the job's next check (raise_if_stopped, the loop's) acts on
            # it
            return
        if isinstance(info.exc_value, SignalInterrupt):
            LOST.append(info.exc_value.args[0] if info.exc_value.args else "SIGINT")
        else:
            previous(info)

    unraisable.keeps_interrupts = True
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        sys.unraisablehook = previous


@contextmanager
def stop_on_signals(on_first: Callable[[str], None] | None = None) -> Iterator[StopRequest]:
    """The job's StopRequest handling SIGINT and SIGTERM while inside, with a signal the interpreter
    dropped before the job (LOST) taken as its first, and interrupts that cannot be raised kept
    (keeping_lost_interrupts). Outside the main thread signals are left alone (the StopRequest still
    takes a sweep's stop)."""
    request = StopRequest(on_first)
    with handling_signals(request, JOB_SIGNALS) as installed:
        if not installed:
            yield request
            return
        lost = take_lost()  # a signal before the job whose interrupt the interpreter dropped
        if lost is not None:
            request.request(lost)
        with keeping_lost_interrupts():
            yield request
