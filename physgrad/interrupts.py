"""SIGINT and SIGTERM as an exception, without losing one the interpreter cannot raise.

A signal handler's exception is raised in whatever Python code runs when the signal arrives. If that code is
one the interpreter runs on its own (a garbage-collector callback such as jaxlib's, a finaliser, a weakref
callback), the exception cannot propagate: Python prints "Exception ignored in ..." with a traceback and goes
on as if no signal had come. Here such an interrupt is dropped without a traceback and kept in `LOST`; the
next place that checks (a job's start, the end of a command) acts on it as if it had been raised there.
This module imports nothing heavy: the console script installs it before JAX is loaded.
"""

from __future__ import annotations

import signal
import sys
from contextlib import contextmanager


class SignalInterrupt(KeyboardInterrupt):
    """KeyboardInterrupt raised by a handler here; args[0] is the signal's name ('SIGINT', 'SIGTERM')."""


LOST: list[str] = []  # names of signals whose SignalInterrupt was dropped by the interpreter, oldest first


def raise_interrupt(signum, frame):
    """Signal handler: SIGINT and SIGTERM both as a (Signal)KeyboardInterrupt naming the signal."""
    raise SignalInterrupt(signal.Signals(signum).name)


def take_lost() -> str | None:
    """The first lost signal's name, forgetting all of them (one stop acts on every signal before it)."""
    name = LOST[0] if LOST else None
    LOST.clear()
    return name


@contextmanager
def keeping_lost_interrupts():
    """While inside: a SignalInterrupt the interpreter cannot raise goes to LOST, silently; any other
    unraisable exception is reported as before."""
    previous = sys.unraisablehook

    def unraisable(info):
        if isinstance(info.exc_value, SignalInterrupt):
            name = info.exc_value.args[0] if info.exc_value.args else "SIGINT"
            LOST.append(name)
        else:
            previous(info)

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        sys.unraisablehook = previous
