"""physgrad's error types, at the bottom of the package: any module may raise them, none imports
upward for them.

A UserError is the user's mistake (reported as one line, never a traceback); the others are what the
file system did (a results file that could not be written, a folder another process holds, a disk
without locks).
"""

import re


def innermost_cause(error: BaseException) -> str:
    """An error in one line: its first line, or, where its text carries a Python traceback (an
    exception raised in a host callback of a compiled step: a solver's step limit, an equinox or
    checkify error, as XLA reports it), the exception line that ends it. Equinox ends its runtime
    errors with advice between lines of dashes: the cause is the text above them."""
    text = str(error).strip()
    text = re.split(r"^\s*-{4,}\s*$", text, maxsplit=1, flags=re.MULTILINE)[0].strip() or text
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if "Traceback (most recent call last)" in text and lines:
        return lines[-1]
    first = lines[0] if lines else ""
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


def scene_failed(error: BaseException) -> bool:
    """Whether an error raised by a compiled step came from the scene's own code called back on
    the host (a solver that gave up, an equinox runtime check): XLA reports such an exception as a
    callback error carrying its traceback."""
    first = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return "callback error" in first.lower()


class UserError(Exception):
    """A mistake in what the user asked for; reported as one line, never as a traceback."""


class LauncherRefused(BaseException):
    """A sweep's launcher could not start its jobs (sbatch missing or refusing the array): the
    message in one line. A BaseException, as KeyboardInterrupt is, so that Hydra's multirun, which
    prints any Exception from its launcher with a traceback, lets it through to the command line
    (physgrad.cli: `physgrad: error: ...`, exit code 2)."""


class ResultsWriteError(OSError):
    """results.h5 could not be written (disk full, quota, permissions): one line that names the
    file."""


class FolderOwned(RuntimeError):
    """Another live process owns the job (or sweep) folder."""


class LockingUnsupported(OSError):
    """The file system of a folder supports neither flock nor POSIX locks (a Lustre mount without
    flock, an NFS mount without a lock daemon): one line with the real reason and what to do."""
