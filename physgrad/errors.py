"""physgrad's error types, at the bottom of the package: any module may raise them, none imports
upward for them.

A UserError is the user's mistake (reported as one line, never a traceback); the others are what the
file system did (a results file that could not be written, a folder another process holds, a disk
without locks).
"""


class UserError(Exception):
    """A mistake in what the user asked for; reported as one line, never as a traceback."""


class ResultsWriteError(OSError):
    """results.h5 could not be written (disk full, quota, permissions): one line that names the
    file."""


class FolderOwned(RuntimeError):
    """Another live process owns the job (or sweep) folder."""


class LockingUnsupported(OSError):
    """The file system of a folder supports neither flock nor POSIX locks (a Lustre mount without
    flock, an NFS mount without a lock daemon): one line with the real reason and what to do."""
