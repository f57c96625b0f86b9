"""Self-collision of a pair's commands, checked with python-fcl on the URDF's collision meshes.

Independent of the retargeting solver: the link meshes (or box, cylinder and sphere
primitives) named by the URDF's ``<collision>`` elements are loaded with trimesh, posed
by Pinocchio's forward kinematics, and tested with python-fcl (BVH triangle meshes).

Checked link pairs, for one finger pair:

* every link moved by finger 1's joints against every link moved by finger 2's, except
  the two pad links (:func:`payload.retarget.collision.pad_links`: a pinch closes the
  pads on each other, so that pair has no margin and is not a collision here);
* every link moved by either finger against the structure: the links that no joint of
  any pair moves (for our hand the base, the stage and the rail carriage), except the
  link a finger's first joint is mounted on, against that finger's first link (they are
  joined by the joint).

Links of the hand's other pairs are left out: their configuration is not this pair's.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import fcl
import numpy as np
import pinocchio as pin

from payload.retarget.features import PairKinematics


def _origin(el: ET.Element | None) -> np.ndarray:
    pose = np.eye(4)
    if el is None:
        return pose
    xyz = [float(v) for v in el.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in el.get("rpy", "0 0 0").split()]
    pose[:3, :3] = pin.rpy.rpyToMatrix(*rpy)
    pose[:3, 3] = xyz
    return pose


def _geometry(geo: ET.Element, urdf_dir: Path) -> fcl.CollisionGeometry | None:
    from payload.retarget.collision_geometry import load_collision_mesh

    mesh = geo.find("mesh")
    if mesh is not None:
        tm = load_collision_mesh(mesh.get("filename", ""), urdf_dir)
        scale = np.array([float(v) for v in mesh.get("scale", "1 1 1").split()])
        vertices = np.asarray(tm.vertices, dtype=float) * scale
        model = fcl.BVHModel()
        model.beginModel(len(vertices), len(tm.faces))
        model.addSubModel(vertices, np.asarray(tm.faces, dtype=np.int64))
        model.endModel()
        return model
    box = geo.find("box")
    if box is not None:
        return fcl.Box(*[float(v) for v in box.get("size", "0 0 0").split()])
    cyl = geo.find("cylinder")
    if cyl is not None:
        return fcl.Cylinder(float(cyl.get("radius", 0)), float(cyl.get("length", 0)))
    sph = geo.find("sphere")
    if sph is not None:
        return fcl.Sphere(float(sph.get("radius", 0)))
    return None


def _tf(pose: np.ndarray) -> fcl.Transform:
    return fcl.Transform(pose[:3, :3], pose[:3, 3])


class PairMeshCheck:
    """python-fcl self-collision check of one pair's configurations.

    Args:
        pk: The pair's kinematics (its hand's URDF supplies the collision geometry).

    Attributes:
        fingers: Per finger, the names of the links it moves that have collision geometry.
        structure: Structure links with collision geometry.
        pads: Per finger, its pad link (the pad pair is not checked).
        pairs: The checked link pairs.
    """

    def __init__(self, pk: PairKinematics) -> None:
        self.pk = pk
        model = pk.kin.model
        self._data = model.createData()
        root = ET.parse(pk.kin.urdf).getroot()
        urdf_dir = Path(pk.kin.urdf).parent
        shapes: dict[str, list[tuple[fcl.CollisionGeometry, np.ndarray]]] = {}
        for link in root.findall("link"):
            for col in link.findall("collision"):
                geo = col.find("geometry")
                g = None if geo is None else _geometry(geo, urdf_dir)
                if g is not None:
                    shapes.setdefault(link.get("name", ""), []).append(
                        (g, _origin(col.find("origin")))
                    )
        joint_child = {j.get("name"): j.find("child").get("link") for j in root.findall("joint")}
        joint_parent = {j.get("name"): j.find("parent").get("link") for j in root.findall("joint")}
        all_pair_joints = {j for p in pk.hand.pairs.values() for j in p.joints}

        def ancestors(link: str) -> set[str]:
            fid = model.getFrameId(link, pin.FrameType.BODY)
            j, out = model.frames[fid].parentJoint, set()
            while j > 0:
                out.add(model.names[j])
                j = model.parents[j]
            return out

        self.fingers: tuple[tuple[str, ...], ...] = tuple(
            tuple(sorted(n for n in shapes if ancestors(n) & set(fj)))
            for fj in pk.desc.finger_joints
        )
        self.structure: tuple[str, ...] = tuple(
            sorted(n for n in shapes if not ancestors(n) & all_pair_joints)
        )
        mounted = {(joint_parent[fj[0]], joint_child[fj[0]]) for fj in pk.desc.finger_joints if fj}
        from payload.retarget.collision import pad_links

        self.pads: tuple[str | None, ...] = pad_links(pk, frozenset(shapes))
        pads = set(self.pads) if None not in self.pads else set()
        pairs = [(a, b) for a in self.fingers[0] for b in self.fingers[1] if {a, b} != pads]
        for finger in self.fingers:
            for a in finger:
                pairs += [(a, s) for s in self.structure if (s, a) not in mounted]
        self.pairs: tuple[tuple[str, str], ...] = tuple(pairs)
        self._shapes = shapes
        self._fids = {
            n: model.getFrameId(n, pin.FrameType.BODY) for n in {x for p in pairs for x in p}
        }
        self._objects = {
            n: [(fcl.CollisionObject(g), off) for g, off in shapes[n]] for n in self._fids
        }

    @property
    def available(self) -> bool:
        """True when the URDF gives the pair any link pair to check."""
        return bool(self.pairs)

    def _pose(self, q: np.ndarray) -> None:
        model = self.pk.kin.model
        pin.framesForwardKinematics(model, self._data, self.pk.full_configuration(q))
        for n, objs in self._objects.items():
            m = self._data.oMf[self._fids[n]].homogeneous
            for obj, off in objs:
                obj.setTransform(_tf(m @ off))

    def in_collision(self, q: np.ndarray) -> bool:
        """True if any checked link pair touches at pair configuration q (shape (n,))."""
        self._pose(q)
        req, res = fcl.CollisionRequest(), fcl.CollisionResult()
        for a, b in self.pairs:
            for oa, _ in self._objects[a]:
                for ob, _ in self._objects[b]:
                    if fcl.collide(oa, ob, req, res) > 0:
                        return True
        return False

    def _local_points(self) -> dict[str, np.ndarray]:
        """Per checked link, points whose convex hull holds its collision geometry (link frame)."""
        pts = self.__dict__.get("_points")
        if pts is None:
            from payload.retarget.collision import _points, link_geometry

            geo = link_geometry(Path(self.pk.kin.urdf))
            pts = {n: np.vstack([_points(k, g, o) for k, g, o in geo[n]]) for n in self._fids}
            self.__dict__["_points"] = pts
        return pts

    def near_pairs(self, q: np.ndarray, cutoff: float) -> list[tuple[str, str]]:
        """Checked pairs whose posed bounding boxes come within ``cutoff`` [m] (the others
        are farther apart than that, so they can neither touch nor be nearer)."""
        self._pose(q)
        world = {}
        for n, corners in self._local_points().items():
            m = self._data.oMf[self._fids[n]]
            w = corners @ np.array(m.rotation).T + np.array(m.translation)
            world[n] = (w.min(axis=0) - cutoff / 2, w.max(axis=0) + cutoff / 2)
        return [
            (a, b)
            for a, b in self.pairs
            if np.all(world[a][0] <= world[b][1]) and np.all(world[b][0] <= world[a][1])
        ]

    def min_distance_near(self, q: np.ndarray, cutoff: float) -> float:
        """Smallest distance over the checked pairs at q [m], or ``cutoff`` if every pair
        is farther than that (bounding boxes first, FCL on the near pairs only)."""
        best = cutoff
        for a, b in self.near_pairs(q, cutoff):  # near_pairs poses the objects at q
            for oa, _ in self._objects[a]:
                for ob, _ in self._objects[b]:
                    d = fcl.distance(oa, ob, fcl.DistanceRequest(), fcl.DistanceResult())
                    best = min(best, float(max(d, 0.0)))
        return best

    def min_distance(self, q: np.ndarray) -> tuple[float, tuple[str, str]]:
        """Smallest distance over the checked pairs [m] (0 when touching) and that pair."""
        self._pose(q)
        best, where = np.inf, ("", "")
        for a, b in self.pairs:
            for oa, _ in self._objects[a]:
                for ob, _ in self._objects[b]:
                    d = fcl.distance(oa, ob, fcl.DistanceRequest(), fcl.DistanceResult())
                    if d < best:
                        best, where = float(max(d, 0.0)), (a, b)
        return best, where
