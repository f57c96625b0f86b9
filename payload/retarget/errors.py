"""The retargeting error."""

from __future__ import annotations

from payload.errors import PayloadError


class RetargetError(PayloadError):
    """Invalid retargeting input: a hand file, a configuration, a target or a setting."""
