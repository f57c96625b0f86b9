"""The payload's solids as collision geometry: exact meshes and convex pieces per link.

Every link solid is a union of parts (:class:`payload.design.solids.Part`). For
distances the workbench uses one convex piece per part (python-fcl ``Convex``,
signed distance by GJK/EPA, so a penetration has a depth); for volume tests it
uses the exact manifold3d solid. A piece is the part's convex hull, or, for a
fingertip pad cut from a sphere by the distal link, that sphere (the union with the
link body is the same). Every piece of the default design is exact except the
stage plate's hull, which closes the guide-column holes and the notches beside the
bushings: only the guide columns come near them, and they slide in those holes as
the stage's parent link, so that pair is never checked.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import fcl
import manifold3d as m3d
import numpy as np

from payload.design.solids import sphere
from payload.design.tree import KinematicTree

HULL_EXACT_TOL = 0.01
"""Relative volume excess above which a part's convex hull is reported as approximate."""


@dataclass(frozen=True)
class ConvexPiece:
    """The convex hull of one part of a link.

    Attributes:
        link: Link name.
        name: Part name, e.g. ``A_bracket``.
        vertices: Piece vertices in the link frame, shape (k, 3) [m].
        geometry: The python-fcl ``Convex`` of the hull, or a ``Sphere``.
        excess: Volume the piece adds to the link solid, over the part's volume (0 when
            the piece lies inside the link solid).
        sphere: (centre in the link frame [m], radius [m]) when the piece is a sphere.
    """

    link: str
    name: str
    vertices: np.ndarray
    geometry: fcl.CollisionGeometry
    excess: float
    sphere: tuple[np.ndarray, float] | None = None


def mesh_arrays(solid: m3d.Manifold) -> tuple[np.ndarray, np.ndarray]:
    """Vertices, shape (k, 3) [m], and triangles, shape (t, 3), of a solid in double precision."""
    mesh = solid.to_mesh64()
    vertices = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    return vertices, np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)


def bvh_object(solid: m3d.Manifold) -> fcl.CollisionObject:
    """A solid's triangle mesh as a python-fcl BVH object at the identity pose."""
    vertices, faces = mesh_arrays(solid)
    return fcl.CollisionObject(_bvh(vertices, faces), fcl.Transform())


def _covered(piece: m3d.Manifold, solid: m3d.Manifold, rel: float = 1e-6) -> bool:
    """The piece adds no volume to the link solid (it lies inside it)."""
    return (piece - solid).volume() <= rel * max(solid.volume(), 1e-18)


def _piece(
    part: m3d.Manifold, solid: m3d.Manifold, spheres: Sequence[tuple[Sequence[float], float]]
) -> tuple[m3d.Manifold, tuple[np.ndarray, float] | None]:
    """The convex piece standing for a part, and its sphere when it is one.

    The piece is the part's convex hull, or a collision sphere of the link that holds
    the part and adds nothing to the link: a pad cut from a sphere by the link body
    is that sphere, as far as the union goes.
    """
    hull = part.hull()
    if hull.volume() <= part.volume() * (1 + 1e-9) or _covered(hull, solid):
        return hull, None
    for center, radius in spheres:
        ball = sphere(radius, tuple(center))
        if (part - ball).volume() <= 1e-6 * part.volume() and _covered(ball, solid):
            return ball, (np.asarray(center, dtype=float), float(radius))
    return hull, None


def _convex(vertices: np.ndarray, faces: np.ndarray) -> fcl.Convex:
    flat = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
    return fcl.Convex(np.asarray(vertices, dtype=np.float64), len(faces), flat)


def _bvh(vertices: np.ndarray, faces: np.ndarray) -> fcl.BVHModel:
    model = fcl.BVHModel()
    model.beginModel(len(vertices), len(faces))
    model.addSubModel(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    model.endModel()
    return model


def transform(pose: np.ndarray) -> fcl.Transform:
    """A python-fcl transform from a homogeneous matrix, shape (4, 4)."""
    return fcl.Transform(np.asarray(pose[:3, :3]), np.asarray(pose[:3, 3]))


def apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points of shape (k, 3) moved by the homogeneous ``pose``."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def box_geometry(lower: np.ndarray, upper: np.ndarray) -> fcl.CollisionObject:
    """An axis-aligned box from ``lower`` to ``upper`` as a posed python-fcl object [m]."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    size = upper - lower
    return fcl.CollisionObject(fcl.Box(*size), fcl.Transform((lower + upper) / 2))


_SIGNED = fcl.DistanceRequest(enable_signed_distance=True)


def signed_distance(a: fcl.CollisionObject, b: fcl.CollisionObject) -> float:
    """Signed distance between two convex python-fcl objects [m] (negative = depth)."""
    return float(fcl.distance(a, b, _SIGNED, fcl.DistanceResult()))


def aabb(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of points of shape (k, 3)."""
    return points.min(axis=0), points.max(axis=0)


def aabb_gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """Distance between two axis-aligned boxes (0 when they overlap) [m]."""
    gap = np.maximum(np.maximum(a[0] - b[1], b[0] - a[1]), 0.0)
    return float(np.linalg.norm(gap))


class PayloadGeometry:
    """Collision geometry of every link of a kinematic tree.

    Attributes:
        tree: The kinematic tree.
        links: Link names with a body, in tree order.
        solids: Link name -> manifold3d solid in the link frame.
        mesh_vertices: Link name -> mesh vertices in the link frame, shape (k, 3) [m].
        pieces: Link name -> convex pieces of the link.
        adjacent: Parent/child link pairs (joined by a joint), never checked.
        pairs: Every other link pair, checked for self-collision.
    """

    def __init__(self, tree: KinematicTree) -> None:
        self.tree = tree
        self.links: tuple[str, ...] = tuple(
            link.name for link in tree.links if link.body is not None
        )
        self.solids: dict[str, m3d.Manifold] = {}
        self.mesh_vertices: dict[str, np.ndarray] = {}
        self.pieces: dict[str, tuple[ConvexPiece, ...]] = {}
        self._bvh: dict[str, fcl.BVHModel] = {}
        cache: dict[str, tuple] = {}
        for name in self.links:
            body = tree.link_map[name].body
            assert body is not None
            if body.mesh not in cache:
                solid = body.solid()
                vertices, faces = mesh_arrays(solid)
                pieces = []
                for part in body.parts:
                    piece, ball = _piece(part.solid, solid, body.spheres)
                    hv, hf = mesh_arrays(piece)
                    excess = 0.0
                    if not _covered(piece, solid):
                        excess = piece.volume() / max(part.solid.volume(), 1e-18) - 1.0
                    geometry = _convex(hv, hf) if ball is None else fcl.Sphere(ball[1])
                    pieces.append((part.name, hv, geometry, excess, ball))
                cache[body.mesh] = (solid, vertices, pieces, _bvh(vertices, faces))
            solid, vertices, pieces, bvh = cache[body.mesh]
            self.solids[name] = solid
            self.mesh_vertices[name] = vertices
            self._bvh[name] = bvh
            self.pieces[name] = tuple(ConvexPiece(name, *piece) for piece in pieces)
        self.adjacent: frozenset[frozenset[str]] = frozenset(
            frozenset((j.parent, j.child)) for j in tree.joints
        )
        self.pairs: tuple[tuple[str, str], ...] = tuple(
            (a, b)
            for a, b in itertools.combinations(self.links, 2)
            if frozenset((a, b)) not in self.adjacent
        )
        self._hull_vertices = {
            n: np.vstack([p.vertices for p in self.pieces[n]]) for n in self.links
        }

    @property
    def root(self) -> str:
        """The link fixed to the vehicle (mounted on the bays' top face)."""
        return self.tree.root

    def excluded_pairs(self) -> list[tuple[str, str]]:
        """The adjacent (parent, child) link pairs left out of self-collision checks."""
        return [(j.parent, j.child) for j in self.tree.joints if j.parent in self.solids]

    def approximate_pieces(self) -> list[ConvexPiece]:
        """Parts whose convex hull is more than :data:`HULL_EXACT_TOL` larger than the part."""
        seen, out = set(), []
        for name in self.links:
            for p in self.pieces[name]:
                key = (self.tree.link_map[name].body.mesh, p.name)
                if p.excess > HULL_EXACT_TOL and key not in seen:
                    seen.add(key)
                    out.append(p)
        return out

    def poses(self, q: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Link poses in the payload frame for joint values ``q`` (missing = 0)."""
        return self.tree.link_poses(q)

    def hull_vertices(self, link: str, pose: np.ndarray) -> np.ndarray:
        """Vertices of the link's convex pieces in the payload frame, shape (k, 3) [m].

        Every extreme point of the link solid is one of them, so a convex function
        (the distance outside a box) is largest, and a concave one (the distance to a
        box's walls from inside) smallest, at one of these points.
        """
        return apply(pose, self._hull_vertices[link])

    def piece_bounds(self, link: str, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of the link's convex pieces in the payload frame [m]: the
        hull vertices', and a sphere piece's whole sphere (its mesh's vertices lie inside
        the sphere the collision checks use)."""
        lo, hi = aabb(self.hull_vertices(link, pose))
        for p in self.pieces[link]:
            if p.sphere is not None:
                centre = pose[:3, :3] @ p.sphere[0] + pose[:3, 3]
                lo = np.minimum(lo, centre - p.sphere[1])
                hi = np.maximum(hi, centre + p.sphere[1])
        return lo, hi

    def reach(self, link: str) -> float:
        """The farthest any point of the link's convex pieces lies from its frame's origin
        [m] (a sphere piece's: its centre's distance plus its radius)."""
        far = float(np.max(np.linalg.norm(self._hull_vertices[link], axis=1)))
        for p in self.pieces[link]:
            if p.sphere is not None:
                far = max(far, float(np.linalg.norm(p.sphere[0])) + float(p.sphere[1]))
        return far

    def posed_solid(self, link: str, pose: np.ndarray) -> m3d.Manifold:
        """The link solid in the payload frame."""
        return self.solids[link].transform(np.asarray(pose[:3, :]).tolist())

    def mesh_object(self, link: str, pose: np.ndarray) -> fcl.CollisionObject:
        """The link's exact triangle mesh as a posed python-fcl BVH object."""
        return fcl.CollisionObject(self._bvh[link], transform(pose))

    def piece_objects(self, link: str, pose: np.ndarray) -> list[fcl.CollisionObject]:
        """The link's convex pieces as posed python-fcl objects."""
        tf = transform(pose)
        out = []
        for p in self.pieces[link]:
            if p.sphere is None:
                out.append(fcl.CollisionObject(p.geometry, tf))
            else:
                centre = pose[:3, :3] @ p.sphere[0] + pose[:3, 3]
                out.append(fcl.CollisionObject(p.geometry, fcl.Transform(centre)))
        return out

    def link_distance(self, a: str, b: str, poses: Mapping[str, np.ndarray]) -> float:
        """Signed distance between two links' convex pieces [m] (negative = penetration)."""
        oa, ob = self.piece_objects(a, poses[a]), self.piece_objects(b, poses[b])
        return min(signed_distance(x, y) for x in oa for y in ob)

    def overlap_volume(self, a: str, b: str, poses: Mapping[str, np.ndarray]) -> float:
        """Volume shared by two link solids [m^3] (exact mesh booleans)."""
        return float((self.posed_solid(a, poses[a]) ^ self.posed_solid(b, poses[b])).volume())

    def min_distance(
        self,
        poses: Mapping[str, np.ndarray],
        pairs: Iterable[tuple[str, str]] | None = None,
        others: Sequence[tuple[str, fcl.CollisionObject, tuple[np.ndarray, np.ndarray]]] = (),
        moving: Sequence[str] | None = None,
    ) -> tuple[float, tuple[str, str]]:
        """The smallest signed distance among link pairs and against fixed obstacles.

        Pairs are visited in order of their bounding-box gap and the search stops when
        that gap exceeds the best distance found, so the result is exact.

        Args:
            poses: Link poses in the payload frame.
            pairs: Link pairs (default: every non-adjacent pair).
            others: Fixed obstacles ``(name, convex object, (lower, upper) bounds)``.
            moving: Links checked against ``others`` (default: every link).

        Returns:
            (distance [m], names of the closest pair).
        """
        pairs = self.pairs if pairs is None else tuple(pairs)
        boxes = {n: self.piece_bounds(n, poses[n]) for n in self.links}
        tasks: list[tuple[float, str, str, fcl.CollisionObject | None]] = []
        for a, b in pairs:
            tasks.append((aabb_gap(boxes[a], boxes[b]), a, b, None))
        for link in self.links if moving is None else moving:
            for name, obj, bounds in others:
                tasks.append((aabb_gap(boxes[link], bounds), link, name, obj))
        tasks.sort(key=lambda t: t[0])
        best, where = np.inf, ("", "")
        for gap, a, b, obj in tasks:
            if gap > 0.0 and gap > best:  # AABBs apart: the pair is at least ``gap`` apart
                break
            if obj is None:
                d = self.link_distance(a, b, poses)
            else:
                d = min(signed_distance(o, obj) for o in self.piece_objects(a, poses[a]))
            if d < best:
                best, where = d, (a, b)
        return float(best), where


__all__ = [
    "HULL_EXACT_TOL",
    "ConvexPiece",
    "PayloadGeometry",
    "aabb",
    "aabb_gap",
    "apply",
    "box_geometry",
    "bvh_object",
    "mesh_arrays",
    "signed_distance",
    "transform",
]
