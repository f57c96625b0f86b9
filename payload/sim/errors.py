"""The simulator's error types."""

from __future__ import annotations

from payload.errors import PayloadError


class SimError(PayloadError):
    """The simulated world cannot be built or driven as asked."""


class PropulsionError(PayloadError):
    """Bad propulsion parameters or wrench requests."""
