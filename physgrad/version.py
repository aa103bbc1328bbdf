"""The package version, recorded in every results file."""

__version__ = "0.2.0"
