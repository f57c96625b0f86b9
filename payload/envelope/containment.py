"""Containment of the stowed parts in the (box) bay envelope.

A part is inside the (convex) bay envelope when every extreme point of the part is
(closed form on the convex-hull vertices, exact for a polyhedral solid), and the
part's volume outside the envelope (manifold3d difference) is nil. Clearance to the
walls of an inside part is a python-fcl distance between the part's triangle mesh
and slabs standing on the six walls; the protrusion of an outside part is the
largest distance of a part point beyond the envelope.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import fcl
import manifold3d as m3d
import numpy as np

from payload.envelope.fit_results import (
    VOLUME_TOL,
    PartFit,
)
from payload.envelope.geometry import PayloadGeometry, box_geometry, bvh_object, mesh_arrays
from payload.envelope.vehicle import Vehicle

INSIDE_TOL = 1e-6
"""A part point may lie this far outside the envelope and still count as inside [m]."""


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
    beyond = np.maximum(-wall_gaps(hull_points, lo, hi).min(axis=0), 0.0)
    beyond[beyond <= INSIDE_TOL] = 0.0  # as a part inside: within the tolerance
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
        tuple(float(b) for b in beyond),
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


__all__ = [
    "INSIDE_TOL",
    "box_clearance",
    "box_solid",
    "fit_parts",
    "fit_solid",
    "protrusion",
    "wall_gaps",
    "wall_slabs",
]
