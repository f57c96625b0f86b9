"""Reach of the deployed fingers: workspaces, pair spans, rail spacing, grasp check.

The joint space is sampled uniformly inside the limits (the 17 manipulation
coordinates, stage deployed) and every configuration goes through a batched,
vectorised forward kinematics derived from the kinematic tree. Self-collision of
every sample is checked by MuJoCo on a model built from the convex pieces of the
link solids (the same pieces python-fcl uses for the stowed checks), with the
vehicle body beside it.

A pair's span is eq. 2's fingertip separation l = |p2 - p1|. The two fingers of a
pair hang from the same link (A, C from the stage; B, D from the carriage), so
every combination of one finger's samples with the other's is a configuration of
the pair: the span range is the range of distances between the two fingertip
clouds (a k-d tree for the nearest, the hull vertices for the farthest), refined
by a bounded local search from the extreme pair.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import mujoco
import numpy as np
from scipy import optimize
from scipy.spatial import ConvexHull, cKDTree

from payload.design.params import FINGER_JOINTS, FINGERS
from payload.design.tree import ALL_JOINTS, KinematicTree, rpy_matrix
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.vehicle import Vehicle, display_path
from payload.errors import PayloadError
from payload.rotations import matrix_to_quat

PAIRS: dict[str, tuple[str, str]] = {"L": ("A", "C"), "R": ("B", "D")}
"""Finger pairs: the left hand drives L = (A, C), the right hand R = (B, D)."""

OPPOSITION_CONE = np.radians(30.0)
"""Largest angle between a pinch axis and the across-array (y) axis for opposing pads [rad]."""

CHUNK = 20_000
"""Configurations per batch of the vectorised forward kinematics."""

Progress = Callable[[str, float], None]


def _quiet(stage: str, fraction: float) -> None:
    return None


class ReachError(PayloadError):
    """Bad input to the reach analysis (a sample count, a thickness, a pair)."""


class GraspFeature(NamedTuple):
    """A thickness of the Cargo Transfer Bag an opposing pair may close on.

    Attributes:
        name: What it is.
        thickness: Object thickness between the pads [m].
        source: Where the number comes from (``ASSUMPTION`` when it is not measured).
    """

    name: str
    thickness: float
    source: str


CTB_FEATURES: tuple[GraspFeature, ...] = (
    GraspFeature("handle strap (flat webbing)", 0.003, "ASSUMPTION: soft strap, ~3 mm"),
    GraspFeature("handle strap folded double", 0.006, "ASSUMPTION"),
    GraspFeature("bag edge: fabric wall with piping", 0.010, "ASSUMPTION"),
    GraspFeature("bag edge: two walls at a seam", 0.020, "ASSUMPTION"),
    GraspFeature("half CTB across its 23.5 cm side", 0.235, "docs/sources.md (NASA packing data)"),
    GraspFeature("rigid CTB model across its 25 cm side", 0.25, "docs/sources.md (pyastrobee)"),
)
"""Default features checked by the grasp check (``--thickness`` adds more)."""


# ----------------------------------------------------------------- batched FK


def batch_link_poses(
    tree: KinematicTree, q: Mapping[str, np.ndarray], links: Sequence[str] | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Vectorised forward kinematics of the tree for a batch of configurations.

    Args:
        tree: The kinematic tree.
        q: Joint name -> values, shape (n,) each (a missing joint is 0) [rad or m].
        links: Links to return (default: all).

    Returns:
        Link name -> (rotations, shape (n, 3, 3); positions, shape (n, 3) [m]), in the
        payload frame.
    """
    n = len(next(iter(q.values()))) if q else 1
    names = list(tree.link_map) if links is None else list(links)
    parent_of = {j.child: j for j in tree.joints}
    needed: set[str] = set()
    for name in names:
        while name in parent_of and name not in needed:
            needed.add(name)
            name = parent_of[name].parent
    rot = {tree.root: np.broadcast_to(np.eye(3), (n, 3, 3))}
    pos = {tree.root: np.zeros((n, 3))}
    for j in tree.joints:
        if j.child not in needed:
            continue
        r_p, p_p = rot[j.parent], pos[j.parent]
        r_o = rpy_matrix(j.rpy)
        r_po = r_p @ r_o
        p_c = p_p + r_p @ np.asarray(j.xyz, dtype=float)
        values = q.get(j.name)
        axis = np.asarray(j.axis, dtype=float)
        if j.kind == "revolute" and values is not None:
            k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            s, c = np.sin(values)[:, None, None], np.cos(values)[:, None, None]
            r_m = np.eye(3) + s * k + (1 - c) * (k @ k)
            rot[j.child] = r_po @ r_m
        else:
            rot[j.child] = r_po
            if j.kind == "prismatic" and values is not None:
                p_c = p_c + (r_po @ axis) * np.asarray(values)[:, None]
        pos[j.child] = p_c
    return {name: (rot[name], pos[name]) for name in names}


def batch_frames(
    tree: KinematicTree, q: Mapping[str, np.ndarray], frames: Sequence[str]
) -> dict[str, np.ndarray]:
    """Payload-frame positions of named frames for a batch of configurations.

    Args:
        tree: The kinematic tree.
        q: Joint name -> values, shape (n,) each [rad or m].
        frames: Frame names (e.g. ``A_tip``).

    Returns:
        Frame name -> positions, shape (n, 3) [m].
    """
    fmap = {f.name: f for f in tree.frames}
    missing = [f for f in frames if f not in fmap]
    if missing:
        raise ReachError(f"unknown frame(s): {', '.join(missing)}")
    poses = batch_link_poses(tree, q, sorted({fmap[f].parent for f in frames}))
    out = {}
    for name in frames:
        fr = fmap[name]
        r, p = poses[fr.parent]
        out[name] = p + r @ np.asarray(fr.xyz, dtype=float)
    return out


def sample_configurations(
    tree: KinematicTree, n: int, rng: np.random.Generator, stage: float | None = None
) -> np.ndarray:
    """Uniform samples of the 17 manipulation joints inside their limits.

    Args:
        tree: The kinematic tree.
        n: Number of configurations.
        rng: Random generator.
        stage: Deployment coordinate of every sample (default: fully deployed) [m].

    Returns:
        Shape (n, 18), columns in :data:`ALL_JOINTS` order [rad, m].
    """
    lo = np.array([tree.joint_map[j].lower for j in ALL_JOINTS])
    hi = np.array([tree.joint_map[j].upper for j in ALL_JOINTS])
    out = lo + (hi - lo) * rng.random((n, len(ALL_JOINTS)))
    out[:, -1] = tree.joint_map["stage"].upper if stage is None else stage
    return out


def columns(samples: np.ndarray) -> dict[str, np.ndarray]:
    """Configuration rows (:data:`ALL_JOINTS` order) as joint name -> column."""
    return {j: samples[:, i] for i, j in enumerate(ALL_JOINTS)}


def fingertips(tree: KinematicTree, samples: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
    """Fingertip positions of every sample, in chunks.

    Args:
        tree: The kinematic tree.
        samples: Shape (n, 18), :data:`ALL_JOINTS` order.
        chunk: Batch size.

    Returns:
        Shape (n, 4, 3), fingers A, B, C, D, payload frame [m].
    """
    out = np.empty((len(samples), len(FINGERS), 3))
    frames = [f"{f}_tip" for f in FINGERS]
    for start in range(0, len(samples), chunk):
        block = samples[start : start + chunk]
        tips = batch_frames(tree, columns(block), frames)
        for i, name in enumerate(frames):
            out[start : start + chunk, i] = tips[name]
    return out


# ----------------------------------------------------------------- collisions


class CollisionModel:
    """MuJoCo model of the payload's convex pieces and the vehicle body, for batch checks.

    Every convex piece of every link becomes a mesh geom (MuJoCo collides the convex
    hull, which is the piece) or a sphere geom; parent/child bodies never collide (MuJoCo's parent
    filter), which leaves out exactly the adjacent pairs the stowed check excludes.
    The vehicle body is five boxes in the world body.
    """

    def __init__(self, geom: PayloadGeometry, vehicle: Vehicle) -> None:
        tree = geom.tree
        spec = mujoco.MjSpec()
        spec.modelname = "payload_collision"
        bodies = {tree.root: spec.worldbody.add_body(name=tree.root)}
        self._payload_bodies = [tree.root]
        for j in tree.joints:
            body = bodies[j.parent].add_body(name=j.child, pos=list(j.xyz))
            body.quat = _quat(rpy_matrix(j.rpy))
            if j.kind in ("revolute", "prismatic"):
                jt = (
                    mujoco.mjtJoint.mjJNT_HINGE
                    if j.kind == "revolute"
                    else mujoco.mjtJoint.mjJNT_SLIDE
                )
                body.add_joint(name=j.name, type=jt, axis=list(j.axis), range=[j.lower, j.upper])
            bodies[j.child] = body
            self._payload_bodies.append(j.child)
        for name in geom.links:
            for k, piece in enumerate(geom.pieces[name]):
                if piece.sphere is not None:
                    bodies[name].add_geom(
                        type=mujoco.mjtGeom.mjGEOM_SPHERE,
                        size=[piece.sphere[1], 0.0, 0.0],
                        pos=list(piece.sphere[0]),
                        contype=1,
                        conaffinity=1,
                    )
                    continue
                mesh = spec.add_mesh(name=f"{name}_{k}", uservert=piece.vertices.ravel().tolist())
                bodies[name].add_geom(
                    type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name, contype=1, conaffinity=1
                )
        for k, (lo, hi) in enumerate(vehicle.body_boxes()):
            spec.worldbody.add_geom(
                name=f"vehicle_{k}",
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=list((hi - lo) / 2),
                pos=list((hi + lo) / 2),
                contype=1,
                conaffinity=1,
            )
        for j in tree.joints:
            spec.add_exclude(bodyname1=j.parent, bodyname2=j.child)
        spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_GRAVITY)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in ALL_JOINTS])
        self.body_names = [m.body(b).name for b in range(m.nbody)]

    def check(self, samples: np.ndarray, progress: Progress = _quiet, workers: int = 1) -> Contacts:
        """Every contact of every configuration.

        Args:
            samples: Shape (n, 18), :data:`ALL_JOINTS` order.
            progress: Progress callback.
            workers: Processes (forked, on Linux; elsewhere and for fewer than 10,000
                samples the check runs in this process).

        Returns:
            The :class:`Contacts` (body pairs in contact, per sample).
        """
        n = len(samples)
        bounds = np.linspace(0, n, max(2, min(100, n // 500)) + 1).astype(int)
        ranges = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
        parts = []
        if workers > 1 and n >= 10_000 and sys.platform.startswith("linux"):
            global _ACTIVE
            _ACTIVE = (self, samples)
            try:
                with mp.get_context("fork").Pool(workers) as pool:
                    for k, part in enumerate(pool.imap_unordered(_check_range, ranges)):
                        parts.append(part)
                        progress("collisions", (k + 1) / len(ranges))
            finally:
                _ACTIVE = None
        else:
            for k, (a, b) in enumerate(ranges):
                parts.append(self._check_range(samples, a, b))
                progress("collisions", (k + 1) / len(ranges))
        rows = np.concatenate(parts) if parts else np.zeros((0, 3), dtype=int)
        rows = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))]
        return Contacts(n, rows[:, 0], rows[:, 1], rows[:, 2], tuple(self.body_names))

    def _check_range(self, samples: np.ndarray, start: int, stop: int) -> np.ndarray:
        """Rows (sample, body a, body b) of distinct body pairs in contact, a < b."""
        m, d = self.model, self.data
        qpos = np.zeros(m.nq)
        adr = self._qadr
        found = []
        for i in range(start, stop):
            qpos[adr] = samples[i]
            d.qpos[:] = qpos
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            if d.ncon:
                g = d.contact.geom[: d.ncon]
                found.append(np.column_stack([np.full(len(g), i), m.geom_bodyid[g]]))
        if not found:
            return np.zeros((0, 3), dtype=int)
        rows = np.concatenate(found)
        rows[:, 1:] = np.sort(rows[:, 1:], axis=1)
        return np.unique(rows, axis=0)

    def pair_free(self, row: np.ndarray, links: Sequence[str], ignore: Sequence[str]) -> bool:
        """No contact of ``links`` with anything but ``ignore`` in one configuration (18,)."""
        return not bool(self.check(np.atleast_2d(row)).involving(links, ignore)[0])


class Contacts(NamedTuple):
    """Body pairs in contact in a batch of configurations (one row per sample and pair).

    Attributes:
        n: Number of configurations.
        index: Configuration of each row, shape (m,).
        body_a: Lower body id of each row, shape (m,) (0 is the vehicle).
        body_b: Higher body id, shape (m,).
        body_names: Body id -> name (``world`` is the vehicle body).
    """

    n: int
    index: np.ndarray
    body_a: np.ndarray
    body_b: np.ndarray
    body_names: tuple[str, ...]

    def flags(self, rows: np.ndarray) -> np.ndarray:
        """Configurations with at least one of the selected rows, shape (n,)."""
        out = np.zeros(self.n, dtype=bool)
        out[self.index[rows]] = True
        return out

    def self_collision(self) -> np.ndarray:
        """Configurations where two payload links touch, shape (n,)."""
        return self.flags(self.body_a != 0)

    def vehicle_contact(self) -> np.ndarray:
        """Configurations where a payload link touches the vehicle body, shape (n,)."""
        return self.flags(self.body_a == 0)

    def involving(self, links: Sequence[str], ignore: Sequence[str] = ()) -> np.ndarray:
        """Configurations where one of ``links`` touches anything but ``ignore``, (n,)."""
        own = np.zeros(len(self.body_names), dtype=bool)
        own[[self.body_names.index(n) for n in links]] = True
        skip = np.zeros(len(self.body_names), dtype=bool)
        skip[[self.body_names.index(n) for n in ignore]] = True
        a, b = self.body_a, self.body_b
        return self.flags((own[a] & ~skip[b]) | (own[b] & ~skip[a]))

    def pair_counts(self) -> dict[tuple[str, str], int]:
        """Link pair (``world`` = the vehicle) -> configurations where they touch."""
        out: dict[tuple[str, str], int] = {}
        pairs, counts = np.unique(
            np.column_stack([self.body_a, self.body_b]), axis=0, return_counts=True
        )
        for (a, b), c in zip(pairs, counts):
            name_a = "vehicle" if a == 0 else self.body_names[a]
            out[(name_a, self.body_names[b])] = int(c)
        return out


_ACTIVE: tuple[CollisionModel, np.ndarray] | None = None
"""The model and samples a forked worker checks (set by the parent before forking)."""


def _check_range(bounds: tuple[int, int]) -> np.ndarray:
    assert _ACTIVE is not None
    model, samples = _ACTIVE
    return model._check_range(samples, *bounds)


def _quat(r: np.ndarray) -> list[float]:
    return matrix_to_quat(r).tolist()


# ----------------------------------------------------------------- workspace, spans


class Workspace(NamedTuple):
    """A fingertip's sampled, reachable workspace.

    Attributes:
        finger: Finger name.
        points: Reachable fingertip positions, shape (k, 3), payload frame [m].
        hull_volume: Volume of the points' convex hull [m^3].
        lower: Lower bounding-box corner, shape (3,) [m].
        upper: Upper bounding-box corner, shape (3,) [m].
        below_vehicle: Largest depth of the fingertip below the vehicle's bottom face [m].
        reachable: Fraction of the samples kept (the finger touching nothing).
    """

    finger: str
    points: np.ndarray
    hull_volume: float
    lower: np.ndarray
    upper: np.ndarray
    below_vehicle: float
    reachable: float


def workspace(
    finger: str, points: np.ndarray, bottom_z: float, keep: np.ndarray | None = None
) -> Workspace:
    """Hull volume, bounds and depth below the vehicle of a fingertip cloud.

    Args:
        finger: Finger name.
        points: Shape (n, 3) [m].
        bottom_z: z of the vehicle's bottom face [m].
        keep: Samples to keep, shape (n,) (default: all).
    """
    frac = 1.0 if keep is None else float(np.mean(keep))
    pts = points if keep is None else points[keep]
    if len(pts) < 4:
        raise ReachError(f"finger {finger}: fewer than 4 reachable samples; sample more")
    hull = ConvexHull(pts)
    return Workspace(
        finger,
        pts,
        float(hull.volume),
        pts.min(axis=0),
        pts.max(axis=0),
        float(bottom_z - pts[:, 2].min()),
        frac,
    )


class SpanRange(NamedTuple):
    """Range of a pair's fingertip separation (eq. 2's l) over its joint space.

    Attributes:
        pair: Pair name.
        minimum: Smallest separation [m].
        maximum: Largest separation [m].
        q_min: The 8 pair joints (finger 1 then finger 2) at the minimum [rad].
        q_max: The 8 pair joints at the maximum [rad].
    """

    pair: str
    minimum: float
    maximum: float
    q_min: np.ndarray
    q_max: np.ndarray


def pair_joints(pair: str) -> list[str]:
    """The 8 joints of a pair: finger 1's four, then finger 2's."""
    if pair not in PAIRS:
        raise ReachError(f"unknown pair {pair!r} (expected one of: {', '.join(PAIRS)})")
    return [f"{f}_{j}" for f in PAIRS[pair] for j in FINGER_JOINTS]


def grasp_base(tree: KinematicTree) -> dict[str, float]:
    """Rail and stage of every grasp witness: rail at home, stage fully deployed [m]."""
    return {"rail": float(tree.design.home.rail), "stage": float(tree.joint_map["stage"].upper)}


def _pair_tips(tree: KinematicTree, pair: str, q8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fingertips of a pair for joint rows of shape (n, 8), at :func:`grasp_base`."""
    names = pair_joints(pair)
    q = {j: q8[:, i] for i, j in enumerate(names)}
    q.update({j: np.full(len(q8), v) for j, v in grasp_base(tree).items()})
    tips = batch_frames(tree, q, [f"{f}_tip" for f in PAIRS[pair]])
    f1, f2 = PAIRS[pair]
    return tips[f"{f1}_tip"], tips[f"{f2}_tip"]


def _finger_tips(tree: KinematicTree, finger: str, q4: np.ndarray) -> np.ndarray:
    """Fingertip of one finger for joint rows of shape (n, 4), rail and stage at 0 [m]."""
    names = [f"{finger}_{j}" for j in FINGER_JOINTS]
    return batch_frames(tree, {j: q4[:, i] for i, j in enumerate(names)}, [f"{finger}_tip"])[
        f"{finger}_tip"
    ]


def _check_common_parent(tree: KinematicTree, pair: str) -> None:
    f1, f2 = PAIRS[pair]
    p1, p2 = tree.joint_map[f"{f1}_mcp_flex"].parent, tree.joint_map[f"{f2}_mcp_flex"].parent
    if p1 != p2:
        raise ReachError(f"pair {pair}: fingers {f1} and {f2} hang from different links")


def span_range(
    tree: KinematicTree,
    pair: str,
    q1: np.ndarray,
    q2: np.ndarray,
    refine: bool = True,
) -> SpanRange:
    """Smallest and largest fingertip separation of a pair over every combination.

    Args:
        tree: The kinematic tree.
        pair: ``L`` or ``R``.
        q1: Finger 1 joint samples, shape (n1, 4) [rad].
        q2: Finger 2 joint samples, shape (n2, 4) [rad].
        refine: Refine both extremes by a bounded local search (L-BFGS-B).

    Returns:
        The :class:`SpanRange` (over the n1 x n2 combinations when not refined).
    """
    _check_common_parent(tree, pair)
    f1, f2 = PAIRS[pair]
    p1 = _finger_tips(tree, f1, q1)
    p2 = _finger_tips(tree, f2, q2)
    # nearest: a k-d tree over finger 2's cloud
    dist, idx = cKDTree(p2).query(p1, k=1, workers=-1)
    i_min = int(np.argmin(dist))
    j_min = int(idx[i_min])
    # farthest: attained at hull vertices of both clouds (a convex function of each point)
    h1 = _hull_indices(p1)
    h2 = _hull_indices(p2)
    d = np.linalg.norm(p1[h1][:, None, :] - p2[h2][None, :, :], axis=2)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    i_max, j_max = int(h1[a]), int(h2[b])
    x_min = np.concatenate([q1[i_min], q2[j_min]])
    x_max = np.concatenate([q1[i_max], q2[j_max]])
    lo_d, hi_d = float(dist[i_min]), float(d[a, b])
    if refine:
        x_min, lo_d = _refine_span(tree, pair, x_min, +1.0, lo_d)
        x_max, hi_d = _refine_span(tree, pair, x_max, -1.0, hi_d)
    return SpanRange(pair, lo_d, hi_d, x_min, x_max)


def _hull_indices(points: np.ndarray) -> np.ndarray:
    if len(points) < 5:
        return np.arange(len(points))
    try:
        return ConvexHull(points).vertices
    except Exception:  # degenerate (coplanar) clouds: every point is a candidate
        return np.arange(len(points))


def span_of(tree: KinematicTree, pair: str, q8: np.ndarray) -> np.ndarray:
    """Fingertip separation for pair joint rows of shape (n, 8) [m], shape (n,)."""
    p1, p2 = _pair_tips(tree, pair, np.atleast_2d(q8))
    return np.linalg.norm(p2 - p1, axis=1)


def _refine_span(
    tree: KinematicTree, pair: str, x0: np.ndarray, sign: float, value: float
) -> tuple[np.ndarray, float]:
    names = pair_joints(pair)
    bounds = [(tree.joint_map[j].lower, tree.joint_map[j].upper) for j in names]
    h = 1e-6

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        rows = np.vstack([x, x + h * np.eye(len(x))])
        s = span_of(tree, pair, rows)
        return float(sign * s[0]), sign * (s[1:] - s[0]) / h

    res = optimize.minimize(
        fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 60}
    )
    x = np.clip(res.x, [b[0] for b in bounds], [b[1] for b in bounds])
    s = float(span_of(tree, pair, x)[0])
    if sign * s < sign * value:
        return x, s
    return x0, value


def rail_spacing(tree: KinematicTree) -> tuple[float, float]:
    """Pair spacing along the rail axis at the two rail limits [m].

    The spacing is the x distance between the pairs' centres (the midpoints of the
    pairs' MCP flexion axes, pair R minus pair L).
    """
    rail = tree.joint_map["rail"]
    q = {"rail": np.array([rail.lower, rail.upper])}
    knuckles = [f"{f}_knuckle" for f in FINGERS]
    poses = batch_link_poses(tree, q, knuckles)
    centre = {
        pair: 0.5 * (poses[f"{a}_knuckle"][1] + poses[f"{b}_knuckle"][1])
        for pair, (a, b) in PAIRS.items()
    }
    dx = centre["R"][:, 0] - centre["L"][:, 0]
    return float(dx.min()), float(dx.max())


# ----------------------------------------------------------------- grasp check


class GraspResult(NamedTuple):
    """Whether a pair can close on a thickness, with a witness configuration.

    Attributes:
        feature: The feature checked.
        pair: Pair name.
        closes: A witness exists.
        span: The witness's fingertip separation [m] (NaN when none).
        angle: The witness's pinch-axis angle from the across-array axis [rad].
        depth: How far the witness's higher pad stays below the vehicle's bottom face [m].
        q: The witness's 8 pair joints [rad] (empty when none); the rail and stage are
            at :func:`grasp_base` (rail at home, stage deployed).
    """

    feature: GraspFeature
    pair: str
    closes: bool
    span: float
    angle: float
    depth: float
    q: np.ndarray


def opposition(p1: np.ndarray, p2: np.ndarray, side_sign: float) -> np.ndarray:
    """Angle between the pinch axis p1 -> p2 and the across-array direction [rad], (n,).

    Args:
        p1: Finger 1 tips, shape (n, 3) [m].
        p2: Finger 2 tips, shape (n, 3) [m].
        side_sign: +1 when finger 2 sits on the +y side, -1 when on the -y side.
    """
    d = p2 - p1
    cos = side_sign * d[:, 1] / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _pinch(
    tree: KinematicTree, pair: str, rows: np.ndarray, side: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Span [m], cosine of the opposition angle and higher tip z [m] for (n, 8) rows."""
    p1, p2 = _pair_tips(tree, pair, rows)
    d = p2 - p1
    span = np.linalg.norm(d, axis=1)
    cos = side * d[:, 1] / np.maximum(span, 1e-12)
    return span, cos, np.maximum(p1[:, 2], p2[:, 2])


def symmetric_samples(
    tree: KinematicTree, pair: str, n: int, rng: np.random.Generator
) -> np.ndarray:
    """Pair configurations with both fingers at the same joint values, shape (n, 8) [rad].

    The two fingers of a pair face each other (one turned half a turn about z), so
    equal joint values place the fingertips symmetrically about the vertical axis
    between the two MCP joints: a family of opposing pinches that uniform sampling of
    the 8 joints rarely visits.
    """
    names = pair_joints(pair)[:4]
    lo = np.array([tree.joint_map[j].lower for j in names])
    hi = np.array([tree.joint_map[j].upper for j in names])
    half = lo + (hi - lo) * rng.random((n, 4))
    return np.hstack([half, half])


def grasp_check(
    tree: KinematicTree,
    pair: str,
    candidates: np.ndarray,
    vehicle: Vehicle,
    features: Sequence[GraspFeature],
    is_free: Callable[[np.ndarray], bool] | None = None,
    window: float = 3e-3,
    tolerance: float = 1e-4,
    attempts: int = 8,
) -> list[GraspResult]:
    """Which thicknesses an opposing pair can close on, below the vehicle.

    A pair closes on thickness t when it has a witness: a configuration inside the
    joint limits with its pads opposing (pinch axis within :data:`OPPOSITION_CONE` of
    the across-array axis), both pads wholly below the vehicle's bottom face (rail at
    home, stage deployed: :func:`grasp_base`), a
    fingertip separation within ``tolerance`` of t plus the two pad radii, and no
    contact of the pair's links (``is_free``). The candidates whose separation lies
    within ``window`` of the target are moved onto it by a bounded least-squares step
    over the pair's 8 joints, then checked.

    Args:
        tree: The kinematic tree.
        pair: ``L`` or ``R``.
        candidates: Pair joint rows (finger 1 then finger 2), shape (m, 8) [rad].
        vehicle: The vehicle.
        features: Thicknesses to check.
        is_free: Collision check of the pair's 8 joints (default: none).
        window: Largest separation error of a starting candidate [m].
        tolerance: Largest separation error of a witness [m].
        attempts: Candidates tried per feature.

    Returns:
        One :class:`GraspResult` per feature (the nearest opposing candidate when none
        closes).
    """
    r = tree.design.finger.pad.radius
    bounds = np.array(
        [[tree.joint_map[j].lower, tree.joint_map[j].upper] for j in pair_joints(pair)]
    )
    side = _side(tree, pair)
    span, cos, z = _pinch(tree, pair, candidates, side)
    ok = (cos >= np.cos(OPPOSITION_CONE)) & (z + r <= vehicle.bottom_z)
    cand, span, cos, z = candidates[ok], span[ok], cos[ok], z[ok]
    out = []
    for feat in features:
        target = feat.thickness + 2 * r
        if len(cand) == 0:
            out.append(GraspResult(feat, pair, False, np.nan, np.nan, np.nan, np.empty(0)))
            continue
        order = np.argsort(np.abs(span - target))
        found = None
        for i in order[:attempts]:
            if abs(span[i] - target) > window:
                break
            res = optimize.least_squares(
                lambda x, target=target: _pinch(tree, pair, x[None, :], side)[0] - target,
                cand[i],
                bounds=(bounds[:, 0], bounds[:, 1]),
                max_nfev=30,
                xtol=1e-12,
            )
            q8 = np.clip(res.x, bounds[:, 0], bounds[:, 1])
            (s,), (c,), (zz,) = _pinch(tree, pair, q8[None, :], side)
            ang = float(np.arccos(np.clip(c, -1.0, 1.0)))
            depth = float(vehicle.bottom_z - (zz + r))
            if abs(s - target) > tolerance or ang > OPPOSITION_CONE or depth < 0:
                continue
            if is_free is not None and not is_free(q8):
                continue
            found = GraspResult(feat, pair, True, float(s), ang, depth, q8)
            break
        if found is None:
            i = order[0]
            found = GraspResult(
                feat,
                pair,
                False,
                float(span[i]),
                float(np.arccos(np.clip(cos[i], -1, 1))),
                float(vehicle.bottom_z - (z[i] + r)),
                cand[i],
            )
        out.append(found)
    return out


def _side(tree: KinematicTree, pair: str) -> float:
    """+1 when finger 2 of the pair sits on the +y side of finger 1, else -1."""
    f1, f2 = PAIRS[pair]
    y1 = tree.joint_map[f"{f1}_mcp_flex"].xyz[1]
    y2 = tree.joint_map[f"{f2}_mcp_flex"].xyz[1]
    return 1.0 if y2 > y1 else -1.0


# ----------------------------------------------------------------- the analysis


@dataclass
class PairReach:
    """Everything reported for one pair.

    Attributes:
        name: ``L`` or ``R``.
        fingers: The two fingers.
        span: Range of eq. 2's separation over the pair's joint space.
        pad_contact: Separation at which the two pads touch (twice the pad radius) [m].
        free_fraction: Samples in which the pair's links touch nothing (the other pair's
            fingers aside, whose posture is independent).
        free_span: (min, max) separation over those samples [m].
        opposed_span: (min, max) over those samples with opposing pads below the
            vehicle [m] (NaN when none).
        grasps: Grasp-check results.
        free: Per-sample flags of the pair touching nothing, shape (n,).
    """

    name: str
    fingers: tuple[str, str]
    span: SpanRange
    pad_contact: float
    free_fraction: float
    free_span: tuple[float, float]
    opposed_span: tuple[float, float]
    grasps: list[GraspResult]
    free: np.ndarray

    @property
    def span_min(self) -> float:
        """Smallest separation with the pads not interpenetrating [m]."""
        return max(self.span.minimum, self.pad_contact)


@dataclass
class ReachAnalysis:
    """The reach report's content.

    Attributes:
        vehicle: The vehicle.
        design_source: The design file.
        samples: Number of sampled configurations.
        seed: Random seed.
        workspaces: Per finger.
        pairs: Per pair.
        rail_spacing: (min, max) pair spacing over the rail [m].
        contacts: Every contact of every sample.
        tips: Fingertips of every sample, shape (n, 4, 3) [m].
        home_below_vehicle: Fingertip depth below the bottom face in the home posture [m].
        timings: Stage -> seconds.
        seconds: Wall time of the analysis [s].
    """

    vehicle: Vehicle
    design_source: str
    samples: int
    seed: int
    workspaces: list[Workspace]
    pairs: list[PairReach]
    rail_spacing: tuple[float, float]
    contacts: Contacts
    tips: np.ndarray
    home_below_vehicle: float
    timings: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def collision_free_fraction(self) -> float:
        """Fraction of samples in which no two payload links touch."""
        return float(1.0 - self.contacts.self_collision().mean())

    @property
    def below_vehicle(self) -> float:
        """Largest fingertip depth below the vehicle's bottom face over all samples [m]."""
        return max(w.below_vehicle for w in self.workspaces)

    def assumptions(self) -> list[str]:
        v = self.vehicle
        size = " x ".join(f"{s * 1e3:.0f}" for s in v.bay_size)
        return [
            f"ASSUMPTION (bay size): {v.assumption}",
            f"bay envelope {size} mm from {v.source}; the vehicle's bottom face is at "
            f"z = {v.bottom_z * 1e3:.0f} mm (payload frame)",
            "joints sampled uniformly inside their limits, stage fully deployed",
            "collisions use the convex hull of every part of the link solids (MuJoCo); "
            "parent/child links are never checked",
            f"opposing pads: pinch axis within {np.degrees(OPPOSITION_CONE):.0f} deg of the "
            "across-array (y) axis, both pads wholly below the vehicle's bottom face",
            "grasp witnesses: rail at its home position, stage fully deployed",
            "CTB strap and edge thicknesses marked ASSUMPTION are not measured values",
        ]

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``payload report reach --json`` (mm, SI seconds)."""
        return reach_json(self)


def _mm(x: float) -> float | None:
    return round(float(x) * 1e3, 2) if np.isfinite(x) else None


def reach_json(a: ReachAnalysis) -> dict[str, Any]:
    """The reach analysis as plain data (lengths in mm)."""
    mm = _mm
    pairs = {}
    for p in a.pairs:
        pairs[p.name] = {
            "fingers": list(p.fingers),
            "span_min_mm": mm(p.span_min),
            "span_max_mm": mm(p.span.maximum),
            "span_min_geometric_mm": mm(p.span.minimum),
            "pad_contact_mm": mm(p.pad_contact),
            "collision_free_fraction": round(p.free_fraction, 4),
            "collision_free_span_mm": {"min": mm(p.free_span[0]), "max": mm(p.free_span[1])},
            "opposed_span_mm": {"min": mm(p.opposed_span[0]), "max": mm(p.opposed_span[1])},
            "grasp": [
                {
                    "feature": g.feature.name,
                    "thickness_mm": mm(g.feature.thickness),
                    "source": g.feature.source,
                    "closes": bool(g.closes),
                    "span_mm": mm(g.span),
                    "opposition_deg": round(float(np.degrees(g.angle)), 1)
                    if np.isfinite(g.angle)
                    else None,
                    "below_vehicle_mm": mm(g.depth),
                    "q": [round(float(v), 4) for v in g.q],
                }
                for g in p.grasps
            ],
        }
    selfc, vehc = a.contacts.self_collision(), a.contacts.vehicle_contact()
    return {
        "design": display_path(a.design_source),
        "samples": int(a.samples),
        "seed": int(a.seed),
        "seconds": round(a.seconds, 2),
        "pairs": pairs,
        "rail_spacing_mm": {"min": mm(a.rail_spacing[0]), "max": mm(a.rail_spacing[1])},
        "below_vehicle_mm": mm(a.below_vehicle),
        "collision_free_fraction": round(a.collision_free_fraction, 4),
        "vehicle_contact_fraction": round(float(vehc.mean()), 4),
        "free_fraction_with_vehicle": round(float((~selfc & ~vehc).mean()), 4),
        "home_below_vehicle_mm": mm(a.home_below_vehicle),
        "fingers": {
            w.finger: {
                "hull_volume_cm3": round(w.hull_volume * 1e6, 1),
                "bbox_min_mm": [mm(v) for v in w.lower],
                "bbox_max_mm": [mm(v) for v in w.upper],
                "below_vehicle_mm": mm(w.below_vehicle),
                "reachable_fraction": round(w.reachable, 4),
            }
            for w in a.workspaces
        },
        "collision_pairs": [
            {"links": list(k), "fraction": round(v / a.samples, 4)}
            for k, v in sorted(a.contacts.pair_counts().items(), key=lambda kv: -kv[1])[:12]
        ],
        "timings_s": {k: round(v, 2) for k, v in a.timings.items()},
        "assumptions": a.assumptions(),
    }


def finger_link_names(tree: KinematicTree, finger: str) -> list[str]:
    """The links moved by a finger's joints."""
    names = {f"{finger}_{j}" for j in FINGER_JOINTS}
    moved: set[str] = set()
    for j in tree.joints:
        if j.name in names or j.parent in moved:
            moved.add(j.child)
    return [link.name for link in tree.links if link.name in moved]


def analyse_reach(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    samples: int = 100_000,
    seed: int = 0,
    features: Sequence[GraspFeature] = CTB_FEATURES,
    workers: int | None = None,
    progress: Progress = _quiet,
) -> ReachAnalysis:
    """Sample the deployed joint space and measure reach, spans and collisions.

    Args:
        geom: Collision geometry of the design.
        vehicle: The vehicle.
        samples: Number of configurations (at least 1,000).
        seed: Random seed.
        features: Thicknesses for the grasp check.
        workers: Processes for the collision checks (default: up to 2, the CPUs there are).
        progress: Progress callback.

    Returns:
        The :class:`ReachAnalysis`.

    Raises:
        ReachError: Too few samples, or a negative thickness.
    """
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1000:
        raise ReachError(f"samples must be an integer of at least 1000 (got {samples!r})")
    for f in features:
        if not (np.isfinite(f.thickness) and f.thickness >= 0):
            raise ReachError(f"thickness of {f.name!r} must be >= 0 m (got {f.thickness})")
    tree = geom.tree
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    rng = np.random.default_rng(seed)
    progress("sampling", 0.0)
    q = sample_configurations(tree, int(samples), rng)
    tips = fingertips(tree, q)
    timings["batched FK"] = time.perf_counter() - t0

    t = time.perf_counter()
    model = CollisionModel(geom, vehicle)
    if workers is None:
        workers = min(2, os.cpu_count() or 1)
    contacts = model.check(q, progress, workers=workers)
    timings["collisions"] = time.perf_counter() - t

    t = time.perf_counter()
    spaces = []
    links = {f: finger_link_names(tree, f) for f in FINGERS}
    for i, f in enumerate(FINGERS):
        others = [n for g in FINGERS if g != f for n in links[g]]
        keep = ~contacts.involving(links[f], ignore=others)
        spaces.append(workspace(f, tips[:, i], vehicle.bottom_z, keep))
        progress("workspaces", (i + 1) / len(FINGERS))
    timings["workspaces"] = time.perf_counter() - t

    t = time.perf_counter()
    r = tree.design.finger.pad.radius
    pairs = []
    for name, (f1, f2) in PAIRS.items():
        c1 = [ALL_JOINTS.index(f"{f1}_{j}") for j in FINGER_JOINTS]
        c2 = [ALL_JOINTS.index(f"{f2}_{j}") for j in FINGER_JOINTS]
        span = span_range(tree, name, q[:, c1], q[:, c2])
        own = finger_link_names(tree, f1) + finger_link_names(tree, f2)
        others = [n for g in FINGERS if g not in (f1, f2) for n in finger_link_names(tree, g)]
        free = ~contacts.involving(own, ignore=others)
        i1, i2 = FINGERS.index(f1), FINGERS.index(f2)
        ell = np.linalg.norm(tips[:, i2] - tips[:, i1], axis=1)
        free_span = _range(ell[free])
        side = _side(tree, name)
        ang = opposition(tips[:, i1], tips[:, i2], side)
        top = np.maximum(tips[:, i1, 2], tips[:, i2, 2]) + r
        opp = free & (ang <= OPPOSITION_CONE) & (top <= vehicle.bottom_z)
        base = q[0].copy()
        for j, v in grasp_base(tree).items():
            base[ALL_JOINTS.index(j)] = v
        cols = c1 + c2

        def pair_free(q8: np.ndarray, own=own, others=others, base=base, cols=cols) -> bool:
            row = base.copy()
            row[cols] = q8
            return model.pair_free(row, own, others)

        candidates = np.vstack([q[opp][:, cols], symmetric_samples(tree, name, 20_000, rng)])
        grasps = grasp_check(tree, name, candidates, vehicle, features, is_free=pair_free)
        pairs.append(
            PairReach(
                name,
                (f1, f2),
                span,
                2 * r,
                float(free.mean()),
                free_span,
                _range(ell[opp]),
                grasps,
                free,
            )
        )
        progress("spans and grasps", len(pairs) / len(PAIRS))
    timings["spans and grasps"] = time.perf_counter() - t

    home_tips = tree.frame_positions(tree.posture("home"))
    home_depth = max(vehicle.bottom_z - home_tips[f"{f}_tip"][2] for f in FINGERS)
    out = ReachAnalysis(
        vehicle,
        tree.design.source,
        int(samples),
        seed,
        spaces,
        pairs,
        rail_spacing(tree),
        contacts,
        tips,
        float(home_depth),
        timings,
    )
    out.seconds = time.perf_counter() - t0
    return out


def _range(values: np.ndarray) -> tuple[float, float]:
    if len(values) == 0:
        return (float("nan"), float("nan"))
    return (float(values.min()), float(values.max()))


__all__ = [
    "CTB_FEATURES",
    "OPPOSITION_CONE",
    "PAIRS",
    "CollisionModel",
    "Contacts",
    "GraspFeature",
    "GraspResult",
    "PairReach",
    "ReachAnalysis",
    "ReachError",
    "SpanRange",
    "Workspace",
    "analyse_reach",
    "batch_frames",
    "batch_link_poses",
    "columns",
    "finger_link_names",
    "fingertips",
    "grasp_base",
    "grasp_check",
    "opposition",
    "pair_joints",
    "rail_spacing",
    "reach_json",
    "sample_configurations",
    "span_of",
    "span_range",
    "symmetric_samples",
    "workspace",
]
