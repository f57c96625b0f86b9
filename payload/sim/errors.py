"""The simulator's error type."""

from __future__ import annotations

from payload.errors import PayloadError


class SimError(PayloadError):
    """The simulated world cannot be built or driven as asked."""
