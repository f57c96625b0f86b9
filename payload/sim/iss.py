"""The ISS interior along the cargo route: Kibo, the hatch vestibule and Node 2.

World frame (REP-103 style, ISS analysis axes turned to y-left): origin at the centre of
Node 2 (Harmony), x forward along Node 2's axis, y to port, z to zenith. Kibo berths on
Node 2's port side, so Kibo's long axis runs along +y.

Every interior is an axis-aligned box of open space bounded by rack faces (thin collision
boxes) with handrails standing off them; the hatch vestibule is a square tube joining
Node 2's port rack face to Kibo's forward rack face. Figures come from
``docs/sources.md``; where a figure is not published the default is marked ASSUMPTION.
This module holds the layout (volumes, route) and the MJCF bodies of the walls.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import mujoco
import numpy as np

from payload.sim.errors import SimError

# Collision bits. The payload MJCF uses contype 1 (fingers) and 2 (structure), conaffinity 1.
_ISS_CONTYPE, _ISS_CONAFFINITY = 4, 1 | 2
_ASTROBEE_CONTYPE, _ASTROBEE_CONAFFINITY = 8, 4  # walls only: the payload sits inside it
_CTB_CONTYPE, _CTB_CONAFFINITY = 16, 1 | 2 | 4 | 8


class IssModule(str, enum.Enum):
    """Where a point is: one of the modules along the cargo route."""

    KIBO = "kibo"
    VESTIBULE = "vestibule"
    NODE2 = "node2"

    @property
    def title(self) -> str:
        """The module's name in words, for labels and reports."""
        return _MODULE_TITLES[self]


_MODULE_TITLES = {
    IssModule.KIBO: "Kibo (JEM)",
    IssModule.VESTIBULE: "hatch vestibule",
    IssModule.NODE2: "Node 2 (Harmony)",
}


class Zone(NamedTuple):
    """An axis-aligned box of open interior, world frame [m]."""

    module: IssModule
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, point: Sequence[float]) -> bool:
        """True when ``point`` (3,) [m] lies inside the box (boundary included)."""
        return self.holds(float(point[0]), float(point[1]), float(point[2]))

    def holds(self, x: float, y: float, z: float) -> bool:
        """:meth:`contains` of the point (x, y, z) [m], its coordinates already floats."""
        lo, hi = self.lo, self.hi
        return lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]

    @property
    def centre(self) -> np.ndarray:
        """Centre of the box, shape (3,) [m]."""
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2.0

    @property
    def size(self) -> np.ndarray:
        """Extent along x, y, z, shape (3,) [m]."""
        return np.asarray(self.hi) - np.asarray(self.lo)


@dataclass(frozen=True)
class IssLayout:
    """Dimensions of the route's three volumes (world frame, metres).

    Attributes:
        kibo_width: Kibo open interior across its axis, along x (docs/sources.md: 1.7 m).
        kibo_height: Kibo open interior, along z (docs/sources.md: 2.0 m).
        kibo_length: Kibo open interior along its axis, y (docs/sources.md: 7.3 m).
        node2_length: Node 2 open interior along its axis, x. ASSUMPTION: 6.0 m of the
            7.2 m module (end cones excluded).
        node2_width: Node 2 open interior between rack faces, along y and z. ASSUMPTION:
            2.0 m, Kibo's figure (rack depth is common to the pressurised modules).
        module_diameter: Outer diameter of Node 2 (docs/sources.md: 4.4 m); sets how far the port
            rack face stands from the hull.
        hatch: Edge of the square common hatch (docs/sources.md: 1.3 m).
        vestibule_length: Length of the berthing vestibule (docs/sources.md: 0.4 m).
        kibo_endcone: Kibo's forward bulkhead to its first rack face. ASSUMPTION: 0.6 m.
        hatch_x: x of the Kibo hatch centre on Node 2. ASSUMPTION: 1.5 m (radial ports
            toward the forward end of Node 2).
        wall: Thickness of the rack-face collision slabs.
        handrail_section: Square section of a handrail.
        handrail_length: Length of a handrail.
        handrail_standoff: Rack face to handrail centre line.
        handrail_pitch: Spacing of handrails along a module (about one rack bay).
        route_height: z of the Astrobee centre along the route: puts the vehicle, payload
            and CTB stack (+0.16 m to about -0.65 m) in the middle of the 1.3 m hatch.
        route_start_depth: How far into Kibo (from its forward rack face) the route starts.
        route_aft: Distance travelled aft along Node 2 after the turn.
    """

    kibo_width: float = 1.7
    kibo_height: float = 2.0
    kibo_length: float = 7.3
    node2_length: float = 6.0
    node2_width: float = 2.0
    module_diameter: float = 4.4
    hatch: float = 1.3
    vestibule_length: float = 0.4
    kibo_endcone: float = 0.6
    hatch_x: float = 1.5
    wall: float = 0.1
    handrail_section: float = 0.025
    handrail_length: float = 0.5
    handrail_standoff: float = 0.06
    handrail_pitch: float = 1.2
    route_height: float = 0.25
    route_start_depth: float = 3.8
    route_aft: float = 2.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if name == "hatch_x":
                continue
            if not (math.isfinite(value) and value > 0.0):
                raise SimError(f"IssLayout.{name}: must be a positive number, got {value!r}")
        half = self.hatch / 2.0
        if half > min(self.kibo_width, self.kibo_height, self.node2_width) / 2.0:
            raise SimError("IssLayout.hatch: the hatch is larger than a module cross-section")
        if abs(self.hatch_x) + half > self.node2_length / 2.0:
            raise SimError("IssLayout.hatch_x: the hatch does not fit on Node 2's port face")
        if not self.route_start_depth < self.kibo_length:
            raise SimError("IssLayout.route_start_depth: the start lies beyond Kibo's end")
        if self.route_aft > self.node2_length / 2.0 + self.hatch_x:
            raise SimError("IssLayout.route_aft: the route ends beyond Node 2's aft end")

    # -- volumes -------------------------------------------------------------------------
    @property
    def node2(self) -> Zone:
        """Node 2 open interior."""
        hx, hw = self.node2_length / 2.0, self.node2_width / 2.0
        return Zone(IssModule.NODE2, (-hx, -hw, -hw), (hx, hw, hw))

    @property
    def vestibule(self) -> Zone:
        """The passage from Node 2's port rack face through the hatch and vestibule to Kibo."""
        half = self.hatch / 2.0
        y0 = self.node2_width / 2.0
        y1 = self.module_diameter / 2.0 + self.vestibule_length + self.kibo_endcone
        return Zone(
            IssModule.VESTIBULE, (self.hatch_x - half, y0, -half), (self.hatch_x + half, y1, half)
        )

    @property
    def kibo(self) -> Zone:
        """Kibo (JEM pressurised module) open interior between its racks."""
        y0 = self.vestibule.hi[1]
        hw, hh = self.kibo_width / 2.0, self.kibo_height / 2.0
        return Zone(
            IssModule.KIBO,
            (self.hatch_x - hw, y0, -hh),
            (self.hatch_x + hw, y0 + self.kibo_length, hh),
        )

    def zones(self) -> tuple[Zone, Zone, Zone]:
        """Kibo, vestibule, Node 2, in route order."""
        return (self.kibo, self.vestibule, self.node2)

    @functools.cached_property
    def _lookup_order(self) -> tuple[Zone, Zone, Zone]:
        """The zones as :meth:`module_at` tries them (vestibule first); computed once,
        the layout being frozen."""
        kibo, vest, node2 = self.zones()
        return (vest, kibo, node2)

    def module_at(self, point: Sequence[float]) -> IssModule | None:
        """The module containing ``point`` (3,) [m, world frame], or None outside all three.

        The vestibule wins on its shared faces with the modules (a point on the hatch
        plane counts as in the hatch).
        """
        x, y, z = (point.tolist() if isinstance(point, np.ndarray) else point)[:3]
        x, y, z = float(x), float(y), float(z)  # Zone.contains's numbers, converted once
        for zone in self._lookup_order:
            if zone.holds(x, y, z):
                return zone.module
        return None

    # -- route ----------------------------------------------------------------------------
    def route(self) -> np.ndarray:
        """Waypoints of the cargo route, shape (3, 3) [m]: start in Kibo, the turn on
        Node 2's axis in front of the hatch, the end aft in Node 2."""
        z = self.route_height
        start = (self.hatch_x, self.kibo.lo[1] + self.route_start_depth, z)
        turn = (self.hatch_x, 0.0, z)
        end = (self.hatch_x - self.route_aft, 0.0, z)
        return np.array([start, turn, end], dtype=float)

    def start(self) -> np.ndarray:
        """Where the vehicle starts, the route's first waypoint, shape (3,) [m]."""
        return self.route()[0]

    def route_length(self) -> float:
        """Length of the route polyline [m]."""
        return float(np.sum(np.linalg.norm(np.diff(self.route(), axis=0), axis=1)))

    def start_yaw(self) -> float:
        """Heading of the first route leg [rad] (Astrobee's x along the route)."""
        d = np.diff(self.route()[:2], axis=0)[0]
        return float(math.atan2(d[1], d[0]))


# -- building ---------------------------------------------------------------------------------
def _box(body: mujoco.MjsBody, default: mujoco.MjsDefault, name: str, lo, hi) -> None:
    """A box ``lo``..``hi`` [m, world frame] in a static body at the world origin."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    body.add_geom(
        default=default,
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=((lo + hi) / 2.0).tolist(),
        size=((hi - lo) / 2.0).tolist(),
    )


def _face_slabs(zone: Zone, axis: int, side: int, wall: float, hole: Zone | None):
    """Slabs closing one face of ``zone`` (axis 0..2, side 0 = lo, 1 = hi), minus a hole."""
    lo = np.array(zone.lo, float) - wall
    hi = np.array(zone.hi, float) + wall
    if side == 0:
        lo[axis], hi[axis] = zone.lo[axis] - wall, zone.lo[axis]
    else:
        lo[axis], hi[axis] = zone.hi[axis], zone.hi[axis] + wall
    if hole is None:
        return [(lo, hi)]
    u, v = [a for a in range(3) if a != axis]
    slabs = []
    # strips below and above the hole along u (full v extent), then left/right along v
    for a, b in ((lo[u], hole.lo[u]), (hole.hi[u], hi[u])):
        if b - a > 1e-9:
            s_lo, s_hi = lo.copy(), hi.copy()
            s_lo[u], s_hi[u] = a, b
            slabs.append((s_lo, s_hi))
    for a, b in ((lo[v], hole.lo[v]), (hole.hi[v], hi[v])):
        if b - a > 1e-9:
            s_lo, s_hi = lo.copy(), hi.copy()
            s_lo[u], s_hi[u] = hole.lo[u], hole.hi[u]
            s_lo[v], s_hi[v] = a, b
            slabs.append((s_lo, s_hi))
    return slabs


def _handrails(zone: Zone, along: int, layout: IssLayout, hole: Zone | None):
    """Handrails on the four long faces of ``zone``, running along axis ``along``."""
    rails = []
    half_len = layout.handrail_length / 2.0
    half_sec = layout.handrail_section / 2.0
    n = max(1, int(zone.size[along] // layout.handrail_pitch))
    first = zone.lo[along] + (zone.size[along] - (n - 1) * layout.handrail_pitch) / 2.0
    for axis in (a for a in range(3) if a != along):
        other = 3 - along - axis
        for side in (0, 1):
            face = zone.lo[axis] if side == 0 else zone.hi[axis]
            offset = layout.handrail_standoff if side == 0 else -layout.handrail_standoff
            for k in range(n):
                c = np.zeros(3)
                c[along] = first + k * layout.handrail_pitch
                c[axis] = face + offset
                c[other] = zone.centre[other]
                half = np.full(3, half_sec)
                half[along] = half_len
                if hole is not None and axis == 1 and side == 1:
                    # the port face: no handrail across the hatch opening
                    margin = 0.05
                    if (
                        c[along] + half_len > hole.lo[along] - margin
                        and c[along] - half_len < hole.hi[along] + margin
                    ):
                        continue
                rails.append((axis, side, c - half, c + half))
    return rails


def _add_iss(spec: mujoco.MjSpec, layout: IssLayout) -> None:
    wall = spec.add_default("iss_wall", spec.default)
    wall.geom.contype, wall.geom.conaffinity = _ISS_CONTYPE, _ISS_CONAFFINITY
    wall.geom.rgba = [0.82, 0.82, 0.78, 0.25]
    wall.geom.group = 1
    wall.geom.density = 0.0  # static: mass would only pollute whole-world mass totals
    rail = spec.add_default("iss_handrail", spec.default)
    rail.geom.contype, rail.geom.conaffinity = _ISS_CONTYPE, _ISS_CONAFFINITY
    rail.geom.rgba = [0.9, 0.75, 0.2, 1.0]
    rail.geom.group = 1
    rail.geom.density = 0.0
    world = spec.worldbody
    kibo, vest, node2 = layout.zones()
    t = layout.wall
    # One static body per module face (rack-face slabs and their handrails): each gets its
    # own bounding box in the broad phase, so a vehicle in mid-module is tested against no
    # ISS geom at all (a single world body would cost about a third of the step time).
    faces: dict[str, mujoco.MjsBody] = {}

    def face(name: str) -> mujoco.MjsBody:
        if name not in faces:
            faces[name] = world.add_body(name=name)
        return faces[name]

    openings = {("kibo", 1, 0): vest, ("node2", 1, 1): vest}  # the hatch passage
    for zone, key in ((kibo, "kibo"), (node2, "node2")):
        for axis in range(3):
            for side in (0, 1):
                body = face(f"{key}_{'xyz'[axis]}{side}")
                hole = openings.get((key, axis, side))
                for i, (lo, hi) in enumerate(_face_slabs(zone, axis, side, t, hole)):
                    _box(body, wall, f"{key}_wall_{'xyz'[axis]}{side}_{i}", lo, hi)
    # Vestibule: a square tube along y (faces x and z only), ending flush with the rack
    # faces of the two modules (whose slabs frame the opening).
    for axis in (0, 2):
        for side in (0, 1):
            (lo, hi) = _face_slabs(vest, axis, side, t, None)[0]
            lo[1], hi[1] = vest.lo[1], vest.hi[1]
            name = f"vestibule_{'xyz'[axis]}{side}"
            _box(face(name), wall, f"vestibule_wall_{'xyz'[axis]}{side}", lo, hi)
    for zone, key, along, hole in ((kibo, "kibo", 1, None), (node2, "node2", 0, vest)):
        for i, (axis, side, lo, hi) in enumerate(_handrails(zone, along, layout, hole)):
            _box(face(f"{key}_{'xyz'[axis]}{side}"), rail, f"{key}_handrail_{i}", lo, hi)
    world.add_light(pos=[layout.hatch_x, 0.0, 0.9], dir=[0, 0, -1])
    world.add_light(pos=[layout.hatch_x, layout.kibo.centre[1], 0.9], dir=[0, 0, -1])
