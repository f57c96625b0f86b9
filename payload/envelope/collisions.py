"""Self-collision and vehicle contact of sampled configurations (MuJoCo)."""

from __future__ import annotations

import itertools
import multiprocessing as mp
import sys
from collections.abc import Callable, Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from payload.design.tree import ALL_JOINTS, rpy_matrix
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.overlap import compile_check, touching
from payload.envelope.progress import Progress, quiet
from payload.envelope.vehicle import Vehicle
from payload.rotations import matrix_to_quat

RANGE = 1000
"""The most samples a range of the check holds (a worker's task; about 3.4 MB of poses
for the default design)."""


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
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in ALL_JOINTS])
        self.body_names = [m.body(b).name for b in range(m.nbody)]
        self._pieces = _Pieces.of(m)

    def qpos(self, samples: np.ndarray) -> np.ndarray:
        """The model's ``qpos`` of configurations (n, 18) in :data:`ALL_JOINTS` order: (n, nq)."""
        out = np.zeros((len(samples), self.model.nq))
        out[:, self._qadr] = samples
        return out

    def check(self, samples: np.ndarray, progress: Progress = quiet, workers: int = 1) -> Contacts:
        """The body pairs in contact in every configuration.

        Args:
            samples: Shape (n, 18), :data:`ALL_JOINTS` order.
            progress: Progress callback.
            workers: Processes (forked, on Linux; elsewhere and for fewer than 10,000
                samples the check runs in this process).

        Returns:
            The :class:`Contacts` (body pairs in contact, per sample).
        """
        return self.start(samples, workers)(progress)

    def start(self, samples: np.ndarray, workers: int = 1) -> Callable[[Progress], Contacts]:
        """Start :meth:`check` in forked workers now and return what waits for its result
        (call it once, with a progress callback), so that this process can do other work
        meanwhile. Without workers (one, fewer than 10,000 samples, or not Linux) the
        check runs when the result is asked for."""
        n = len(samples)
        # ranges of at most RANGE samples (a range's poses: RANGE x geoms x 12 floats)
        bounds = np.linspace(0, n, max(2, -(-n // RANGE)) + 1).astype(int)
        ranges = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
        if not (workers > 1 and n >= 10_000 and sys.platform.startswith("linux")):

            def serial(progress: Progress) -> Contacts:
                parts = []
                for k, (a, b) in enumerate(ranges):
                    parts.append((a, b, self._check_range(samples, a, b)))
                    progress("collisions", (k + 1) / len(ranges))
                return self._contacts(n, parts)

            return serial
        # load the compiled check here, once, for the workers to inherit (each would
        # otherwise load it from Numba's cache itself: about 0.3 s a process)
        compile_check()
        global _ACTIVE
        _ACTIVE = (self, samples)  # kept until the results are in (a replaced worker forks)
        try:
            pool = mp.get_context("fork").Pool(workers)  # the workers fork here
        except BaseException:
            _ACTIVE = None
            raise
        results = pool.imap_unordered(_check_range, ranges)

        def forked(progress: Progress) -> Contacts:
            global _ACTIVE
            parts = []
            try:
                with pool:
                    for k, part in enumerate(results):
                        parts.append(part)
                        progress("collisions", (k + 1) / len(ranges))
            finally:
                _ACTIVE = None
            return self._contacts(n, parts)

        return forked

    def _contacts(self, n: int, parts: list[tuple[int, int, np.ndarray]]) -> Contacts:
        """The rows of every range ``(start, stop, packed flags)`` (:meth:`_check_range`),
        in sample order whatever order the ranges came in."""
        p = self._pieces
        ngroup = len(p.body_a)
        flags = np.zeros((n, ngroup), dtype=bool)
        for start, stop, packed in parts:
            bits = np.unpackbits(packed, count=(stop - start) * ngroup)
            flags[start:stop] = bits.reshape(stop - start, ngroup).view(bool)
        k, group = np.nonzero(flags)  # row-major: by sample, then body pair (sorted)
        return Contacts(n, k, p.body_a[group], p.body_b[group], tuple(self.body_names))

    def _check_range(self, samples: np.ndarray, start: int, stop: int) -> np.ndarray:
        """The body pairs in contact in samples ``start:stop``: flags (sample, body pair)
        packed into bits (:func:`numpy.packbits`, row-major; 1/8 of the bytes to send
        back from a worker).

        MuJoCo places the pieces sample by sample; the compiled overlap test then runs
        once over the whole range.
        """
        m, d = self.model, self.data
        qpos = self.qpos(samples[start:stop])
        xpos = np.empty((stop - start, m.ngeom, 3))
        xmat = np.empty((stop - start, m.ngeom, 9))
        q, geom_xpos, geom_xmat = d.qpos, d.geom_xpos, d.geom_xmat  # views, taken once
        for k in range(stop - start):
            q[:] = qpos[k]
            mujoco.mj_kinematics(m, d)
            xpos[k] = geom_xpos
            xmat[k] = geom_xmat
        p = self._pieces
        flags = touching(
            xpos, xmat, p.verts, p.vadr, p.vnum, p.radius, p.box_c, p.box_h, p.g1, p.g2,
            p.group_start,
        )  # fmt: skip
        return np.packbits(flags)

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
        nb = len(self.body_names)
        counts = np.bincount(self.body_a * nb + self.body_b, minlength=nb * nb)
        out: dict[tuple[str, str], int] = {}
        for key in np.flatnonzero(counts):
            a, b = divmod(int(key), nb)
            name_a = "vehicle" if a == 0 else self.body_names[a]
            out[(name_a, self.body_names[b])] = int(counts[key])
        return out


class _Pieces(NamedTuple):
    """What :func:`payload.envelope.overlap.touching` needs of a model: every geom's
    vertices in its frame (a mesh's as MuJoCo holds them, a box's corners, a sphere's
    centre and radius) and bounding box, and the geom pairs MuJoCo's filters pass,
    grouped by body pair (sorted)."""

    verts: np.ndarray
    vadr: np.ndarray
    vnum: np.ndarray
    radius: np.ndarray
    box_c: np.ndarray
    box_h: np.ndarray
    g1: np.ndarray
    g2: np.ndarray
    group_start: np.ndarray
    body_a: np.ndarray
    body_b: np.ndarray

    @classmethod
    def of(cls, m: mujoco.MjModel) -> _Pieces:
        verts = []
        radius = np.zeros(m.ngeom)
        for g in range(m.ngeom):
            if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                i = m.geom_dataid[g]
                v = m.mesh_vert[m.mesh_vertadr[i] : m.mesh_vertadr[i] + m.mesh_vertnum[i]]
            elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
                v = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * m.geom_size[g]
            elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
                v = np.zeros((1, 3))
                radius[g] = m.geom_size[g, 0]
            else:
                raise ValueError(f"geom {g}: the overlap check takes meshes, boxes and spheres")
            verts.append(np.asarray(v, dtype=float))
        vnum = np.array([len(v) for v in verts])
        groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for g1, g2 in itertools.combinations(range(m.ngeom), 2):
            if _mujoco_filters(m, g1, g2):
                a, b = sorted((int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])))
                groups.setdefault((a, b), []).append((g1, g2))
        keys = sorted(groups)
        pairs = np.array([p for k in keys for p in groups[k]], dtype=np.int64).reshape(-1, 2)
        return cls(
            verts=np.concatenate(verts),
            vadr=np.concatenate([[0], np.cumsum(vnum)[:-1]]).astype(np.int64),
            vnum=vnum.astype(np.int64),
            radius=radius,
            box_c=np.array([(v.min(0) + v.max(0)) / 2 for v in verts]),
            box_h=np.array([(v.max(0) - v.min(0)) / 2 for v in verts]) + radius[:, None],
            g1=pairs[:, 0].copy(),
            g2=pairs[:, 1].copy(),
            group_start=np.cumsum([0] + [len(groups[k]) for k in keys]).astype(np.int64),
            body_a=np.array([a for a, _ in keys], dtype=np.int64),
            body_b=np.array([b for _, b in keys], dtype=np.int64),
        )


def _mujoco_filters(m: mujoco.MjModel, g1: int, g2: int) -> bool:
    """Whether ``mj_collision`` would test geoms ``g1`` and ``g2`` at all: bodies not welded
    together, not welded parent and child (its parent filter), not an excluded body pair,
    and contype/conaffinity matching (``filterBodyPair``, the exclusions and
    ``filterBitmask`` of MuJoCo's collision driver)."""
    b1, b2 = int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])
    w1, w2 = int(m.body_weldid[b1]), int(m.body_weldid[b2])
    if w1 == w2:
        return False
    wp1, wp2 = int(m.body_weldid[m.body_parentid[w1]]), int(m.body_weldid[m.body_parentid[w2]])
    if w1 and w2 and (w1 == wp2 or w2 == wp1):
        return False
    lo, hi = sorted((b1, b2))
    if (lo << 16) + hi in set(m.exclude_signature.tolist()):
        return False
    return bool(
        m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1]
    )


_ACTIVE: tuple[CollisionModel, np.ndarray] | None = None
"""The model and samples a forked worker checks (set by the parent before forking)."""


def _check_range(bounds: tuple[int, int]) -> tuple[int, int, np.ndarray]:
    assert _ACTIVE is not None
    model, samples = _ACTIVE
    return bounds[0], bounds[1], model._check_range(samples, *bounds)


def _quat(r: np.ndarray) -> list[float]:
    return matrix_to_quat(r).tolist()


__all__ = [
    "CollisionModel",
    "Contacts",
]
