"""Stowed fit: containment in the bays, self-collision, posture search, deployment sweep.

Containment is a volume test: a part is inside the (convex) bay envelope when every
extreme point of the part is (closed form on the convex-hull vertices, exact for a
polyhedral solid), and the part's volume outside the envelope (manifold3d
difference) is nil. Clearance to the walls of an inside part is a python-fcl
distance between the part's triangle mesh and slabs standing on the six walls;
the protrusion of an outside part is the largest distance of a part point beyond
the envelope. Self-collision is a manifold3d intersection volume for every
non-adjacent link pair; penetration depths and clearances come from signed
distances (GJK/EPA) between the convex pieces of the links.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import fcl
import manifold3d as m3d
import numpy as np
from scipy import optimize

from payload.design.params import FINGER_JOINTS, FINGERS
from payload.envelope.geometry import PayloadGeometry, box_geometry, bvh_object, mesh_arrays
from payload.envelope.vehicle import Vehicle

INSIDE_TOL = 1e-6
"""A part point may lie this far outside the envelope and still count as inside [m]."""

VOLUME_TOL = 1e-12
"""Volume (1e-3 mm^3) below which an overlap or an outside part counts as nil [m^3]."""

Progress = Callable[[str, float], None]
"""``progress(stage, fraction)`` callback for long work."""


def _quiet(stage: str, fraction: float) -> None:
    return None


# ----------------------------------------------------------------- box envelope


def wall_gaps(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Signed distance of each point to each wall, positive inside.

    Args:
        points: Shape (k, 3) [m].
        lower: Lower envelope corner, shape (3,) [m].
        upper: Upper envelope corner, shape (3,) [m].

    Returns:
        Shape (k, 6): gaps to the -x, +x, -y, +y, -z, +z walls [m].
    """
    p = np.asarray(points, dtype=float)
    return np.stack(
        [
            p[:, 0] - lower[0],
            upper[0] - p[:, 0],
            p[:, 1] - lower[1],
            upper[1] - p[:, 1],
            p[:, 2] - lower[2],
            upper[2] - p[:, 2],
        ],
        axis=1,
    )


def protrusion(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[float, int]:
    """Largest distance of a point outside the box, and the wall it crosses most.

    Args:
        points: Shape (k, 3) [m].
        lower: Lower envelope corner, shape (3,) [m].
        upper: Upper envelope corner, shape (3,) [m].

    Returns:
        (distance [m], 0 when every point is inside; wall index 0..5 of the largest
        excess at the farthest point).
    """
    gaps = wall_gaps(points, lower, upper)
    excess = np.maximum(-gaps, 0.0)
    # at most one wall of each axis pair is crossed: the Euclidean norm of the
    # per-axis excess is the point's distance to the box
    dist = np.sqrt((excess**2).sum(axis=1))
    k = int(np.argmax(dist))
    return float(dist[k]), int(np.argmax(excess[k]))


def box_clearance(
    points: np.ndarray, lower: np.ndarray, upper: np.ndarray, skip: Sequence[int] = ()
) -> tuple[float, int]:
    """Smallest wall gap over points inside the box, and the nearest wall.

    Args:
        points: Shape (k, 3) [m]; every point inside the box.
        lower: Lower envelope corner, shape (3,) [m].
        upper: Upper envelope corner, shape (3,) [m].
        skip: Wall indices left out (e.g. the mount face of the mounted part).

    Returns:
        (clearance [m], wall index 0..5).
    """
    gaps = wall_gaps(points, lower, upper)
    gaps[:, list(skip)] = np.inf
    per_wall = gaps.min(axis=0)
    w = int(np.argmin(per_wall))
    return float(per_wall[w]), w


def wall_slabs(lower: np.ndarray, upper: np.ndarray) -> list[fcl.CollisionObject]:
    """Six thick python-fcl boxes standing on the envelope walls (outside), -x .. +z."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    t = float(np.max(upper - lower))
    out = []
    for axis in range(3):
        for side in (0, 1):
            lo, hi = lower - t, upper + t
            if side == 0:
                hi = hi.copy()
                hi[axis] = lower[axis]
            else:
                lo = lo.copy()
                lo[axis] = upper[axis]
            out.append(box_geometry(lo, hi))
    return out


def box_solid(lower: np.ndarray, upper: np.ndarray) -> m3d.Manifold:
    """An axis-aligned box solid [m]."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    return m3d.Manifold.cube(list(upper - lower)).translate(list(lower))


# ----------------------------------------------------------------- results


class PartFit(NamedTuple):
    """How one part (link) sits in the bay envelope.

    Attributes:
        name: Link name.
        inside: Wholly inside the envelope.
        clearance: Smallest distance to a wall when inside, minus the protrusion when not [m].
        protrusion: Largest distance of a part point beyond the walls (0 inside) [m].
        wall: The nearest wall (inside) or the wall crossed most (outside).
        outside_volume: Part volume outside the envelope [m^3].
        mounted: The part is the one bolted to the mount face (+z wall), whose contact
            with that face is its mounting and not a clearance.
        wall_clearance: python-fcl distance to each of the six walls, -x .. +z [m]
            (NaN for a mounted part's mount face; 0 when touching or crossing).
    """

    name: str
    inside: bool
    clearance: float
    protrusion: float
    wall: str
    outside_volume: float
    mounted: bool
    wall_clearance: tuple[float, ...]


class PairContact(NamedTuple):
    """Two links' proximity.

    Attributes:
        a: First link.
        b: Second link.
        distance: Signed distance between their convex pieces [m] (negative = depth).
        overlap_volume: Exact volume the two solids share [m^3].
    """

    a: str
    b: str
    distance: float
    overlap_volume: float

    @property
    def colliding(self) -> bool:
        return bool(self.overlap_volume > VOLUME_TOL)


class SweepResult(NamedTuple):
    """The deployment sweep: the stage from stowed to deployed, fingers in one posture.

    Attributes:
        clear: No contact with the vehicle body or the fixed base along the path, and no
            self-collision among the parts the stage carries (they move as one body).
        vehicle_clear: No contact with the vehicle body or the base along the path.
        min_distance: Smallest signed distance to the vehicle or the base [m].
        at_stage: Stage travel where it occurs [m].
        between: The two things closest there.
        samples: Stage positions evaluated.
        certified: Every interval between samples was proved contact-free (the
            distance is 1-Lipschitz in the stage travel: ``d0 + d1 > step``) or holds a
            sample in contact.
        first_contact: Stage travel of the first contact (NaN when none) [m].
    """

    clear: bool
    vehicle_clear: bool
    min_distance: float
    at_stage: float
    between: tuple[str, str]
    samples: int
    certified: bool
    first_contact: float = float("nan")


class PostureSearch(NamedTuple):
    """The finger posture (shared by the four fingers) that maximises the minimum clearance.

    Attributes:
        finger: Joint values [mcp_flex, mcp_abd, pip, dip] [rad].
        clearance: The minimum over envelope clearances and self-collision distances [m].
        limited_by: What sets that minimum (a part and a wall, or two links).
        evaluations: Objective evaluations.
        seconds: Wall time [s].
    """

    finger: tuple[float, float, float, float]
    clearance: float
    limited_by: str
    evaluations: int
    seconds: float


@dataclass
class StowedCheck:
    """Every check of one stowed configuration.

    Attributes:
        q: Joint values (every joint of the tree) [rad, m].
        parts: Per-part fit.
        self_contacts: Every checked (non-adjacent) pair, closest first.
        sweep: The deployment sweep from this configuration.
    """

    q: dict[str, float]
    parts: list[PartFit]
    self_contacts: list[PairContact]
    sweep: SweepResult

    @property
    def fits(self) -> bool:
        return all(p.inside for p in self.parts)

    @property
    def min_clearance(self) -> float:
        """Smallest part clearance (negative: largest protrusion) [m]."""
        return min(p.clearance for p in self.parts)

    @property
    def tightest(self) -> PartFit:
        return min(self.parts, key=lambda p: p.clearance)

    @property
    def collisions(self) -> list[PairContact]:
        return [c for c in self.self_contacts if c.colliding]

    @property
    def self_collision(self) -> bool:
        return bool(self.collisions)

    @property
    def min_self_clearance(self) -> PairContact:
        return min(self.self_contacts, key=lambda c: c.distance)

    @property
    def passed(self) -> bool:
        return self.fits and not self.self_collision and self.sweep.clear

    def failures(self) -> list[str]:
        """One phrase per failed check, naming parts and millimetres."""
        out = []
        for p in sorted(self.parts, key=lambda p: round(p.clearance, 8)):
            if not p.inside:
                out.append(
                    f"{p.name} protrudes {p.protrusion * 1e3:.1f} mm beyond the {p.wall} wall"
                )
        for c in self.collisions:
            out.append(
                f"{c.a} and {c.b} collide ({-c.distance * 1e3:.1f} mm deep, "
                f"{c.overlap_volume * 1e9:.0f} mm^3)"
            )
        if not self.sweep.vehicle_clear:
            a, b = self.sweep.between
            if np.isfinite(self.sweep.first_contact):
                out.append(
                    f"deployment: {a} hits {b} from stage {self.sweep.first_contact * 1e3:.1f} mm "
                    f"(deepest {-self.sweep.min_distance * 1e3:.1f} mm at "
                    f"{self.sweep.at_stage * 1e3:.1f} mm)"
                )
            else:
                out.append("deployment: the sweep could not prove the path contact-free")
        return out


@dataclass
class EnvelopeAnalysis:
    """The envelope report's content.

    Attributes:
        vehicle: The vehicle and bay envelope used.
        design_source: The design file.
        given: Checks of the design's stowed configuration.
        search: The stowed-posture search (run when the given posture fails, or on request).
        suggested: Checks of the searched posture (when a search ran).
        excluded_pairs: Adjacent link pairs left out of self-collision.
        approximate: Parts whose convex hull is larger than the part (name, excess).
        seconds: Wall time of the analysis [s].
    """

    vehicle: Vehicle
    design_source: str
    given: StowedCheck
    search: PostureSearch | None
    suggested: StowedCheck | None
    excluded_pairs: list[tuple[str, str]]
    approximate: list[tuple[str, float]]
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return self.given.passed

    def assumptions(self) -> list[str]:
        v = self.vehicle
        size = " x ".join(f"{s * 1e3:.0f}" for s in v.bay_size)
        body = " x ".join(f"{s * 1e3:.0f}" for s in v.body_size)
        return [
            f"ASSUMPTION (bay size): {v.assumption}",
            f"bay envelope {size} mm from {v.source}; vehicle body {body} mm with its "
            f"bottom face at z = {v.bottom_z * 1e3:.0f} mm (payload frame)",
            "the mounted part's contact with the mount face (+z wall) is its mounting, "
            "not a clearance",
            "self-collision ignores parent/child link pairs (they meet at their joint by "
            "construction)",
        ]


# ----------------------------------------------------------------- checks


def fit_solid(
    name: str,
    solid: m3d.Manifold,
    vehicle: Vehicle,
    mounted: bool = False,
    hull_points: np.ndarray | None = None,
    mesh: fcl.CollisionObject | None = None,
) -> PartFit:
    """Containment and clearance of one solid (in the payload frame) in the bay envelope.

    Args:
        name: Part name.
        solid: The part [m], payload frame.
        vehicle: The vehicle whose bay envelope is checked.
        mounted: The part is bolted to the mount face (+z wall): that face is left out of
            its clearance.
        hull_points: Extreme points of the part (default: its convex-hull vertices) [m].
        mesh: The part's posed python-fcl mesh (default: built from ``solid``).

    Returns:
        The :class:`PartFit`.
    """
    lo, hi = vehicle.bay_lower, vehicle.bay_upper
    if hull_points is None:
        hull_points = mesh_arrays(solid.hull())[0]
    if mesh is None:
        mesh = bvh_object(solid)
    prot, prot_wall = protrusion(hull_points, lo, hi)
    outside = float((solid - box_solid(lo, hi)).volume())
    request = fcl.DistanceRequest()
    walls = []
    for w, slab in enumerate(wall_slabs(lo, hi)):
        if mounted and w == 5:
            walls.append(float("nan"))
            continue
        d = float(fcl.distance(mesh, slab, request, fcl.DistanceResult()))
        walls.append(max(d, 0.0))
    inside = bool(prot <= INSIDE_TOL and outside <= VOLUME_TOL)
    if inside:
        w = int(np.nanargmin(walls))
        clearance, wall = walls[w], vehicle.walls[w]
    else:
        clearance, wall = -prot, vehicle.walls[prot_wall]
    return PartFit(
        name,
        inside,
        float(clearance),
        0.0 if inside else float(prot),
        wall,
        outside,
        bool(mounted),
        tuple(walls),
    )


def fit_parts(
    geom: PayloadGeometry, poses: Mapping[str, np.ndarray], vehicle: Vehicle
) -> list[PartFit]:
    """Containment and clearance of every link in the bay envelope.

    Args:
        geom: Collision geometry of the payload.
        poses: Link poses in the payload frame.
        vehicle: The vehicle whose bay envelope is checked.

    Returns:
        One :class:`PartFit` per link, in tree order.
    """
    top = vehicle.bay_upper[2]
    out = []
    for name in geom.links:
        pose = poses[name]
        pts = geom.hull_vertices(name, pose)
        mounted = name == geom.root and float(pts[:, 2].max()) >= top - INSIDE_TOL
        out.append(
            fit_solid(
                name,
                geom.posed_solid(name, pose),
                vehicle,
                mounted,
                pts,
                geom.mesh_object(name, pose),
            )
        )
    return out


def self_contacts(
    geom: PayloadGeometry, poses: Mapping[str, np.ndarray], near: float = 1e-4
) -> list[PairContact]:
    """Signed distance of every non-adjacent link pair, with the exact overlap volume.

    Args:
        geom: Collision geometry of the payload.
        poses: Link poses in the payload frame.
        near: Pairs closer than this (convex pieces) get a manifold3d intersection
            volume; farther pairs share no volume [m].

    Returns:
        Every pair, closest first.
    """
    out = []
    for a, b in geom.pairs:
        d = geom.link_distance(a, b, poses)
        vol = geom.overlap_volume(a, b, poses) if d < near else 0.0
        out.append(PairContact(a, b, d, vol))
    # closest first; equal distances (to 10 nm) keep the tree's pair order
    order = sorted(range(len(out)), key=lambda i: (round(out[i].distance, 8), i))
    return [out[i] for i in order]


def _obstacles(geom: PayloadGeometry, vehicle: Vehicle) -> list[tuple[str, Any, tuple]]:
    names = (
        "above the bays",
        "aft of the bays",
        "forward of the bays",
        "right of the bays",
        "left of the bays",
    )
    out = []
    for (lo, hi), name in zip(vehicle.body_boxes(), names):
        out.append((f"vehicle body ({name})", box_geometry(lo, hi), (lo, hi)))
    return out


def deployment_sweep(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    q: Mapping[str, float],
    contacts: Sequence[PairContact] | None = None,
    min_step: float = 1e-5,
    extra: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
) -> SweepResult:
    """Lower the stage from 0 to its full travel with the fingers held in ``q``.

    The stage carries every link but the base rigidly, so their mutual distances do
    not change on the way: the sweep checks them against the vehicle body (five
    convex boxes around the open bays), the base and any ``extra`` obstacle, and
    takes the carried parts' self-collision from ``contacts``. The distance to the
    fixed things is 1-Lipschitz in the stage travel, so an interval whose end
    distances add up to more than its length is contact-free; other intervals are
    halved down to ``min_step``.

    Args:
        geom: Collision geometry.
        vehicle: The vehicle.
        q: Joint values; ``q["stage"]`` is ignored.
        contacts: Self-contacts of ``q`` (computed when not given).
        min_step: Smallest interval halved [m].
        extra: More fixed boxes ``(name, lower corner, upper corner)`` [m].

    Returns:
        The :class:`SweepResult`.
    """
    stage = geom.tree.joint_map["stage"]
    moving = [n for n in geom.links if n != geom.root]
    pairs = [(n, geom.root) for n in moving if frozenset((n, geom.root)) not in geom.adjacent]
    obstacles = _obstacles(geom, vehicle)
    obstacles += [
        (name, box_geometry(lo, hi), (np.asarray(lo), np.asarray(hi))) for name, lo, hi in extra
    ]
    q = dict(q)

    def dist(s: float) -> tuple[float, tuple[str, str]]:
        q["stage"] = s
        return geom.min_distance(geom.poses(q), pairs=pairs, others=obstacles, moving=moving)

    grid = np.linspace(stage.lower, stage.upper, 9)
    values = {float(s): dist(float(s)) for s in grid}
    stack = [(float(a), float(b)) for a, b in itertools.pairwise(grid)]
    certified = True
    while stack:
        a, b = stack.pop()
        da, db = values[a][0], values[b][0]
        if da <= 0 or db <= 0 or da + db > b - a:
            continue
        if b - a < min_step:
            certified = False
            continue
        m = 0.5 * (a + b)
        values[m] = dist(m)
        stack += [(a, m), (m, b)]
    order = sorted(values)
    first = float("nan")
    hits = [s for s in order if values[s][0] <= 0]
    if hits:
        # bisect the interval that ends at the first sample in contact
        hi_s = hits[0]
        lo_s = max((s for s in order if s < hi_s), default=None)
        while lo_s is not None and hi_s - lo_s > min_step:
            m = 0.5 * (lo_s + hi_s)
            values[m] = dist(m)
            if values[m][0] <= 0:
                hi_s = m
            else:
                lo_s = m
        first = hi_s
    s_min = min(values, key=lambda s: values[s][0])
    d_min, between = values[s_min]
    vehicle_clear = not hits and certified
    if contacts is None:
        contacts = self_contacts(geom, geom.poses(q))
    carried = any(c.colliding and geom.root not in (c.a, c.b) for c in contacts)
    return SweepResult(
        bool(vehicle_clear and not carried),
        bool(vehicle_clear),
        float(d_min),
        float(s_min),
        between,
        len(values),
        bool(certified),
        float(first),
    )


def check_stowed(geom: PayloadGeometry, vehicle: Vehicle, q: Mapping[str, float]) -> StowedCheck:
    """Containment, self-collision and the deployment sweep of one stowed configuration."""
    q = dict(q)
    q["stage"] = geom.tree.joint_map["stage"].lower
    poses = geom.poses(q)
    contacts = self_contacts(geom, poses)
    return StowedCheck(
        q, fit_parts(geom, poses, vehicle), contacts, deployment_sweep(geom, vehicle, q, contacts)
    )


# ----------------------------------------------------------------- posture search


def with_finger_posture(q: Mapping[str, float], finger: Sequence[float]) -> dict[str, float]:
    """``q`` with the same [mcp_flex, mcp_abd, pip, dip] on every finger [rad]."""
    out = dict(q)
    for f in FINGERS:
        for j, v in zip(FINGER_JOINTS, finger):
            out[f"{f}_{j}"] = float(v)
    return out


def finger_links(geom: PayloadGeometry) -> list[str]:
    """Links moved by a finger joint (the four fingers' links)."""
    fingers = {f"{f}_{j}" for f in FINGERS for j in FINGER_JOINTS}
    moved: set[str] = set()
    for j in geom.tree.joints:
        if j.name in fingers or j.parent in moved:
            moved.add(j.child)
    return [n for n in geom.links if n in moved]


def envelope_margin(
    geom: PayloadGeometry,
    poses: Mapping[str, np.ndarray],
    vehicle: Vehicle,
    links: Sequence[str] | None = None,
) -> tuple[float, str]:
    """Smallest signed part clearance to the walls (negative: protrusion) [m], and where.

    Closed form on the convex-hull vertices (exact for the polyhedral solids); the
    mounted part's mount face is left out.

    Args:
        geom: Collision geometry.
        poses: Link poses in the payload frame.
        vehicle: The vehicle.
        links: Links considered (default: all).
    """
    lo, hi = vehicle.bay_lower, vehicle.bay_upper
    best, where = np.inf, ""
    for name in geom.links if links is None else links:
        pts = geom.hull_vertices(name, poses[name])
        prot, w = protrusion(pts, lo, hi)
        if prot > 0:
            value = -prot
        else:
            skip = (5,) if name == geom.root else ()
            value, w = box_clearance(pts, lo, hi, skip)
        if value < best:
            best, where = value, f"{name} / {vehicle.walls[w]} wall"
    return float(best), where


def search_stowed_posture(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    q: Mapping[str, float],
    grid: int = 6,
    starts: int = 3,
    progress: Progress = _quiet,
) -> PostureSearch:
    """The finger posture, inside the joint limits, that maximises the minimum clearance.

    The objective is the smaller of the fingers' envelope margin
    (:func:`envelope_margin`) and the smallest signed distance between a finger link
    and any non-adjacent link (parts the fingers do not move keep their clearance
    whatever the posture, and are reported apart); the four finger joints
    are shared by every finger (as the design's ``[stowed]`` posture is). A grid of
    ``grid**4`` postures seeds bounded Nelder-Mead refinements from the ``starts``
    best.

    Args:
        geom: Collision geometry.
        vehicle: The vehicle.
        q: The stowed configuration (rail, stage) the fingers are folded in.
        grid: Grid points per joint.
        starts: Local refinements.
        progress: Progress callback.

    Returns:
        The best posture found and its clearance.
    """
    t0 = time.perf_counter()
    limits = np.array(
        [
            [geom.tree.joint_map[f"A_{j}"].lower, geom.tree.joint_map[f"A_{j}"].upper]
            for j in FINGER_JOINTS
        ]
    )
    base = dict(q)
    base["stage"] = geom.tree.joint_map["stage"].lower
    fingers = finger_links(geom)
    pairs = [(a, b) for a, b in geom.pairs if a in fingers or b in fingers]
    count = 0

    def evaluate(x: np.ndarray) -> tuple[float, str]:
        nonlocal count
        count += 1
        x = np.clip(x, limits[:, 0], limits[:, 1])
        poses = geom.poses(with_finger_posture(base, x))
        margin, where = envelope_margin(geom, poses, vehicle, fingers)
        d, (a, b) = geom.min_distance(poses, pairs)
        if d < margin:
            return d, f"{a} / {b}"
        return margin, where

    axes = [np.linspace(lo, hi, grid) for lo, hi in limits]
    seeds = []
    total = grid**4
    for i, x in enumerate(itertools.product(*axes)):
        seeds.append((evaluate(np.array(x))[0], np.array(x)))
        if i % 25 == 0:
            progress("posture search: grid", i / total)
    seeds.sort(key=lambda s: -s[0])
    best_x, best_v = seeds[0][1], seeds[0][0]
    for k, (_, x0) in enumerate(seeds[:starts]):
        progress("posture search: refine", k / starts)
        res = optimize.minimize(
            lambda x: -evaluate(x)[0],
            x0,
            method="Nelder-Mead",
            options={
                "xatol": 1e-4,
                "fatol": 1e-7,
                "maxfev": 400,
                "initial_simplex": _simplex(x0, limits),
            },
        )
        x = np.clip(res.x, limits[:, 0], limits[:, 1])
        if -res.fun > best_v:
            best_x, best_v = x, -res.fun
    value, where = evaluate(best_x)
    progress("posture search", 1.0)
    finger = tuple(float(v) for v in best_x)
    return PostureSearch(finger, value, where, count, time.perf_counter() - t0)  # type: ignore[arg-type]


def _simplex(x0: np.ndarray, limits: np.ndarray) -> np.ndarray:
    step = 0.1 * (limits[:, 1] - limits[:, 0])
    pts = [x0]
    for i in range(len(x0)):
        x = x0.copy()
        x[i] = x[i] - step[i] if x[i] + step[i] > limits[i, 1] else x[i] + step[i]
        pts.append(x)
    return np.array(pts)


# ----------------------------------------------------------------- the analysis


def analyse_envelope(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    search: bool | None = None,
    progress: Progress = _quiet,
) -> EnvelopeAnalysis:
    """Check the design's stowed configuration; search a posture when it fails.

    Args:
        geom: Collision geometry of the design.
        vehicle: The vehicle.
        search: Run the stowed-posture search: ``None`` (default) when the given
            posture fails, ``True`` always, ``False`` never.
        progress: Progress callback.

    Returns:
        The :class:`EnvelopeAnalysis`.
    """
    t0 = time.perf_counter()
    progress("stowed fit", 0.0)
    given = check_stowed(geom, vehicle, geom.tree.posture("stowed"))
    progress("stowed fit", 1.0)
    found = suggested = None
    if search or (search is None and not given.passed):
        found = search_stowed_posture(geom, vehicle, given.q, progress=progress)
        suggested = check_stowed(geom, vehicle, with_finger_posture(given.q, found.finger))
    approx = [(f"{p.link}/{p.name}", p.excess) for p in geom.approximate_pieces()]
    return EnvelopeAnalysis(
        vehicle,
        geom.tree.design.source,
        given,
        found,
        suggested,
        geom.excluded_pairs(),
        approx,
        time.perf_counter() - t0,
    )


__all__ = [
    "INSIDE_TOL",
    "VOLUME_TOL",
    "EnvelopeAnalysis",
    "PairContact",
    "PartFit",
    "PostureSearch",
    "StowedCheck",
    "SweepResult",
    "analyse_envelope",
    "box_clearance",
    "box_solid",
    "check_stowed",
    "deployment_sweep",
    "envelope_margin",
    "finger_links",
    "fit_parts",
    "fit_solid",
    "protrusion",
    "search_stowed_posture",
    "self_contacts",
    "wall_gaps",
    "wall_slabs",
    "with_finger_posture",
]
