"""The design's parameter types: one frozen dataclass per table of ``cad/design.toml``, the
cross-field checks (:meth:`Design.validate`) and the way back to plain data
(:func:`design_to_dict`).

Every field is SI (m, rad, kg, s, N, A); a field's metadata says what it must be
(``positive``, ``nonneg``, ``optional``) for the strict loader
(:mod:`payload.design.params`, which re-exports every name here).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any

from payload.design.plausible import FIT_TOLERANCE, check_plausible
from payload.design.slip import SLIP_FACTOR, as_radians, in_degrees, is_slip_into, spell
from payload.errors import DesignError

FINGERS: tuple[str, ...] = ("A", "B", "C", "D")
"""Finger names. A and C are fixed to the stage; B and D ride the rail carriage."""

FINGER_JOINTS: tuple[str, ...] = ("mcp_flex", "mcp_abd", "pip", "dip")
"""Per-finger joints in LEAP's order (abduction after flexion)."""

FINGER_LINKS: tuple[str, ...] = ("knuckle", "proximal", "middle", "distal")
"""Per-finger links, base to tip (URDF link ``<finger>_<link>``)."""

SIDE_OF: dict[str, int] = {"A": 1, "B": 1, "C": 2, "D": 2}


def _pos(doc: str = "") -> Any:
    return field(metadata={"positive": True, "doc": doc})


def _nonneg(doc: str = "", default: float | None = None) -> Any:
    if default is None:
        return field(metadata={"nonneg": True, "doc": doc})
    # an optional key: design files written before it existed keep their meaning
    return field(default=default, metadata={"nonneg": True, "doc": doc, "optional": True})


def _any(doc: str = "") -> Any:
    return field(metadata={"doc": doc})


@dataclass(frozen=True)
class Range:
    """A closed interval ``[lower, upper]`` (loaded from a two-element array)."""

    lower: float
    upper: float

    @property
    def span(self) -> float:
        return self.upper - self.lower

    def contains(self, value: float) -> bool:
        return self.lower <= value <= self.upper


@dataclass(frozen=True)
class FingerLengths:
    """Distances between consecutive joint origins along the straight finger [m]."""

    knuckle: float = _pos("MCP flexion -> MCP abduction")
    proximal: float = _pos("MCP abduction -> PIP")
    middle: float = _pos("PIP -> DIP")
    distal: float = _pos("DIP -> fingertip point (pad centre)")


@dataclass(frozen=True)
class FingerOffsets:
    """Offsets of each joint origin toward the closing direction [m] (may be negative)."""

    mcp_abd: float = _any()
    pip: float = _any()
    dip: float = _any()
    tip: float = _any()


@dataclass(frozen=True)
class FingerLimits:
    """Joint limits [rad], positive flexion closes toward the opposite side."""

    mcp_flex: Range
    mcp_abd: Range
    pip: Range
    dip: Range


@dataclass(frozen=True)
class Section:
    """Rectangular cross-section of the finger links [m]."""

    width: float = _pos("along the flexion axis (the rail axis)")
    depth: float = _pos("along the closing direction")


@dataclass(frozen=True)
class Pad:
    radius: float = _pos("fingertip pad sphere radius [m]")
    friction: float = _pos("sliding friction coefficient of the pad")
    thickness: float = _pos("silicone skin thickness over the pad sphere [m]")
    modulus: float = _pos("Young's modulus of the pad silicone [Pa]")
    load: float = _pos("pad force the contact stiffness is linearised at [N]")
    damping_ratio: float = _pos("damping ratio of the pad contact (>= 1)")


@dataclass(frozen=True)
class Finger:
    lengths: FingerLengths
    offsets: FingerOffsets
    limits: FingerLimits
    section: Section
    pad: Pad

    def limit(self, joint: str) -> Range:
        return getattr(self.limits, joint)


@dataclass(frozen=True)
class Array:
    """Layout of the 2x2 finger array on the stage (payload frame, x = rail axis)."""

    side_gap: float = _pos("y distance between the MCP flexion axes of side 1 and side 2")
    ac_stagger: float = _any("x offset of finger C from finger A (and D from B)")
    pair_spacing: float = _pos("x distance from finger A to finger B with the rail at 0")
    a_x: float = _any("x of finger A's MCP flexion axis")
    finger_drop: float = _pos("distance from the stage plate underside down to the MCP axes")
    bracket_thickness: float = _pos(
        "thickness of the finger brackets along y (not used by the geometry yet: the "
        "brackets are solid blocks sized by finger.section)"
    )


@dataclass(frozen=True)
class Rail:
    travel: float = _pos("carriage travel [m]")
    length: float = _pos("rail length [m]")
    width: float = _pos("rail width [m]")
    height: float = _pos("rail height [m]")
    carriage_length: float = _pos("carriage length along the rail [m]")
    carriage_thickness: float = _pos("carriage plate thickness [m]")
    drive_radius: float = _pos("pinion pitch radius of the rail drive [m]")


@dataclass(frozen=True)
class Stage:
    travel: float = _pos("vertical deployment travel [m]")
    plate_length: float = _pos("stage plate length along x [m]")
    plate_width: float = _pos("stage plate width along y [m]")
    plate_thickness: float = _pos("stage plate thickness [m]")
    guide_radius: float = _pos("radius of the two vertical guide columns [m]")
    guide_length: float = _pos("length of the guide columns below the mounting plate [m]")
    guide_x: float = _pos("|x| of the guide columns [m]")
    stowed_gap: float = _nonneg("gap between mounting plate and stage plate when stowed [m]")
    drive_radius: float = _pos("pinion pitch radius of the rack drive [m]")


@dataclass(frozen=True)
class Mounting:
    plate_length: float = _pos("[m]")
    plate_width: float = _pos("[m]")
    plate_thickness: float = _pos("[m]")


@dataclass(frozen=True)
class ServoGains:
    """The firmware's Position P, I, D gains (control-table values) per joint kind."""

    finger: tuple[float, float, float]
    abduction: tuple[float, float, float]
    rail: tuple[float, float, float]
    stage: tuple[float, float, float]


@dataclass(frozen=True)
class Servo:
    """A Dynamixel servo: body, datasheet limits, identified physics and the controller it runs.

    The physical constants are output-side (after the gearbox), as the datasheet and
    Rhoban's BAM identification give them; :mod:`payload.design.servo` derives every
    consumer's parameters from them (docs/servo.md).
    """

    model: str = _any()
    width: float = _pos("body size across the output axis [m]")
    length: float = _pos("body length [m]")
    height: float = _pos("body height [m]")
    mass: float = _pos("[kg]")
    stall_torque: float = _pos("[N m]")
    stall_current: float = _pos("[A]")
    current_limit: float = _pos("current cap used on hardware [A]")
    no_load_speed: float = _pos("[rad/s]")
    gear_ratio: float = _pos("gearbox reduction (motor turns per output turn)")
    supply_voltage: float = _pos("supply voltage [V]")
    kt: float = _pos("output torque per ampere [N m/A] (gear losses included)")
    resistance: float = _pos("winding resistance [ohm]")
    armature: float = _pos("output-side apparent rotor and gearbox inertia [kg m^2]")
    coulomb: float = _nonneg("output-side Coulomb friction [N m]")
    viscous: float = _nonneg("output-side viscous friction [N m s/rad]")
    control_period: float = _pos("time base of the firmware's derivative term [s]")
    operating_mode: float = _any("Operating Mode the driver sets (5: current-based position)")
    gains: ServoGains

    @property
    def torque_limit(self) -> float:
        """Torque available at the hardware current cap [N m]: ``kt x Goal Current``."""
        return self.kt * self.current_limit


@dataclass(frozen=True)
class Materials:
    """Densities [kg/m^3]."""

    structure: float = _pos("mounting plate, stage, rail, carriage")
    finger: float = _pos("printed finger links (effective, with infill)")
    pad: float = _pos("fingertip pads")


@dataclass(frozen=True)
class RetargetParams:
    """What the retargeter (``payload.retarget``) takes from the design."""

    collision_margin: float = _pos(
        "least distance [m] a retargeting command keeps between links of different fingers, "
        "and between a finger and the structure (stage, carriage, base), except between "
        "the two pad links of one pair"
    )
    pad_link: str = field(
        default="distal",
        metadata={
            "doc": "the finger link (knuckle, proximal, middle or distal) whose collision "
            "geometry carries the fingertip pad: the two pad links of one pair may close on "
            "each other and on what they hold (no margin between them)",
            "optional": True,
        },
    )


@dataclass(frozen=True)
class Posture:
    """A payload configuration: the same finger joints for every finger."""

    finger: tuple[float, float, float, float]
    rail: float = _any()
    stage: float = _any()


@dataclass(frozen=True)
class Pinch:
    """The grasp pre-shape: the finger posture a pinch closes from."""

    finger: tuple[float, float, float, float]


@dataclass(frozen=True)
class Design:
    """The whole payload design."""

    finger: Finger
    array: Array
    rail: Rail
    stage: Stage
    mounting: Mounting
    servo: Servo
    materials: Materials
    stowed: Posture
    home: Posture
    retarget: RetargetParams
    pinch: Pinch = field(default=None, metadata={"optional": True})  # type: ignore[assignment]
    vehicle: dict[str, Any] = field(
        default_factory=dict, hash=False, metadata={"optional_table": True}
    )
    source: str = field(default="<memory>", compare=False, metadata={"internal": True})

    def validate(self) -> Design:
        """Cross-field checks; returns self or raises :class:`DesignError`."""
        f, s, r, st = self.finger, self.servo, self.rail, self.stage
        check_plausible(
            self, design_to_dict(self)
        )  # first: a unit slip is named before what it breaks
        _validate_servo(s)
        if f.pad.damping_ratio < 1.0:
            raise DesignError(
                "finger.pad.damping_ratio",
                f"{f.pad.damping_ratio} would let the pad contact bounce; must be >= 1",
            )
        if f.pad.thickness >= f.pad.radius:
            raise DesignError(
                "finger.pad.thickness",
                f"{f.pad.thickness} m skin is not thinner than the {f.pad.radius} m pad",
            )
        for j in FINGER_JOINTS:
            lim = f.limit(j)
            if not lim.lower < lim.upper:
                raise DesignError(
                    f"finger.limits.{j}",
                    f"lower limit {lim.lower} is not below upper limit {lim.upper}",
                )
        if r.travel + r.carriage_length > r.length + FIT_TOLERANCE:  # an exact fit is one
            raise DesignError(
                "rail.travel",
                f"travel {r.travel} m plus carriage length {r.carriage_length} m is longer "
                f"than the rail ({r.length} m)",
            )
        if s.width > f.section.width:
            raise DesignError(
                "servo.width",
                f"servo {s.model} ({s.width * 1e3:.1f} mm) does not fit the finger link width "
                f"finger.section.width ({f.section.width * 1e3:.1f} mm)",
            )
        if s.height > f.section.depth:
            raise DesignError(
                "servo.height",
                f"servo {s.model} ({s.height * 1e3:.1f} mm) does not fit the finger link depth "
                f"finger.section.depth ({f.section.depth * 1e3:.1f} mm)",
            )
        if s.length > f.lengths.knuckle:
            raise DesignError(
                "servo.length",
                f"the MCP abduction servo ({s.length * 1e3:.1f} mm) does not fit its link "
                f"finger.lengths.knuckle ({f.lengths.knuckle * 1e3:.1f} mm)",
            )
        if st.travel > st.guide_length:
            raise DesignError(
                "stage.travel",
                f"travel {st.travel} m is longer than the guide columns ({st.guide_length} m)",
            )
        if st.guide_x + st.guide_radius > self.mounting.plate_length / 2 + FIT_TOLERANCE:
            raise DesignError("stage.guide_x", "guide columns stand outside the mounting plate")
        if abs(self.array.ac_stagger) < f.section.width:
            raise DesignError(
                "array.ac_stagger",
                f"|{self.array.ac_stagger}| m is less than the finger width "
                f"{f.section.width} m: opposing fingers would collide when stowed",
            )
        if self.vehicle:
            # Astrobee's body and bays: validated where they are modelled
            from payload.design.vehicle import vehicle_from_dict

            vehicle_from_dict(self.vehicle, source=self.source)
        if self.retarget.pad_link not in FINGER_LINKS:
            raise DesignError(
                "retarget.pad_link",
                f"expected one of {', '.join(FINGER_LINKS)}, got {self.retarget.pad_link!r}",
            )
        _check_finger_posture("pinch", self.pinch.finger, f)
        for name, posture in (("stowed", self.stowed), ("home", self.home)):
            _check_finger_posture(name, posture.finger, f)
            for axis, travel in (("rail", r.travel), ("stage", st.travel)):
                _check_position(f"{name}.{axis}", getattr(posture, axis), travel)
        return self


def _check_finger_posture(name: str, angles: tuple[float, ...], f: Finger) -> None:
    """Refuse a posture's finger joint outside its limits; one typed in degrees says what
    was meant (``[95, 0, 80.1, 103.4] rad: did you mean [1.658, 0, 1.398, 1.805] (degrees
    given)?``)."""
    for j, v in zip(FINGER_JOINTS, angles):
        lim = f.limit(j)
        if lim.contains(v):
            continue
        outside = f"{j} = {v} rad is outside finger.limits.{j} [{lim.lower}, {lim.upper}]"
        if in_degrees(angles):
            raise DesignError(
                f"{name}.finger",
                f"{spell(angles)} rad: did you mean {as_radians(angles)} (degrees given)? "
                f"({outside}, and the design file is in radians)",
            )
        raise DesignError(f"{name}.finger", outside)


def _check_position(parameter: str, value: float, travel: float) -> None:
    """Refuse a posture's rail or stage position outside ``[0, travel]``; one typed in mm
    says what was meant (``25 m: did you mean 25 mm = 0.025?``)."""
    if 0.0 <= value <= travel:
        return
    outside = f"{value} m is outside [0, {travel}]"
    if is_slip_into(value, travel):
        raise DesignError(
            parameter,
            f"{value:g} m: did you mean {value:g} mm = {value / SLIP_FACTOR:g}? ({outside}, "
            "and the design file is in metres)",
        )
    raise DesignError(parameter, outside)


GAIN_MAX = 16383
"""Largest Position P/I/D gain the control table takes (e-Manual, addresses 80-84)."""


def _validate_servo(s: Servo) -> None:
    if s.operating_mode != 5:
        raise DesignError(
            "servo.operating_mode",
            f"{s.operating_mode}: only 5 (current-based position) is modelled",
        )
    for kind in ("finger", "abduction", "rail", "stage"):
        gains = getattr(s.gains, kind)
        for name, g in zip("PID", gains):
            if g != int(g) or not 0 <= g <= GAIN_MAX:
                raise DesignError(
                    f"servo.gains.{kind}",
                    f"Position {name} gain {g} is not an integer in [0, {GAIN_MAX}]",
                )
        if gains[1] != 0:
            raise DesignError(
                f"servo.gains.{kind}",
                f"Position I gain {gains[1]}: the simulator's position actuator has no "
                "integral term; use 0",
            )
    if s.current_limit > s.stall_current:
        raise DesignError(
            "servo.current_limit",
            f"{s.current_limit} A is above the stall current {s.stall_current} A",
        )


def design_to_dict(design: Design) -> dict[str, Any]:
    """The design as plain data (the inverse of
    :func:`~payload.design.params.design_from_dict`)."""

    def conv(obj: Any) -> Any:
        if isinstance(obj, Range):
            return [obj.lower, obj.upper]
        if dataclasses.is_dataclass(obj):
            return {
                f.name: conv(getattr(obj, f.name))
                for f in dataclasses.fields(obj)
                if not f.metadata.get("internal")
            }
        if isinstance(obj, tuple):
            return [conv(x) for x in obj]
        if isinstance(obj, dict):
            return copy.deepcopy(obj)
        return obj

    return conv(design)


__all__ = [
    "FINGERS",
    "FINGER_JOINTS",
    "FINGER_LINKS",
    "FIT_TOLERANCE",
    "GAIN_MAX",
    "SIDE_OF",
    "Array",
    "Design",
    "Finger",
    "FingerLengths",
    "FingerLimits",
    "FingerOffsets",
    "Materials",
    "Mounting",
    "Pad",
    "Pinch",
    "Posture",
    "Rail",
    "Range",
    "RetargetParams",
    "Section",
    "Servo",
    "ServoGains",
    "Stage",
    "design_to_dict",
]
