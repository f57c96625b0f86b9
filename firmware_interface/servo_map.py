"""The servo map: which servo drives which joint, and how joint values become ticks.

A map file (TOML, default: ``servos.toml`` shipped with this package) lists one servo
per actuated joint of the design (the 16 finger joints, ``rail`` and ``stage``) with its
bus ID, direction and zero offset. Loading validates it against the design: every joint
mapped exactly once, IDs unique, limits inside the design's. Rotary joints convert as
``ticks = zero + direction * q / RAD_PER_TICK``; the rail and the stage are rack and
pinion drives, so their servo angle is ``x * gear / drive_radius`` with the design's
``rail.drive_radius`` and ``stage.drive_radius``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from firmware_interface.control_table import MODEL_NUMBER, RAD_PER_TICK
from payload.design.params import Design, load_design, posture_values
from payload.design.tree import ALL_JOINTS
from payload.errors import PayloadError, closest, not_text
from payload.schema import PayloadCommand

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

LINEAR_JOINTS = ("rail", "stage")
_SERVO_KEYS = {"id", "joint", "direction", "zero", "gear", "lower", "upper"}
_TOP_KEYS = {"baud", "return_delay", "watchdog_ms", "on_fault", "servo"}
ON_FAULT = ("hold", "torque_off")


class ServoMapError(PayloadError):
    """A servo map that does not fit the design; the message names the entry."""


@dataclass(frozen=True)
class ServoSpec:
    """One servo of the map.

    Attributes:
        id: Bus ID.
        joint: Joint name.
        direction: +1 or -1.
        zero: Ticks at joint value 0.
        lower: Lower joint limit [rad or m].
        upper: Upper joint limit [rad or m].
        units_per_tick: Joint units per encoder tick [rad or m].
    """

    id: int
    joint: str
    direction: int
    zero: int
    lower: float
    upper: float
    units_per_tick: float

    def to_ticks(self, value: float) -> int:
        """Goal ticks for a joint value, clamped to the limits first."""
        v = min(max(float(value), self.lower), self.upper)
        return round(self.zero + self.direction * v / self.units_per_tick)

    def from_ticks(self, ticks: int | float) -> float:
        """Joint value of a present position [rad or m]."""
        return self.direction * (float(ticks) - self.zero) * self.units_per_tick


@dataclass(frozen=True)
class ServoMap:
    """The validated map, servos in the design's joint order (17 manipulation, then stage).

    Attributes:
        servos: One spec per joint, ordered as ``ALL_JOINTS``.
        baud: Bus baud rate [bit/s].
        return_delay: Return Delay Time register value (unit 2 us).
        watchdog_ms: Bus Watchdog period [ms] (0 disables).
        on_fault: ``hold`` or ``torque_off``.
        current_limit_ma: Goal Current cap [mA] (the design's ``servo.current_limit``).
        source: Where the map came from.
        model_number: The model number every servo must report (the XC330-M288-T's:
            the control table the driver writes is that servo's).
    """

    servos: tuple[ServoSpec, ...]
    baud: int
    return_delay: int
    watchdog_ms: int
    on_fault: str
    current_limit_ma: int
    source: str
    model_number: int = MODEL_NUMBER

    @property
    def ids(self) -> list[int]:
        return [s.id for s in self.servos]

    def by_id(self, dxl_id: int) -> ServoSpec:
        for s in self.servos:
            if s.id == dxl_id:
                return s
        raise ServoMapError(f"{self.source}: no servo with ID {dxl_id}")

    def joint_of(self, dxl_id: int) -> str:
        return self.by_id(dxl_id).joint

    def command_ticks(self, command: PayloadCommand) -> list[int]:
        """Goal ticks of all servos (map order) for a command, limits applied first."""
        values = np.append(command.q, command.deploy)
        return [s.to_ticks(v) for s, v in zip(self.servos, values)]

    def joint_values(self, ticks: list[int] | np.ndarray) -> np.ndarray:
        """Joint values (map order) of present positions, shape (18,)."""
        return np.array([s.from_ticks(t) for s, t in zip(self.servos, ticks)])


def _design_limits(design: Design, joint: str) -> tuple[float, float]:
    if joint == "rail":
        return 0.0, design.rail.travel
    if joint == "stage":
        return 0.0, design.stage.travel
    lim = design.finger.limit(joint.split("_", 1)[1])
    return lim.lower, lim.upper


def _units_per_tick(design: Design, joint: str, gear: float) -> float:
    if joint == "rail":
        return RAD_PER_TICK * design.rail.drive_radius / gear
    if joint == "stage":
        return RAD_PER_TICK * design.stage.drive_radius / gear
    return RAD_PER_TICK


def _number(entry: dict[str, Any], key: str, where: str, default: Any = None) -> float:
    v = entry.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ServoMapError(f"{where}.{key}: expected a number, got {v!r}")
    return float(v)


def _servo(entry: Any, k: int, design: Design, source: str) -> ServoSpec:
    where = f"{source}: [[servo]] table {k + 1}"  # counted as a reader counts, from 1
    if not isinstance(entry, dict):
        raise ServoMapError(f"{where}: expected a table")
    unknown = set(entry) - _SERVO_KEYS
    if unknown:
        raise ServoMapError(f"{where}: unknown key(s) {sorted(unknown)}")
    joint = entry.get("joint")
    if joint not in ALL_JOINTS:
        close = closest(str(joint), ALL_JOINTS)
        hint = f" (did you mean {close!r}?)" if close else ""
        raise ServoMapError(f"{where}.joint: {joint!r} is not a joint of the design{hint}")
    where = f"{source}: servo {joint}"
    dxl_id = entry.get("id")
    if isinstance(dxl_id, bool) or not isinstance(dxl_id, int) or not 0 <= dxl_id <= 252:
        raise ServoMapError(f"{where}.id: expected an integer 0..252, got {dxl_id!r}")
    direction = entry.get("direction", 1)
    if direction not in (1, -1) or isinstance(direction, bool):
        raise ServoMapError(f"{where}.direction: expected 1 or -1, got {direction!r}")
    zero = entry.get("zero")
    if isinstance(zero, bool) or not isinstance(zero, int) or abs(zero) > 1_048_575:
        raise ServoMapError(f"{where}.zero: expected an integer tick count, got {zero!r}")
    if "gear" in entry and joint not in LINEAR_JOINTS:
        raise ServoMapError(f"{where}.gear: only the rail and the stage have a gear")
    gear = _number(entry, "gear", where, 1.0)
    if gear <= 0:
        raise ServoMapError(f"{where}.gear: must be positive, got {gear}")
    d_lo, d_hi = _design_limits(design, joint)
    lo = _number(entry, "lower", where, d_lo)
    hi = _number(entry, "upper", where, d_hi)
    if not d_lo <= lo < hi <= d_hi:
        raise ServoMapError(
            f"{where}: limits [{lo}, {hi}] are not inside the design's [{d_lo}, {d_hi}]"
        )
    return ServoSpec(dxl_id, joint, direction, zero, lo, hi, _units_per_tick(design, joint, gear))


def servo_map_from_dict(
    data: dict[str, Any], design: Design | None = None, source: str = "<memory>"
) -> ServoMap:
    """Validate a parsed map against ``design`` (default: the project's design).

    Raises:
        ServoMapError: Naming the first problem (unknown joint, joint mapped twice or
            not at all, duplicate ID, limits outside the design's, bad settings).
    """
    design = design if design is not None else load_design()
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ServoMapError(f"{source}: unknown key(s) {sorted(unknown)}")
    entries = data.get("servo")
    if not isinstance(entries, list):
        raise ServoMapError(f"{source}: expected [[servo]] tables")
    specs = [_servo(e, k, design, source) for k, e in enumerate(entries)]
    by_joint: dict[str, ServoSpec] = {}
    ids: dict[int, str] = {}
    for s in specs:
        if s.joint in by_joint:
            raise ServoMapError(f"{source}: joint {s.joint} is mapped twice")
        if s.id in ids:
            raise ServoMapError(f"{source}: ID {s.id} is used by {ids[s.id]} and {s.joint}")
        by_joint[s.joint], ids[s.id] = s, s.joint
    missing = [j for j in ALL_JOINTS if j not in by_joint]
    if missing:
        raise ServoMapError(f"{source}: joint(s) not mapped: {', '.join(missing)}")
    baud = data.get("baud", 4_000_000)
    if baud not in (57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000):
        raise ServoMapError(f"{source}: baud {baud!r} is not a Dynamixel baud rate")
    delay = data.get("return_delay", 0)
    if not isinstance(delay, int) or not 0 <= delay <= 254:
        raise ServoMapError(f"{source}: return_delay must be 0..254, got {delay!r}")
    wd = data.get("watchdog_ms", 100)
    if not isinstance(wd, int) or not 0 <= wd <= 2540 or wd % 20:
        raise ServoMapError(f"{source}: watchdog_ms must be a multiple of 20 up to 2540")
    on_fault = data.get("on_fault", "hold")
    if on_fault not in ON_FAULT:
        raise ServoMapError(f"{source}: on_fault must be 'hold' or 'torque_off'")
    cap = round(design.servo.current_limit * 1000)
    return ServoMap(tuple(by_joint[j] for j in ALL_JOINTS), baud, delay, wd, on_fault, cap, source)


def default_map_text() -> str:
    """The default map shipped with the package."""
    return resources.files("firmware_interface").joinpath("servos.toml").read_text("utf-8")


def load_servo_map(path: str | Path | None = None, design: Design | None = None) -> ServoMap:
    """Load and validate a map file (default: the packaged map for our design).

    Raises:
        ServoMapError: Unreadable file, invalid TOML, or a map that does not fit.
    """
    if path is None:
        text, source = default_map_text(), "servos.toml (default)"
    else:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise ServoMapError(f"{source}: cannot read ({exc.strerror})") from exc
        except UnicodeDecodeError as exc:
            raise ServoMapError(f"{source}: {not_text(exc, 'TOML')}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ServoMapError(f"{source}: not valid TOML: {exc}") from exc
    return servo_map_from_dict(data, design, source)


def travel_ticks(smap: ServoMap, design: Design | None = None) -> dict[int, tuple[int, int]]:
    """The rail's and the stage's travel ends (their hard stops), ID -> (low, high) ticks."""
    design = design if design is not None else load_design()
    out = {}
    for s in smap.servos:
        if s.joint in LINEAR_JOINTS:
            lo, hi = _design_limits(design, s.joint)
            ends = [round(s.zero + s.direction * v / s.units_per_tick) for v in (lo, hi)]
            out[s.id] = (min(ends), max(ends))
    return out


def home_values(design: Design | None = None) -> dict[str, float]:
    """The design's ``home`` posture (where every trial starts), joint -> value."""
    return posture_values(design if design is not None else load_design(), "home")


def posture_command(design: Design | None = None, name: str = "home") -> PayloadCommand:
    """The command of a design posture (:func:`posture_values`; joints in ``ALL_JOINTS``
    order)."""
    values = posture_values(design if design is not None else load_design(), name)
    v = np.array([values[j] for j in ALL_JOINTS])
    return PayloadCommand(v[:-1], float(v[-1]), 0.0)


def home_command(design: Design | None = None) -> PayloadCommand:
    """The command of the design's ``home`` posture (joints in ``ALL_JOINTS`` order)."""
    return posture_command(design, "home")


def posture_ticks(
    smap: ServoMap, design: Design | None = None, name: str = "home"
) -> dict[int, int]:
    """Present positions of a design posture (:func:`posture_values`), ID -> ticks."""
    values = posture_values(design if design is not None else load_design(), name)
    return {s.id: s.to_ticks(values[s.joint]) for s in smap.servos}


def home_ticks(smap: ServoMap, design: Design | None = None) -> dict[int, int]:
    """Present positions of the design's ``home`` posture, ID -> ticks."""
    return posture_ticks(smap, design, "home")
