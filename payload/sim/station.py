"""Contacts and clearance between the station and what moves with the vehicle.

Measured in every trial, with or without the base safety filter: at each control step,
whether any MuJoCo contact joins a station geom (walls, handrails) to a geom of Astrobee,
the payload or the CTB, and the least distance between those two sets by MuJoCo's own
distance query (``mj_geomDistance``), for the pairs whose world bounding boxes come within
:data:`CLEARANCE_CAP` of each other (farther pairs count as the cap).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import mujoco
import numpy as np

CLEARANCE_CAP = 0.3
"""Distances beyond this are not measured [m]: the clearance reads at most the cap."""

_SLACK = 1e-6
"""Added to the reach of a moving geom's box [m]: far more than the rounding of the box
arithmetic (about 1e-15 m at the station's scale), far less than anything measured."""


class StationReading(NamedTuple):
    """One control step's reading.

    Attributes:
        contact: Some station geom touches the vehicle, the payload or the CTB.
        clearance: Least distance between them [m], at most :data:`CLEARANCE_CAP`.
    """

    contact: bool
    clearance: float


def moving_geoms(world: Any) -> np.ndarray:
    """Collision geoms of Astrobee, the payload and the CTB, shape (G,)."""
    m = world.model
    out = [
        g
        for g in range(m.ngeom)
        if (
            m.body_rootid[m.geom_bodyid[g]] == world.astrobee
            or (world.ctb >= 0 and m.geom_bodyid[g] == world.ctb)
        )
        and (m.geom_contype[g] or m.geom_conaffinity[g])
    ]
    return np.array(out, dtype=int)


def _world_aabb(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray):
    box = model.geom_aabb[geoms]
    rot = data.geom_xmat[geoms].reshape(-1, 3, 3)
    centre = data.geom_xpos[geoms] + np.einsum("nij,nj->ni", rot, box[:, :3])
    half = np.einsum("nij,nj->ni", np.abs(rot), box[:, 3:])
    return centre - half, centre + half


class StationMonitor:
    """Reads :class:`StationReading` from a world's model and data.

    Args:
        world: The simulator's :class:`~payload.sim.world.World`.
    """

    def __init__(self, world: Any) -> None:
        self.model = world.model
        self.moving = moving_geoms(world)
        self.station = np.asarray(world.iss_geoms, dtype=int)
        self._is_moving = np.zeros(self.model.ngeom, bool)
        self._is_moving[self.moving] = True
        self._is_station = np.zeros(self.model.ngeom, bool)
        self._is_station[self.station] = True
        self._station_box: tuple[np.ndarray, np.ndarray] | None = None
        self._fromto = np.zeros(6)
        self._kernel: tuple[Any, Any] | None = None
        self._contact: tuple[Any] | None = None  # (the compiled reader or None) once tried
        # per moving geom, a bound on how far its world box reaches from its frame's
        # origin along any axis: |R c|_i <= |c| and (|R| h)_i <= |h| for a rotation R
        # (the box's centre c and half-sizes h in the geom frame), with slack for rounding
        box = self.model.geom_aabb[self.moving]
        self._reach = (
            np.sqrt((box[:, :3] ** 2).sum(axis=1)) + np.sqrt((box[:, 3:] ** 2).sum(axis=1))
        )[:, None] * (1.0 + 1e-9) + _SLACK

    def read(self, data: mujoco.MjData) -> StationReading:
        """The contact flag and the clearance now."""
        m = self.model
        contact = False
        if data.ncon:
            kernel = self._contact_kernel(data)
            contact = kernel(data) if kernel is not None else self._contact_numpy(data)
        if self._station_box is None:  # static geoms: their boxes never change
            self._station_box = _world_aabb(m, data, self.station)
        # first a box around every moving geom's box (its origin plus its reach): when
        # no station box comes within the cap of their union, neither does any of the
        # boxes inside (the test below, with the same monotone subtractions), and the
        # clearance reads the cap (most steps, in mid-module)
        kernel = self._bound_kernel(data)
        if not (kernel.near() if kernel is not None else self._near_numpy(data)):
            return StationReading(contact, CLEARANCE_CAP)
        best = kernel.clearance() if kernel is not None else None
        if best is None:
            best = self._clearance_numpy(data)
        return StationReading(contact or best <= 0.0, float(best))

    def _contact_numpy(self, data: mujoco.MjData) -> bool:
        """Whether a station geom and a moving one are in contact (numpy)."""
        con = data.contact
        g1, g2 = con.geom1, con.geom2
        pair = (self._is_station[g1] & self._is_moving[g2]) | (
            self._is_station[g2] & self._is_moving[g1]
        )
        return bool((pair & (con.dist <= 0.0)).any())

    def _contact_kernel(self, data: mujoco.MjData) -> Any:
        """:meth:`_contact_numpy` compiled (:mod:`payload.sim.contacts_c`, checked on the
        first data with contacts it is asked about), or None."""
        if self._contact is None:
            from payload.sim.contacts_c import compiled_station_contact

            self._contact = (
                compiled_station_contact(
                    data, self._is_station, self._is_moving, self._contact_numpy
                ),
            )
        return self._contact[0]

    def _clearance_numpy(self, data: mujoco.MjData) -> float:
        """The least distance between the moving geoms and the station, at most the cap
        (MuJoCo's distance for every pair whose world boxes come within the cap)."""
        m = self.model
        s_lo, s_hi = self._station_box
        lo, hi = _world_aabb(m, data, self.moving)
        # the station boxes within the cap of the moving geoms' union box first (IEEE
        # subtraction is monotone, so every pair within the cap passes this), then the
        # pairs among those
        near = np.flatnonzero(
            ((s_lo - hi.max(axis=0) < CLEARANCE_CAP) & (lo.min(axis=0) - s_hi < CLEARANCE_CAP)).all(
                axis=1
            )
        )
        best = CLEARANCE_CAP
        if near.size:
            n_lo, n_hi = s_lo[near], s_hi[near]
            gap = np.maximum(n_lo[None] - hi[:, None], lo[:, None] - n_hi[None]).max(axis=2)
            for i, j in zip(*np.nonzero(gap < CLEARANCE_CAP)):
                d = mujoco.mj_geomDistance(
                    m,
                    data,
                    int(self.moving[i]),
                    int(self.station[near[j]]),
                    CLEARANCE_CAP,
                    self._fromto,
                )
                best = min(best, d)
        return best

    def _near_numpy(self, data: mujoco.MjData) -> bool:
        """Whether a station box comes within the cap of the moving geoms' bound."""
        s_lo, s_hi = self._station_box
        origin = data.geom_xpos[self.moving]
        return bool(
            (
                (s_lo - (origin + self._reach).max(axis=0) < CLEARANCE_CAP)
                & ((origin - self._reach).min(axis=0) - s_hi < CLEARANCE_CAP)
            )
            .all(axis=1)
            .any()
        )

    def _bound_kernel(self, data: mujoco.MjData) -> Any:
        """:meth:`_near_numpy` compiled for ``data`` (:mod:`payload.sim.station_c`,
        checked when built), or None."""
        if self._kernel is None or self._kernel[0] is not data:
            from payload.sim.station_c import compiled_station_bound

            s_lo, s_hi = self._station_box
            made = compiled_station_bound(
                data,
                self.moving,
                self._reach,
                s_lo,
                s_hi,
                CLEARANCE_CAP,
                lambda: self._near_numpy(data),
                model=self.model,
                station=self.station,
                clearance=lambda: self._clearance_numpy(data),
                boxes=lambda: _world_aabb(self.model, data, self.moving),
            )
            self._kernel = (data, made)
        return self._kernel[1]


__all__ = ["CLEARANCE_CAP", "StationMonitor", "StationReading", "moving_geoms"]
