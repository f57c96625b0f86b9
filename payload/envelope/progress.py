"""Progress callbacks of the long envelope and reach computations."""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[str, float], None]
"""``progress(stage, fraction)`` callback for long work."""


def quiet(stage: str, fraction: float) -> None:
    """The progress callback that reports nothing."""
    return None


__all__ = [
    "Progress",
    "quiet",
]
