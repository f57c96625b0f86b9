"""Solids of every payload part, built with manifold3d in their link frames.

Each link is a list of :class:`Part` (a watertight solid and its density); the
visual mesh of a link is the union of its parts. Parts of one link never
overlap, so their mass properties add up exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import manifold3d as m3d
import numpy as np

from payload.design.mass_cache import cached_mass_props
from payload.design.params import FINGERS, SIDE_OF, Design
from payload.errors import BuildError

if TYPE_CHECKING:
    import trimesh

SEGMENTS = 32
"""Circular segments of cylinders and spheres (deterministic tessellation)."""


@dataclass(frozen=True)
class Part:
    """A solid of one material.

    Attributes:
        name: Human-readable name, e.g. ``A_bracket``.
        solid: The watertight solid in its link's frame [m].
        density: [kg/m^3].
    """

    name: str
    solid: m3d.Manifold
    density: float


@dataclass(frozen=True)
class MassProps:
    """Mass properties of a rigid body in its link frame.

    Attributes:
        mass: [kg].
        com: Centre of mass, shape (3,) [m].
        inertia: Inertia about the centre of mass, link-frame axes, shape (3, 3) [kg m^2].
    """

    mass: float
    com: np.ndarray
    inertia: np.ndarray

    @staticmethod
    def combine(items: list[MassProps]) -> MassProps:
        """Sum of rigid bodies expressed in the same frame (parallel-axis theorem)."""
        mass = sum(p.mass for p in items)
        if mass <= 0:
            return MassProps(0.0, np.zeros(3), np.zeros((3, 3)))
        com = sum(p.mass * p.com for p in items) / mass
        inertia = np.zeros((3, 3))
        for p in items:
            r = p.com - com
            inertia += p.inertia + p.mass * (np.dot(r, r) * np.eye(3) - np.outer(r, r))
        return MassProps(mass, com, 0.5 * (inertia + inertia.T))


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> m3d.Manifold:
    """Axis-aligned box from corner ``lo`` to corner ``hi`` [m]."""
    size = [h - lo_ for lo_, h in zip(lo, hi)]
    if min(size) <= 0:
        raise BuildError(f"degenerate box {lo} -> {hi}")
    return m3d.Manifold.cube(size).translate(list(lo))


def cylinder(axis: str, radius: float, length: float, center: tuple[float, float, float]):
    """Cylinder of ``length`` along ``axis`` ('x', 'y' or 'z'), centred at ``center``."""
    c = m3d.Manifold.cylinder(length, radius, radius, SEGMENTS, True)
    if axis == "x":
        c = c.rotate([0.0, 90.0, 0.0])
    elif axis == "y":
        c = c.rotate([90.0, 0.0, 0.0])
    return c.translate(list(center))


def sphere(radius: float, center: tuple[float, float, float]) -> m3d.Manifold:
    return m3d.Manifold.sphere(radius, SEGMENTS).translate(list(center))


def to_trimesh(solid: m3d.Manifold) -> trimesh.Trimesh:
    """Convert a manifold3d solid to a trimesh mesh (checked watertight)."""
    import trimesh  # about 0.6 s of imports, needed only where meshes are built

    mesh = solid.to_mesh()
    tm = trimesh.Trimesh(
        vertices=np.asarray(mesh.vert_properties)[:, :3].astype(np.float64),
        faces=np.asarray(mesh.tri_verts).astype(np.int64),
        process=False,
    )
    return tm


def servo_props(design: Design, center: np.ndarray, long_axis: int) -> MassProps:
    """Mass properties of a servo body as a uniform box with its length along ``long_axis``."""
    s = design.servo
    dims = np.array([s.width, s.height, s.length])  # x, y, z for long_axis == 2
    if long_axis == 1:
        dims = np.array([s.width, s.length, s.height])
    elif long_axis == 0:
        dims = np.array([s.length, s.height, s.width])
    a, b, c = dims
    inertia = s.mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    return MassProps(s.mass, np.asarray(center, dtype=float), inertia)


def part_props(part: Part) -> MassProps:
    """Mass properties of one part (trimesh's, kept in the disk cache by the mesh's hash)."""

    def compute() -> tuple[float, np.ndarray, np.ndarray]:
        tm = to_trimesh(part.solid)
        vol = float(tm.volume)
        if vol <= 0:
            raise BuildError(f"part {part.name} has non-positive volume")
        mass = vol * part.density
        return mass, np.asarray(tm.center_mass), np.asarray(tm.moment_inertia) * part.density

    mass, com, inertia = cached_mass_props(part.solid, part.density, compute)
    return MassProps(mass, com, inertia)


@dataclass(frozen=True)
class LinkBody:
    """Geometry and inertia sources of one link.

    Attributes:
        mesh: Name of the shared visual mesh (``cad/meshes/<mesh>.stl``).
        parts: The solids making up the link.
        servos: Servo bodies mounted in the link.
        boxes: Collision boxes ``(center, half_sizes)`` in the link frame.
        cylinders: Collision cylinders ``(center, axis, radius, half_length)``.
        spheres: Collision spheres ``(center, radius)`` (fingertip pads).
    """

    mesh: str
    parts: tuple[Part, ...]
    servos: tuple[MassProps, ...]
    boxes: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...] = ()
    cylinders: tuple[tuple[tuple[float, ...], str, float, float], ...] = ()
    spheres: tuple[tuple[tuple[float, ...], float], ...] = ()

    def solid(self) -> m3d.Manifold:
        out = self.parts[0].solid
        for p in self.parts[1:]:
            out = out + p.solid
        return out

    def mass_props(self) -> MassProps:
        return MassProps.combine([part_props(p) for p in self.parts] + list(self.servos))


def _box_collision(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return (tuple((lo + hi) / 2), tuple((hi - lo) / 2))


def finger_bodies(design: Design) -> dict[str, LinkBody]:
    """The four finger link bodies, shared by all fingers (finger frame: x flexion axis,
    y closing direction, z up; the straight finger points down)."""
    f = design.finger
    w, d = f.section.width, f.section.depth
    L = f.lengths
    o = f.offsets
    rho = design.materials.finger
    bodies: dict[str, LinkBody] = {}

    def segment(length: float, joint_axis: str, name: str) -> Part:
        body = box((-w / 2, -d / 2, -length), (w / 2, d / 2, 0.0))
        if joint_axis == "x":
            knuckle = cylinder("x", d / 2, w, (0.0, 0.0, 0.0))
        else:
            knuckle = cylinder("y", w / 2, d, (0.0, 0.0, 0.0))
        return Part(name, body + knuckle, rho)

    knuckle = segment(L.knuckle, "x", "knuckle")
    bodies["finger_knuckle"] = LinkBody(
        "finger_knuckle",
        (knuckle,),
        (servo_props(design, np.array([0.0, 0.0, -L.knuckle / 2]), 2),),
        boxes=(_box_collision((-w / 2, -d / 2, -L.knuckle), (w / 2, d / 2, 0.0)),),
    )
    proximal = segment(L.proximal, "y", "proximal")
    bodies["finger_proximal"] = LinkBody(
        "finger_proximal",
        (proximal,),
        (servo_props(design, np.array([0.0, 0.0, -L.proximal / 2]), 2),),
        boxes=(_box_collision((-w / 2, -d / 2, -L.proximal), (w / 2, d / 2, 0.0)),),
    )
    middle = segment(L.middle, "x", "middle")
    bodies["finger_middle"] = LinkBody(
        "finger_middle",
        (middle,),
        (servo_props(design, np.array([0.0, 0.0, -L.middle / 2]), 2),),
        boxes=(_box_collision((-w / 2, -d / 2, -L.middle), (w / 2, d / 2, 0.0)),),
    )
    r = f.pad.radius
    tip = (0.0, o.tip, -L.distal)
    distal_body = box((-w / 2, -d / 2, -L.distal), (w / 2, d / 2, 0.0)) + cylinder(
        "x", d / 2, w, (0.0, 0.0, 0.0)
    )
    pad = sphere(r, tip) - distal_body
    bodies["finger_distal"] = LinkBody(
        "finger_distal",
        (Part("distal", distal_body, rho), Part("pad", pad, design.materials.pad)),
        (),
        boxes=(_box_collision((-w / 2, -d / 2, -L.distal), (w / 2, d / 2, 0.0)),),
        spheres=((tip, r),),
    )
    return bodies


def finger_mount(design: Design, finger: str) -> tuple[float, float, float]:
    """Position of a finger's MCP flexion axis point in its parent link frame [m]."""
    a = design.array
    if finger in ("A", "C"):
        x = a.a_x + (a.ac_stagger if finger == "C" else 0.0)
        z = -a.finger_drop
    else:
        x = -a.ac_stagger / 2 if finger == "B" else a.ac_stagger / 2
        z = -(a.finger_drop - design.rail.height)
    y = a.side_gap / 2 if SIDE_OF[finger] == 1 else -a.side_gap / 2
    return (x, y, z)


def carriage_origin_x(design: Design) -> float:
    """x of the carriage centre in the stage frame with the rail at 0 [m]."""
    a = design.array
    return a.a_x + a.pair_spacing + a.ac_stagger / 2


def _bracket(design: Design, finger: str, top: float) -> tuple[Part, MassProps, tuple]:
    """Block from ``top`` down to just above the finger's MCP axis; holds the MCP servo."""
    f = design.finger
    w, d = f.section.width, f.section.depth
    x, y, z = finger_mount(design, finger)
    bottom = z + d / 2 + 0.001
    if bottom >= top:
        raise BuildError(
            f"array.finger_drop is too short to hold finger {finger}'s MCP servo bracket"
        )
    lo, hi = (x - w / 2, y - d / 2, bottom), (x + w / 2, y + d / 2, top)
    part = Part(f"{finger}_bracket", box(lo, hi), design.materials.structure)
    servo = servo_props(design, np.array([x, y, bottom + design.servo.length / 2]), 2)
    return part, servo, _box_collision(lo, hi)


def structure_bodies(design: Design) -> dict[str, LinkBody]:
    """Base (mounting plate, guide columns), stage (plate, bushings, rail, brackets of A and
    C, rail and stage servos) and carriage (plate, brackets of B and D)."""
    mnt, st, rl = design.mounting, design.stage, design.rail
    rho = design.materials.structure
    bodies: dict[str, LinkBody] = {}

    # base: frame at the top centre of the bays; plate below it, guide columns below that
    t = mnt.plate_thickness
    plate_lo = (-mnt.plate_length / 2, -mnt.plate_width / 2, -t)
    plate_hi = (mnt.plate_length / 2, mnt.plate_width / 2, 0.0)
    parts = [Part("mounting_plate", box(plate_lo, plate_hi), rho)]
    cyls = []
    for sx in (-1.0, 1.0):
        c = (sx * st.guide_x, 0.0, -t - st.guide_length / 2)
        parts.append(Part("guide", cylinder("z", st.guide_radius, st.guide_length, c), rho))
        cyls.append((c, "z", st.guide_radius, st.guide_length / 2))
    bodies["base"] = LinkBody(
        "base",
        tuple(parts),
        (),
        boxes=(_box_collision(plate_lo, plate_hi),),
        cylinders=tuple(cyls),
    )

    # stage: frame at the stage plate underside centre
    pt = st.plate_thickness
    sp_lo = (-st.plate_length / 2, -st.plate_width / 2, 0.0)
    sp_hi = (st.plate_length / 2, st.plate_width / 2, pt)
    plate = box(sp_lo, sp_hi)
    bush_half = st.guide_radius * 2
    holes = None
    for sx in (-1.0, 1.0):
        gx = sx * st.guide_x
        bush = box((gx - bush_half, -bush_half, 0.0), (gx + bush_half, bush_half, pt))
        plate = plate + bush
        hole = cylinder("z", st.guide_radius * 1.05, pt * 3, (gx, 0.0, pt / 2))
        holes = hole if holes is None else holes + hole
    plate = plate - holes
    parts = [Part("stage_plate", plate, rho)]
    boxes = [_box_collision(sp_lo, sp_hi)]
    x_c0 = carriage_origin_x(design)
    rail_cx = x_c0 + rl.travel / 2
    r_lo = (rail_cx - rl.length / 2, -rl.width / 2, -rl.height)
    r_hi = (rail_cx + rl.length / 2, rl.width / 2, 0.0)
    parts.append(Part("rail", box(r_lo, r_hi), rho))
    boxes.append(_box_collision(r_lo, r_hi))
    servos = []
    for finger in ("A", "C"):
        part, servo, coll = _bracket(design, finger, 0.0)
        parts.append(part)
        servos.append(servo)
        boxes.append(coll)
    s = design.servo
    # rail and stage servos lie under the plate at the aft end, between the two sides
    for sx in (design.array.a_x + 0.018, design.array.a_x - 0.008):
        servos.append(servo_props(design, np.array([sx, 0.0, -s.height / 2]), 1))
    bodies["stage"] = LinkBody("stage", tuple(parts), tuple(servos), boxes=tuple(boxes))

    # carriage: frame at the carriage plate top centre (rail underside)
    a = design.array
    ct = rl.carriage_thickness
    half_w = a.side_gap / 2 + design.finger.section.depth / 2
    c_lo = (-rl.carriage_length / 2, -half_w, -ct)
    c_hi = (rl.carriage_length / 2, half_w, 0.0)
    parts = [Part("carriage_plate", box(c_lo, c_hi), rho)]
    boxes = [_box_collision(c_lo, c_hi)]
    servos = []
    for finger in ("B", "D"):
        part, servo, coll = _bracket(design, finger, -ct)
        parts.append(part)
        servos.append(servo)
        boxes.append(coll)
    bodies["carriage"] = LinkBody("carriage", tuple(parts), tuple(servos), boxes=tuple(boxes))
    return bodies


def check_solid(name: str, solid: m3d.Manifold) -> trimesh.Trimesh:
    """Raise :class:`BuildError` unless ``solid`` is a valid, watertight, positive solid."""
    status = solid.status()
    if status != m3d.Error.NoError:
        raise BuildError(f"solid {name} is invalid: {status}")
    tm = to_trimesh(solid)
    if not tm.is_watertight or not tm.is_winding_consistent:
        raise BuildError(f"solid {name} is not watertight")
    if tm.volume <= 0:
        raise BuildError(f"solid {name} has non-positive volume")
    return tm


def all_bodies(design: Design) -> dict[str, LinkBody]:
    """Every distinct link body, keyed by mesh name."""
    out = structure_bodies(design)
    out.update(finger_bodies(design))
    return out


__all__ = [
    "FINGERS",
    "LinkBody",
    "MassProps",
    "Part",
    "all_bodies",
    "carriage_origin_x",
    "check_solid",
    "finger_mount",
    "to_trimesh",
]
