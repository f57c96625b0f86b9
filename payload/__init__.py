"""Workbench for a deployable four-finger dexterous payload for NASA's Astrobee."""

from payload.errors import BuildError, DesignError, PayloadError

__version__ = "0.1.0"

__all__ = ["BuildError", "DesignError", "PayloadError", "__version__"]
