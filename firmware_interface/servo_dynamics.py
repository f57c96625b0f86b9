"""The emulated servo's output dynamics: the design's servo model, integrated per control period.

Operating Mode 5 as :mod:`payload.design.servo` states it, on one output shaft:

    e = goal - pos [ticks];  de = e - e_prev (per control period)
    i = clamp((P / 128) e + (I / 65536) sum(e) + (D / 16) de, +-Goal Current) [mA]
    i also bounded by the supply: (-V - kt w) / R <= i <= (V - kt w) / R
    J dw/dt = kt i - b w - c sign(w)       (J = armature + load inertia)

integrated with a fixed step of one control period (semi-implicit Euler, the viscous
term implicit, Coulomb friction as a stick-slip impulse: the shaft stops when the
friction can absorb the step's impulse). A blocked shaft does not move; its current is
the clamped command. The plant constants come from the design (:func:`plant_for`) or,
for a servo holding parameters other than the design's (``payload hw emulate
--servo-params FILE``), from a file (:func:`load_plant_overrides`).
"""

from __future__ import annotations

import functools
import json
import math
import sys
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

from payload.design.params import Design, design_from_dict
from payload.design.servo import (
    CURRENT_UNIT_A,
    KPD_DIV,
    KPI_DIV,
    KPP_DIV,
    TICKS_PER_RAD,
    scale_of,
)
from payload.errors import PayloadError
from payload.project import default_design_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass(frozen=True)
class Plant:
    """One servo's output shaft (SI, output side).

    Attributes:
        inertia: Armature plus the load's inertia at the shaft [kg m^2].
        viscous: Viscous friction [N m s/rad].
        coulomb: Coulomb friction [N m].
        kt: Output torque per ampere [N m/A].
        resistance: Winding resistance [ohm].
        voltage: Supply voltage [V].
        control_period: The firmware's control period [s].
    """

    inertia: float
    viscous: float
    coulomb: float
    kt: float
    resistance: float
    voltage: float
    control_period: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


PLANT_KEYS = tuple(f.name for f in fields(Plant))
_MAY_BE_ZERO = ("viscous", "coulomb")


def plant_for(design: Design, kind: str, load: float) -> Plant:
    """The design's plant for a servo of joint kind ``kind`` moving ``load`` (joint units:
    kg m^2 for a hinge, kg for the rail and stage, reflected through the pinion)."""
    s = design.servo
    r = scale_of(design, kind)
    return Plant(
        inertia=s.armature + load * r**2,
        viscous=s.viscous,
        coulomb=s.coulomb,
        kt=s.kt,
        resistance=s.resistance,
        voltage=s.supply_voltage,
        control_period=s.control_period,
    )


def design_plants(design: Design, kinds: dict[int, str]) -> dict[int, Plant]:
    """Per servo ID (``kinds``: ID -> joint kind): the design's plant with its load."""
    from payload.design.tree import build_tree, load_inertia

    tree = build_tree(design)
    loads = {k: load_inertia(tree, k) for k in set(kinds.values())}
    return {i: plant_for(design, k, loads[k]) for i, k in kinds.items()}


def load_plant_overrides(path: str | Path) -> dict[str, dict[str, float]]:
    """A servo-parameters file: JSON ``{"<id or joint kind or *>": {plant key: value}}``.

    Raises:
        PayloadError: Unreadable file, unknown key, a negative friction or another value
            not positive (one line).
    """
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise PayloadError(f"{p}: cannot read servo parameters ({exc})") from None
    if not isinstance(data, dict):
        raise PayloadError(f"{p}: expected a JSON object of servo parameters")
    for who, values in data.items():
        if not isinstance(values, dict):
            raise PayloadError(f"{p}: {who}: expected an object of plant values")
        for key, v in values.items():
            if key not in PLANT_KEYS:
                raise PayloadError(f"{p}: {who}.{key}: unknown (expected one of {PLANT_KEYS})")
            least = 0.0 if key in _MAY_BE_ZERO else math.ulp(0.0)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= least:
                what = ">= 0" if key in _MAY_BE_ZERO else "> 0"
                raise PayloadError(f"{p}: {who}.{key}: expected a number {what}, got {v!r}")
    return data


OVERRIDE_FACTOR = 10.0
"""How far an emulated servo's override may lie from the design's value, either way: a
real servo's identified constants differ from its datasheet's by tens of percent, so a
value ten times off is a unit slip (mA for A, mm for m), and it drives the emulated shaft
past what its registers hold."""


def apply_overrides(
    plants: dict[int, Plant],
    kinds: dict[int, str],
    overrides: dict[str, dict[str, float]],
    source: str = "servo parameters",
) -> dict[int, Plant]:
    """Plants with overrides applied: ``*`` first, then the joint kind, then the ID.

    Raises:
        PayloadError: An override more than :data:`OVERRIDE_FACTOR` times above or below
            the design's value of a servo it applies to (one line naming ``source``).
    """
    out = {}
    for i, plant in plants.items():
        design = plant  # each override is weighed against the design's value
        for key in ("*", kinds.get(i, ""), str(i)):
            if key not in overrides:
                continue
            for name, value in overrides[key].items():
                base = getattr(design, name)
                if base > 0 and not (
                    (value >= base / OVERRIDE_FACTOR or name in _MAY_BE_ZERO)
                    and value <= base * OVERRIDE_FACTOR
                ):
                    raise PayloadError(
                        f"{source}: {key}.{name}: {value:g} is {value / base:.3g} times the "
                        f"design's {base:g} for servo {i} (more than {OVERRIDE_FACTOR:g} "
                        "times off: the file holds SI values, e.g. kt in N m/A)"
                    )
            plant = replace(plant, **{k: float(v) for k, v in overrides[key].items()})
        out[i] = plant
    return out


class ServoDynamics:
    """The output shaft's state and its integration (module docstring).

    Args:
        plant: The shaft's constants.
        position: Initial position [ticks].
    """

    def __init__(self, plant: Plant, position: float) -> None:
        self.plant = plant
        self.pos = float(position)  # [ticks]
        self.vel = 0.0  # [rad/s]
        self.current = 0.0  # [mA], the clamped command
        self.demand = 0.0  # [mA], before the Goal Current clamp
        self._prev_err: float | None = None
        self._integral = 0.0
        self._pending = 0.0

    def reset(self) -> None:
        """Torque off or REBOOT: the controller's memory and the motion stop."""
        self.vel, self.current, self.demand = 0.0, 0.0, 0.0
        self._prev_err, self._integral, self._pending = None, 0.0, 0.0

    def advance(
        self, dt: float, goal: float, gains: tuple[int, int, int], cap_ma: float, blocked: bool
    ) -> None:
        """Integrate ``dt`` seconds toward ``goal`` [ticks] with Position (P, I, D) and the
        Goal Current cap [mA]; a ``blocked`` shaft stays where it is."""
        period = self.plant.control_period
        self._pending += dt
        n = int(self._pending / period + 1e-9)
        self._pending -= n * period
        for _ in range(n):
            rest = self.vel == 0.0 and self._prev_err == goal - self.pos
            self._step(goal, gains, cap_ma, blocked)
            if rest and self.vel == 0.0 and gains[1] == 0:
                break  # a fixed point: held by friction (or blocked), every later step alike

    def _step(self, goal: float, gains: tuple[int, int, int], cap_ma: float, blocked: bool) -> None:
        pl = self.plant
        p, i_gain, d = gains
        err = goal - self.pos
        d_err = 0.0 if self._prev_err is None else err - self._prev_err
        self._prev_err = err
        self._integral += err
        demand = p / KPP_DIV * err + i_gain / KPI_DIV * self._integral + d / KPD_DIV * d_err
        self.demand = demand
        amps = max(-cap_ma, min(cap_ma, demand)) * CURRENT_UNIT_A
        hi = (pl.voltage - pl.kt * self.vel) / pl.resistance
        lo = (-pl.voltage - pl.kt * self.vel) / pl.resistance
        amps = max(lo, min(hi, amps))
        self.current = amps / CURRENT_UNIT_A
        if blocked:
            self.vel = 0.0
            return
        h = pl.control_period
        momentum = pl.inertia * self.vel + h * pl.kt * amps
        if abs(momentum) <= h * pl.coulomb:
            self.vel = 0.0  # friction holds the shaft
        else:
            momentum -= math.copysign(h * pl.coulomb, momentum)
            self.vel = momentum / (pl.inertia + h * pl.viscous)
        self.pos += self.vel * h * TICKS_PER_RAD


def plants_from_spec(spec: dict[str, Any]) -> dict[int, Plant]:
    """Plants from a bus spec's ``plants`` entry (ID -> plant dict), empty if absent."""
    return {int(k): Plant(**v) for k, v in spec.get("plants", {}).items()}


@functools.cache
def default_plant() -> Plant:
    """An unloaded finger servo of the packaged default design (a servo on the bench)."""
    data = tomllib.loads(default_design_text())
    return plant_for(design_from_dict(data, "<packaged default>"), "finger", 0.0)


__all__ = [
    "PLANT_KEYS",
    "Plant",
    "ServoDynamics",
    "apply_overrides",
    "default_plant",
    "design_plants",
    "load_plant_overrides",
    "plant_for",
    "plants_from_spec",
]
