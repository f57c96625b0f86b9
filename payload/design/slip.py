"""The unit slips a design value or option is checked for: a value in the small unit (mm,
g) typed where the SI one (m, kg) is meant, about a thousand times too large, and an angle
in degrees typed where radians are meant. The design file's plausibility checks
(:mod:`payload.design.plausible`), its ``[vehicle]`` table
(:func:`payload.design.vehicle.vehicle_from_dict`) and the ``--bay-size`` option
(:func:`payload.design.vehicle.with_bay_size`) say what was meant when they see one."""

from __future__ import annotations

import math
from collections.abc import Sequence

SLIP_FACTOR = 1000.0
"""The unit slip recognised: mm typed as m, g typed as kg."""

_SLIP_TOLERANCE = 10**0.5
"""A value within this factor of 1000 times its default counts as a slip (~316x..3162x)."""

TURN = 2 * math.pi
"""[rad] One turn: no finger joint turns further, so an angle beyond it was typed in
degrees."""


def is_slip(value: float, reference: float | None) -> bool:
    """Whether ``value`` is about :data:`SLIP_FACTOR` times ``reference`` (a value of that
    parameter in its own unit): a small unit typed where the large one is meant."""
    if not reference or not value:
        return False
    return 1 / _SLIP_TOLERANCE <= abs(value / reference) / SLIP_FACTOR <= _SLIP_TOLERANCE


def is_slip_into(value: float, upper: float) -> bool:
    """Whether ``value``, a position beyond ``[0, upper]``, is one inside it typed in the
    small unit: about :data:`SLIP_FACTOR` times ``upper`` at most, and inside once divided
    by it (a position of 0 has no default to compare with)."""
    return is_slip(value, upper) and 0 < value / SLIP_FACTOR <= upper


def in_degrees(angles: Sequence[float]) -> bool:
    """Whether joint angles [rad] were typed in degrees: one of them is beyond a
    :data:`TURN`."""
    return any(abs(a) > TURN for a in angles)


def as_radians(angles: Sequence[float]) -> str:
    """Angles typed in degrees, in radians as a design file spells them: ``[-0.314, 2.231]``
    (three decimals, the packaged design's precision)."""
    return spell([round(math.radians(a), 3) + 0.0 for a in angles])  # + 0.0: no "-0"


def spell(values: Sequence[float]) -> str:
    """Numbers as a design file's array spells them, for a message: ``[0.2, 0.1, 0.1]``."""
    return "[" + ", ".join(f"{v:g}" for v in values) + "]"


__all__ = [
    "SLIP_FACTOR",
    "TURN",
    "as_radians",
    "in_degrees",
    "is_slip",
    "is_slip_into",
    "spell",
]
