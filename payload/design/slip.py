"""The unit slip a design value or option is checked for: a value in the small unit (mm,
g) typed where the SI one (m, kg) is meant, about a thousand times too large. The design
file's plausibility checks (:mod:`payload.design.plausible`) and the ``--bay-size`` option
(:func:`payload.design.vehicle.with_bay_size`) say what was meant when they see one."""

from __future__ import annotations

SLIP_FACTOR = 1000.0
"""The unit slip recognised: mm typed as m, g typed as kg."""

_SLIP_TOLERANCE = 10**0.5
"""A value within this factor of 1000 times its default counts as a slip (~316x..3162x)."""


def is_slip(value: float, reference: float | None) -> bool:
    """Whether ``value`` is about :data:`SLIP_FACTOR` times ``reference`` (a value of that
    parameter in its own unit): a small unit typed where the large one is meant."""
    if not reference or not value:
        return False
    return 1 / _SLIP_TOLERANCE <= abs(value / reference) / SLIP_FACTOR <= _SLIP_TOLERANCE


__all__ = ["SLIP_FACTOR", "is_slip"]
