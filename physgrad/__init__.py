"""physgrad: which gradient should I train my physics-in-the-loop network with?"""

__version__ = "0.1.0"


class UserError(Exception):
    """A mistake in what the user asked for; reported as one line, never as a traceback."""
