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
from payload.envelope.progress import Progress, quiet
from payload.envelope.vehicle import Vehicle
from payload.rotations import matrix_to_quat


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
        # Multi-point CCD (on by default since MuJoCo 3.3) adds up to three more contact
        # points to a touching mesh pair; which pairs touch is decided before it, by the
        # first contact, so the check only needs that one (about 10 % of its time).
        # The convex pairs go through libccd's MPR instead of MuJoCo's native GJK/EPA:
        # the same touching pairs (tests/test_reach.py checks them against the native
        # solver and python-fcl), and about a third less time a sample here, since the
        # check needs whether pieces overlap, not EPA's exact penetration (docs/envelope.md).
        spec.option.disableflags |= int(
            mujoco.mjtDisableBit.mjDSBL_GRAVITY
            | mujoco.mjtDisableBit.mjDSBL_MULTICCD
            | mujoco.mjtDisableBit.mjDSBL_NATIVECCD
        )
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in ALL_JOINTS])
        self.body_names = [m.body(b).name for b in range(m.nbody)]

    def check(self, samples: np.ndarray, progress: Progress = quiet, workers: int = 1) -> Contacts:
        """Every contact of every configuration.

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
        bounds = np.linspace(0, n, max(2, min(100, n // 500)) + 1).astype(int)
        ranges = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
        if not (workers > 1 and n >= 10_000 and sys.platform.startswith("linux")):

            def serial(progress: Progress) -> Contacts:
                parts = []
                for k, (a, b) in enumerate(ranges):
                    parts.append((a, self._check_range(samples, a, b)))
                    progress("collisions", (k + 1) / len(ranges))
                return self._contacts(n, parts)

            return serial
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

    def _contacts(self, n: int, parts: list[tuple[int, np.ndarray]]) -> Contacts:
        """The rows of every range, in sample order: each range's rows are sorted by
        (sample, body a, body b) already (:meth:`_check_range`), and the ranges are
        consecutive, so ordering the ranges by their first sample sorts the whole."""
        parts = sorted(parts, key=lambda part: part[0])
        rows = np.concatenate([r for _, r in parts]) if parts else np.zeros((0, 3), dtype=int)
        return Contacts(n, rows[:, 0], rows[:, 1], rows[:, 2], tuple(self.body_names))

    def _check_range(self, samples: np.ndarray, start: int, stop: int) -> np.ndarray:
        """Rows (sample, body a, body b) of distinct body pairs in contact, a < b, sorted.

        The loop does only MuJoCo's work per sample (place, kinematics, collision, copy
        the contacts' geoms); the bookkeeping runs once over the whole range.
        """
        m, d = self.model, self.data
        qpos = np.zeros((stop - start, m.nq))
        qpos[:, self._qadr] = samples[start:stop]
        found: list[np.ndarray] = []
        where: list[int] = []
        counts: list[int] = []
        for k in range(stop - start):
            d.qpos[:] = qpos[k]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            if d.ncon:
                found.append(d.contact.geom.copy())
                where.append(start + k)
                counts.append(d.ncon)
        if not found:
            return np.zeros((0, 3), dtype=int)
        bodies = np.sort(m.geom_bodyid[np.concatenate(found)], axis=1).astype(np.int64)
        index = np.repeat(np.asarray(where, dtype=np.int64), counts)
        nb = np.int64(m.nbody)
        keys = np.unique((index * nb + bodies[:, 0]) * nb + bodies[:, 1])
        return np.column_stack([keys // (nb * nb), (keys // nb) % nb, keys % nb]).astype(int)

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


_ACTIVE: tuple[CollisionModel, np.ndarray] | None = None
"""The model and samples a forked worker checks (set by the parent before forking)."""


def _check_range(bounds: tuple[int, int]) -> tuple[int, np.ndarray]:
    assert _ACTIVE is not None
    model, samples = _ACTIVE
    return bounds[0], model._check_range(samples, *bounds)


def _quat(r: np.ndarray) -> list[float]:
    return matrix_to_quat(r).tolist()


__all__ = [
    "CollisionModel",
    "Contacts",
]
