"""The review's error (kept apart so the command line loads without meshcat)."""

from __future__ import annotations

from payload.errors import PayloadError


class ReviewError(PayloadError):
    """A review cannot be built: a missing or stale model, an unreadable or foreign recording."""


__all__ = ["ReviewError"]
