"""Physical plausibility of a design: bounds derived from the design itself.

:func:`check_plausible` runs after the per-field checks of :mod:`payload.design.params`
(types, signs) and refuses, in one line naming the parameter, a design no one could
build:

- nothing longer than the vehicle: every length, offset and size of the payload must be
  shorter than Astrobee's largest body dimension (the ``[vehicle]`` table's, else the
  default 0.32 m cube), and no servo heavier than the vehicle;
- a link must hold its servos: a link whose both ends are servo-driven joints (knuckle,
  proximal, middle) is at least one servo body width long (two bodies, each
  ``servo.width`` across its output axis, cannot stand closer without intersecting);
  the distal link holds the DIP servo's half body and the pad sphere;
- a joint offset lies within the link: ``|offset| <= finger.section.depth``;
- a pad's Young's modulus lies between a gel's and a hard plastic's
  (:data:`PAD_MODULUS_PA`; ``1.0`` typed for 1 MPa: ``did you mean 1 MPa = 1e+06?``);
- no finger joint turns more than a turn: a limit beyond ``2 pi`` was typed in degrees
  (``[-18, 127.8] rad: did you mean [-0.314, 2.231] (degrees given)?``).

A value refused here that is about 1000 times its packaged default names the probable
unit slip (``45 m: did you mean 45 mm = 0.045?``): the design file is SI throughout. A
size (a field that must be positive: a length, a thickness, the servo's mass) about a
thousandth of its packaged default (a servo 0.034 mm long, a conversion to metres made
twice) is refused as the slip the other way, before the bounds that it would break
further on name another parameter for it. A coordinate, an offset or a gap may be zero,
and is not checked so: a thousandth of its default is a value near zero like any other.
The ``[vehicle]`` table's sizes, which the bounds above are taken from, are checked for
both slips first (:func:`payload.design.vehicle.vehicle_from_dict`).
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from collections.abc import Iterator
from typing import Any

from payload.design.slip import SLIP_FACTOR, TURN, as_radians, in_degrees, is_slip, spell
from payload.errors import DesignError
from payload.project import default_design_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

FIT_TOLERANCE = 1e-9
"""[m] How far a sum of lengths may pass the length it must fit in and still fit: the
rounding of decimal lengths in binary (0.054 + 0.05 is 0.10400000000000001), a
nanometre, far below any machining tolerance."""

PAD_MODULUS_PA = (1e3, 1e10)
"""[Pa] The Young's moduli a fingertip pad can have: from a soft gel (kPa) to a hard
plastic (a few GPa), with room either way; a modulus outside was typed in another unit
(``1.0`` for 1 MPa)."""

LENGTH_TABLES: dict[str, tuple[str, ...] | None] = {
    "finger.lengths": None,
    "finger.offsets": None,
    "finger.section": None,
    "finger.pad": ("radius", "thickness"),
    "array": None,
    "rail": ("travel", "length", "width", "height", "carriage_length", "carriage_thickness",
             "drive_radius"),
    "stage": ("travel", "plate_length", "plate_width", "plate_thickness", "guide_radius",
              "guide_length", "guide_x", "stowed_gap", "drive_radius"),
    "mounting": None,
    "servo": ("width", "length", "height"),
    "retarget": ("collision_margin",),
}  # fmt: skip
"""The design's lengths [m]: a table and its length keys (``None``: every number in it)."""


def _get(data: dict[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        data = data[part]
    return data


def lengths(data: dict[str, Any]) -> Iterator[tuple[str, float]]:
    """Every length of a design as plain data: ``(dotted parameter, value [m])``."""
    for table, keys in LENGTH_TABLES.items():
        values = _get(data, table)
        for key in keys or [k for k, v in values.items() if isinstance(v, (int, float))]:
            yield f"{table}.{key}", float(values[key])


def _slip(parameter: str, value: float, unit: str, small_unit: str) -> str:
    """``45 m: did you mean 45 mm = 0.045? (`` when ``value`` is ~1000 times the packaged
    default of ``parameter``, else ``""``."""
    if not is_slip(value, _packaged_default(parameter)):
        return ""
    return f"{value:g} {unit}: did you mean {value:g} {small_unit} = {value / SLIP_FACTOR:g}? ("


def _packaged_default(parameter: str) -> float | None:
    try:
        value = _get(_packaged(), parameter)
    except (KeyError, TypeError):
        return None
    return float(value) if isinstance(value, (int, float)) else None


@functools.cache
def _packaged() -> dict[str, Any]:
    return tomllib.loads(default_design_text())


def _refuse(parameter: str, value: float, unit: str, small_unit: str, reason: str) -> None:
    slip = _slip(parameter, value, unit, small_unit)
    raise DesignError(parameter, f"{slip}{value:g} {unit} {reason}" + (")" if slip else ""))


def _must_be_positive(design: Any, parameter: str) -> bool:
    """Whether the design's field ``parameter`` (dotted) is a size, marked ``positive``
    (a coordinate, an offset or a gap may be zero, and near it a thousandth of its default
    is no slip)."""
    *tables, name = parameter.split(".")
    table = design
    for part in tables:
        table = getattr(table, part, None)
    if not dataclasses.is_dataclass(table):
        return False
    found = {f.name: f for f in dataclasses.fields(table)}.get(name)
    return bool(found is not None and found.metadata.get("positive"))


def _refuse_small_slip(parameter: str, value: float) -> None:
    """Refuse ``value`` when its packaged default is about :data:`SLIP_FACTOR` times it (a
    length in metres divided again, a mass in kg)."""
    default = _packaged_default(parameter)
    if not is_slip(default or 0.0, value):
        return
    mass = parameter == "servo.mass"
    shown, packaged = (
        (f"{value * 1e3:.3g} g", f"{default * 1e3:g} g") if mass else (_mm(value), _mm(default))
    )
    raise DesignError(
        parameter,
        f"{value:g} {'kg' if mass else 'm'} = {shown} is about a thousandth of its packaged "
        f"value ({packaged}): did you mean {value * SLIP_FACTOR:g}? (the design file is in "
        f"{'kg' if mass else 'metres'})",
    )


def _mm(length: float) -> str:
    """A length [m] in mm for a message: one decimal, or three significant digits where
    that would print a length that is not zero as 0.0 (a value 1000 times too small)."""
    mm = length * 1e3
    return f"{mm:.1f} mm" if mm == 0.0 or abs(mm) >= 0.05 else f"{mm:.3g} mm"


def check_plausible(design: Any, data: dict[str, Any]) -> None:
    """Refuse a design outside the physical bounds above.

    Args:
        design: The :class:`~payload.design.params.Design` (its per-field checks passed).
        data: The same design as plain data (``design_to_dict``).

    Raises:
        DesignError: The first implausible parameter, in one line.
    """
    from payload.design.vehicle import Vehicle, vehicle_from_dict

    vehicle = vehicle_from_dict(design.vehicle) if design.vehicle else Vehicle()
    longest = max(vehicle.body_size)
    for parameter, value in lengths(data):
        if abs(value) >= longest:
            _refuse(
                parameter,
                value,
                "m",
                "mm",
                f"is longer than the vehicle: Astrobee's body is {longest * 1e3:.0f} mm at "
                "its largest, and the design file is in metres",
            )
    s = design.servo
    if s.mass >= vehicle.mass:
        _refuse(
            "servo.mass",
            s.mass,
            "kg",
            "g",
            f"is heavier than the vehicle ({vehicle.mass:g} kg), and the design file is in kg",
        )
    for parameter, value in [*lengths(data), ("servo.mass", s.mass)]:
        if _must_be_positive(design, parameter):  # a size; not a coordinate, offset or gap
            _refuse_small_slip(parameter, value)
    f = design.finger
    for link in ("knuckle", "proximal", "middle"):
        length = getattr(f.lengths, link)
        if length < s.width:
            raise DesignError(
                f"finger.lengths.{link}",
                f"{_mm(length)} cannot hold the servos at its two joints (two "
                f"{s.model} bodies, {s.width * 1e3:.1f} mm across their output axes, need "
                f"at least {s.width * 1e3:.1f} mm between the axes)",
            )
    least = s.width / 2 + f.pad.radius
    if f.lengths.distal < least - FIT_TOLERANCE:  # an exact fit holds them
        raise DesignError(
            "finger.lengths.distal",
            f"{_mm(f.lengths.distal)} cannot hold the DIP servo's half body "
            f"({s.width / 2 * 1e3:.1f} mm) and the pad (radius {f.pad.radius * 1e3:.1f} mm): "
            f"at least {least * 1e3:.1f} mm",
        )
    for joint in ("mcp_abd", "pip", "dip", "tip"):
        offset = getattr(f.offsets, joint)
        if abs(offset) > f.section.depth:
            raise DesignError(
                f"finger.offsets.{joint}",
                f"{_mm(offset)} puts the joint outside its link (finger.section.depth "
                f"{f.section.depth * 1e3:.1f} mm)",
            )
    modulus = f.pad.modulus
    if not PAD_MODULUS_PA[0] <= modulus <= PAD_MODULUS_PA[1]:
        soft = modulus < PAD_MODULUS_PA[0]
        raise DesignError(
            "finger.pad.modulus",
            f"{modulus:g} Pa is {'softer' if soft else 'stiffer'} than any pad material "
            f"({PAD_MODULUS_PA[0]:g} to {PAD_MODULUS_PA[1]:g} Pa, a gel to a hard plastic)"
            + (
                f": did you mean {modulus:g} MPa = {modulus * 1e6:g}?"
                if soft and PAD_MODULUS_PA[0] <= modulus * 1e6 <= PAD_MODULUS_PA[1]
                else ""
            )
            + " (the design file is in Pa)",
        )
    for joint in dataclasses.fields(f.limits):
        typed = (getattr(f.limits, joint.name).lower, getattr(f.limits, joint.name).upper)
        if in_degrees(typed):
            raise DesignError(
                f"finger.limits.{joint.name}",
                f"{spell(typed)} rad: did you mean {as_radians(typed)} (degrees "
                f"given)? (no finger joint turns more than a turn, {TURN:.3f} rad, and the "
                "design file is in radians)",
            )


__all__ = ["FIT_TOLERANCE", "LENGTH_TABLES", "PAD_MODULUS_PA", "check_plausible", "lengths"]
