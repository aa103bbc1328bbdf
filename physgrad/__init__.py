"""physgrad: which gradient should I train my physics-in-the-loop network with?

The package root hands on the Python interface (physgrad.api) and the one error type a caller
catches; see physgrad.api for an example.
"""

from physgrad.api import compare, read_run, read_runs, run
from physgrad.errors import UserError
from physgrad.version import __version__

__all__ = ["UserError", "__version__", "compare", "read_run", "read_runs", "run"]
