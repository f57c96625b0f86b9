"""The ``[vehicle]`` table of a design: Astrobee's body and its two lower 1-U payload bays.

The payload frame (REP-103) has its origin at the top centre of the two lower bays;
the bays reach down to the vehicle's bottom face, where they are open, so the
stage lowers the finger array through it. Astrobee's bay size is not public: the
default is the assumption stated in ``docs/sources.md`` (one 1-U bay = 100 x 100 x
100 mm, the two lower bays side by side fore-aft = 200 x 100 x 100 mm), and every
report names it. Astrobee's flight modes (:data:`FLIGHT_MODES`, its motion and
propulsion limits) live here too: the simulator's controller and the teleoperation
base channel read them. A design file may replace it with a ``[vehicle]`` table (the
packaged default design's is the one to start from);
:class:`~payload.design.params.Design` keeps the table as plain
data (``design.vehicle``) and validates it with :func:`vehicle_from_dict`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.design.slip import SLIP_FACTOR, is_slip, spell
from payload.errors import DesignError, as_toml, is_number
from payload.project import SOURCES

BAY_ASSUMPTION = (
    "Astrobee's payload-bay size is not public: one 1-U bay is assumed to be "
    "100 x 100 x 100 mm and the two lower bays, side by side fore-aft, a combined "
    f"200 x 100 x 100 mm envelope ({SOURCES}#vehicle). Replace it with a [vehicle] "
    "table in the design file."
)


@dataclass(frozen=True)
class FlightMode:
    """Astrobee propulsion and motion limits of one flight mode (docs/sources.md#vehicle).

    Attributes:
        name: Mode name.
        force: Maximum body force per axis x, y, z [N].
        torque: Maximum body torque per axis [N m] (about a tenth of the force figures).
        speed: Maximum linear speed [m/s].
        accel: Maximum linear acceleration [m/s^2].
        omega: Maximum angular rate [rad/s].
        alpha: Maximum angular acceleration [rad/s^2].
        impeller_rpm: Impeller speed the force figures belong to.
    """

    name: str
    force: tuple[float, float, float]
    torque: tuple[float, float, float]
    speed: float
    accel: float
    omega: float
    alpha: float
    impeller_rpm: int


FLIGHT_MODES: dict[str, FlightMode] = {
    "nominal": FlightMode(
        "nominal",
        force=(0.680, 0.332, 0.394),
        torque=(0.0680, 0.0332, 0.0394),
        speed=0.20,
        accel=0.0175,
        omega=0.1745,
        alpha=0.1745,
        impeller_rpm=2500,
    ),
    "difficult": FlightMode(
        "difficult",
        force=(0.849, 0.406, 0.486),
        torque=(0.0849, 0.0406, 0.0486),
        speed=0.40,
        accel=0.020,
        omega=0.5236,
        alpha=0.25,
        impeller_rpm=2800,
    ),
}
"""Astrobee flight modes (gnc.config figures via docs/sources.md)."""

DEFAULT_FLIGHT_MODE = "nominal"
"""Default mode. Its 0.20 m/s cap is the paper's base-channel top speed. Carrying a single
CTB (about 26 kg with vehicle and payload, centre of mass about 0.31 m below Astrobee's)
the binding bound is the torque that must balance the cargo's moment, in either mode:
x acceleration 0.0026 m/s^2 nominal against 0.0032 m/s^2 'difficult'. 'Difficult' buys
about 20 % more acceleration and a 0.40 m/s cap the operator interface never asks for, at
the price of louder, hungrier 2800 rpm impellers."""


_KEYS = ("body_size", "body_offset", "bay_size", "mass", "inertia", "assumption")
_UNITS = {
    "body_size": ("m", "mm", "metres"),
    "bay_size": ("m", "mm", "metres"),
    "mass": ("kg", "g", "kg"),
    "inertia": ("kg m^2", "g m^2", "kg m^2"),
}
"""The ``[vehicle]`` sizes checked for a unit slip: their unit, the small unit a slip types
and the design file's unit named in full (``body_offset`` is a coordinate: it may be
zero, and near it a thousandth of its default is no slip)."""
_WALLS = ("-x (aft)", "+x (forward)", "-y (right)", "+y (left)", "-z (bottom face)", "+z (mount)")


class VehicleError(DesignError):
    """The ``[vehicle]`` table (or a bay-size override) is invalid.

    Attributes:
        parameter: Dotted path of the offending parameter, e.g. ``vehicle.bay_size``.
        reason: What is wrong with it.
    """


@dataclass(frozen=True)
class Vehicle:
    """Astrobee's body and the combined envelope of its two lower bays.

    Attributes:
        body_size: Body extents along x, y, z, shape (3,) [m].
        body_offset: x, y of the body centre from the bays' centre, shape (2,) [m].
        bay_size: Combined envelope of the two lower bays along x, y, z, shape (3,) [m].
        mass: Astrobee's mass without payloads, four batteries [kg] (docs/sources.md).
        inertia: Astrobee's principal inertia about its centre of mass, shape (3,)
            [kg m^2] (docs/sources.md).
        assumption: What the bay size rests on; printed in every report.
        source: Where the values came from (file, ``defaults`` or an override).
    """

    body_size: tuple[float, float, float] = (0.32, 0.32, 0.32)
    body_offset: tuple[float, float] = (0.0, 0.0)
    bay_size: tuple[float, float, float] = (0.20, 0.10, 0.10)
    mass: float = 9.5838
    inertia: tuple[float, float, float] = (0.15343, 0.14271, 0.16230)
    assumption: str = BAY_ASSUMPTION
    source: str = f"defaults ({SOURCES}#vehicle)"

    def __post_init__(self) -> None:
        _check_vector("vehicle.body_size", self.body_size, 3, positive=True)
        _check_vector("vehicle.body_offset", self.body_offset, 2, positive=False)
        _check_vector("vehicle.bay_size", self.bay_size, 3, positive=True)
        _check_vector("vehicle.inertia", self.inertia, 3, positive=True, size="moment")
        _check_positive("vehicle.mass", self.mass)
        if not isinstance(self.assumption, str):
            raise VehicleError("vehicle.assumption", f"expected a string, got {self.assumption!r}")
        for i, axis in enumerate("xy"):
            bay_half = self.bay_size[i] / 2
            body_lo = self.body_offset[i] - self.body_size[i] / 2
            body_hi = self.body_offset[i] + self.body_size[i] / 2
            if -bay_half < body_lo - 1e-12 or bay_half > body_hi + 1e-12:
                raise VehicleError(
                    "vehicle.bay_size",
                    f"the bays ({self.bay_size[i] * 1e3:.1f} mm along {axis}) stick out of the "
                    f"body ({body_lo * 1e3:.1f} .. {body_hi * 1e3:.1f} mm along {axis})",
                )
        if self.bay_size[2] >= self.body_size[2]:
            raise VehicleError(
                "vehicle.bay_size",
                f"the bays ({self.bay_size[2] * 1e3:.1f} mm deep) are not shallower than the "
                f"body ({self.body_size[2] * 1e3:.1f} mm high)",
            )

    @property
    def bay_lower(self) -> np.ndarray:
        """Lower corner of the bay envelope in the payload frame, shape (3,) [m]."""
        sx, sy, sz = self.bay_size
        return np.array([-sx / 2, -sy / 2, -sz])

    @property
    def bay_upper(self) -> np.ndarray:
        """Upper corner of the bay envelope (z = 0 is the mount face), shape (3,) [m]."""
        sx, sy, _ = self.bay_size
        return np.array([sx / 2, sy / 2, 0.0])

    @property
    def bottom_z(self) -> float:
        """z of the vehicle's bottom face in the payload frame [m]."""
        return -float(self.bay_size[2])

    @property
    def body_lower(self) -> np.ndarray:
        """Lower corner of the body box in the payload frame, shape (3,) [m]."""
        return np.array(
            [
                self.body_offset[0] - self.body_size[0] / 2,
                self.body_offset[1] - self.body_size[1] / 2,
                self.bottom_z,
            ]
        )

    @property
    def body_upper(self) -> np.ndarray:
        """Upper corner of the body box in the payload frame, shape (3,) [m]."""
        return np.array(
            [
                self.body_offset[0] + self.body_size[0] / 2,
                self.body_offset[1] + self.body_size[1] / 2,
                self.bottom_z + self.body_size[2],
            ]
        )

    @property
    def walls(self) -> tuple[str, ...]:
        """Names of the six bay walls, in the order -x, +x, -y, +y, -z, +z."""
        return _WALLS

    def body_boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The body minus the open bay cavity as five convex boxes (lower, upper corners).

        The boxes are: the body above the bays, then the blocks aft of, forward of,
        right of and left of the bays, down to the bottom face. Boxes of zero
        thickness (bays flush with the body side) are left out.
        """
        blo, bhi = self.body_lower, self.body_upper
        lo, hi = self.bay_lower, self.bay_upper
        boxes = [
            (np.array([blo[0], blo[1], hi[2]]), bhi.copy()),
            (blo.copy(), np.array([lo[0], bhi[1], hi[2]])),
            (np.array([hi[0], blo[1], blo[2]]), np.array([bhi[0], bhi[1], hi[2]])),
            (np.array([lo[0], blo[1], blo[2]]), np.array([hi[0], lo[1], hi[2]])),
            (np.array([lo[0], hi[1], blo[2]]), np.array([hi[0], bhi[1], hi[2]])),
        ]
        return [(a, b) for a, b in boxes if np.all(b - a > 1e-9)]

    def body_solid(self) -> Any:
        """The vehicle body with the open bay cavity, in the payload frame [m]
        (a ``manifold3d.Manifold``)."""
        import manifold3d as m3d

        blo, bhi = self.body_lower, self.body_upper
        lo, hi = self.bay_lower, self.bay_upper
        body = m3d.Manifold.cube(list(bhi - blo)).translate(list(blo))
        cavity_lo = lo - np.array([0.0, 0.0, 0.01])
        cavity = m3d.Manifold.cube(list(hi - cavity_lo)).translate(list(cavity_lo))
        return body - cavity

    def to_dict(self) -> dict[str, Any]:
        """The geometry keys of the ``[vehicle]`` table (SI values), as the envelope
        reports print them; the mass properties are the simulator's (:attr:`mass`,
        :attr:`inertia`)."""
        return {
            "body_size": list(self.body_size),
            "body_offset": list(self.body_offset),
            "bay_size": list(self.bay_size),
            "assumption": self.assumption,
        }


def _check_vector(where: str, value: Any, n: int, positive: bool, size: str = "size") -> None:
    """Refuse ``value`` unless it is ``n`` finite numbers, every one (``size``: what one is,
    in the message) positive where ``positive``."""
    ok = isinstance(value, (list, tuple)) and len(value) == n and all(map(is_number, value))
    if not ok:
        raise VehicleError(where, f"expected {n} numbers, got {as_toml(value)}")
    for v in value:
        if not math.isfinite(v):
            raise VehicleError(where, f"must be finite (got {v})")
        if positive and not v > 0:
            raise VehicleError(where, f"every {size} must be positive (got {v})")


def _check_positive(where: str, value: Any) -> None:
    if not is_number(value):
        raise VehicleError(where, f"expected a number, got {as_toml(value)}")
    if not (math.isfinite(value) and value > 0):
        raise VehicleError(where, f"must be a positive, finite number (got {value})")


def vehicle_from_dict(data: Any, source: str = "<memory>") -> Vehicle:
    """A :class:`Vehicle` from a ``[vehicle]`` table; missing keys take the defaults.

    Raises:
        VehicleError: An unknown key, or a value of the wrong shape or out of range.
    """
    if not isinstance(data, dict):
        raise VehicleError("vehicle", f"expected a table, got {type(data).__name__}")
    for key in data:
        if key not in _KEYS:
            raise VehicleError(
                f"vehicle.{key}", f"unknown key (expected one of: {', '.join(_KEYS)})"
            )
    kwargs: dict[str, Any] = {"source": source}
    for key in ("body_size", "body_offset", "bay_size", "inertia"):
        if key in data:
            n = 2 if key == "body_offset" else 3
            size = "principal moment of inertia" if key == "inertia" else "size"
            _check_vector(f"vehicle.{key}", data[key], n, key != "body_offset", size)
            kwargs[key] = tuple(float(v) for v in data[key])
    if "mass" in data:
        _check_positive("vehicle.mass", data["mass"])
        kwargs["mass"] = float(data["mass"])
    for key in _UNITS:  # first: a slip is named before the bounds it breaks (the bays)
        if key in kwargs:
            _refuse_slip(key, kwargs[key])
    if "assumption" in data:
        kwargs["assumption"] = data["assumption"]
    elif "bay_size" in data:
        kwargs["assumption"] = f"bay size {_mm(kwargs['bay_size'])} given in {source}"
    return Vehicle(**kwargs)


def _refuse_slip(key: str, value: float | tuple[float, ...]) -> None:
    """Refuse a ``[vehicle]`` size about :data:`SLIP_FACTOR` times its default (a body of
    320 m, mm typed for metres), or about a thousandth of it (a conversion made twice),
    saying what was meant: every other bound of the design is taken from these values,
    and a vehicle a thousand times too large admits a finger a thousand times too long."""
    unit, small, named = _UNITS[key]
    default = getattr(Vehicle, key)
    given, packaged = (v if isinstance(v, tuple) else (v,) for v in (value, default))
    vector = isinstance(value, tuple)

    def show(values: list[float] | tuple[float, ...]) -> str:  # the mass as one number
        return spell(values) if vector else f"{values[0]:g}"

    large = [is_slip(v, d) for v, d in zip(given, packaged)]
    if any(large):
        meant = show([v / SLIP_FACTOR if s else v for v, s in zip(given, large)])
        said = f"{show(given)} {small} = {meant}" if all(large) else meant
        raise VehicleError(
            f"vehicle.{key}",
            f"{show(given)} {unit}: did you mean {said}? (about {SLIP_FACTOR:g} times its "
            f"packaged value, {show(packaged)} {unit}, and the design file is in {named})",
        )
    tiny = [is_slip(d, v) for v, d in zip(given, packaged)]
    if any(tiny):
        meant = show([v * SLIP_FACTOR if s else v for v, s in zip(given, tiny)])
        raise VehicleError(
            f"vehicle.{key}",
            f"{show(given)} {unit} is about a thousandth of its packaged value "
            f"({show(packaged)} {unit}): did you mean {meant}? (the design file is in {named})",
        )


def with_bay_size(vehicle: Vehicle, bay_size: Any) -> Vehicle:
    """``vehicle`` with its bay envelope replaced (e.g. from ``--bay-size X Y Z``) [m]."""
    _check_vector("--bay-size", bay_size, 3, positive=True)
    size = tuple(float(v) for v in bay_size)
    try:
        return _bays(vehicle, size)
    except VehicleError as exc:  # named as the user gave it, with a unit slip's hint
        in_m = tuple(v / SLIP_FACTOR for v in size)
        slips = all(is_slip(v, ref) for v, ref in zip(size, vehicle.bay_size))
        if not (slips and _fits(vehicle, in_m)):
            raise VehicleError("--bay-size", exc.reason) from exc
        given, meant = (" ".join(f"{v:g}" for v in s) for s in (size, in_m))
        raise VehicleError(
            "--bay-size", f"{given} m: did you mean {given} mm = --bay-size {meant}? ({exc.reason})"
        ) from exc


def _bays(vehicle: Vehicle, size: tuple[float, ...]) -> Vehicle:
    return dataclasses.replace(
        vehicle,
        bay_size=size,
        assumption=f"bay size {_mm(size)} given on the command line (replaces: "
        f"{vehicle.assumption})",
        source="--bay-size",
    )


def _fits(vehicle: Vehicle, size: tuple[float, ...]) -> bool:
    try:
        _bays(vehicle, size)
    except VehicleError:
        return False
    return True


def _mm(size: tuple[float, ...]) -> str:
    return " x ".join(f"{v * 1e3:.1f}" for v in size) + " mm"


__all__ = [
    "BAY_ASSUMPTION",
    "DEFAULT_FLIGHT_MODE",
    "FLIGHT_MODES",
    "FlightMode",
    "Vehicle",
    "VehicleError",
    "vehicle_from_dict",
    "with_bay_size",
]
