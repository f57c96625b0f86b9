"""The simulated driver's read-outs: the world state and the payload's measured state.

:class:`DriverReadout` is a base of :class:`~payload.sim.driver.SimDriver`:
:meth:`~DriverReadout.world_state` (Astrobee's and the CTB's poses, Astrobee's body twist,
the fingertip contacts, the module, the wrench held) and :meth:`~DriverReadout.read` (the
payload's positions, velocities, efforts and health), each through the compiled read-out
(:mod:`payload.sim.readout_c`, checked against the numpy code here when built) or in
numpy. It reads the driver's data, world and settings (set by ``SimDriver.__init__``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import mujoco
import numpy as np

from payload.schema import HEALTHS, Health, PayloadState, SchemaError
from payload.sim.contact import opposing
from payload.sim.readout_c import WORLD_SLICES
from payload.sim.vehicle import Wrench
from payload.sim.world import IssModule, SimError


class WorldState(NamedTuple):
    """What the teleoperation loop and the trials need of the world each control step.

    Attributes:
        time: Simulation time [s].
        astrobee_pos: Astrobee centre, world frame, shape (3,) [m].
        astrobee_quat: Astrobee orientation, quaternion (w, x, y, z), shape (4,).
        astrobee_linear: Linear velocity in Astrobee's body frame, shape (3,) [m/s].
        astrobee_angular: Angular velocity in Astrobee's body frame, shape (3,) [rad/s].
        ctb_pos: CTB centre, world frame, shape (3,) [m]; None without a CTB.
        ctb_quat: CTB orientation (w, x, y, z), shape (4,); None without a CTB.
        touching: Fingers whose fingertips touch the CTB.
        opposing_contact: The CTB touches fingertips of both sides of the array.
        module: ISS module containing Astrobee's centre (None outside the three).
        wrench: Body wrench the vehicle controller applies over the next period.

    Every active contact with names and forces is
    :meth:`SimDriver.contacts <payload.sim.driver.SimDriver.contacts>` (built on request:
    the loop does not need it at every step).
    """

    time: float
    astrobee_pos: np.ndarray
    astrobee_quat: np.ndarray
    astrobee_linear: np.ndarray
    astrobee_angular: np.ndarray
    ctb_pos: np.ndarray | None
    ctb_quat: np.ndarray | None
    touching: frozenset[str]
    opposing_contact: bool
    module: IssModule | None
    wrench: Wrench

    def ctb_in_body(self) -> np.ndarray:
        """CTB centre in Astrobee's body frame (the paper's eq. 4), shape (3,) [m]."""
        if self.ctb_pos is None:
            raise SimError("ctb_in_body: the world has no CTB")
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, self.astrobee_quat)
        return rot.reshape(3, 3).T @ (self.ctb_pos - self.astrobee_pos)


class DriverReadout:
    """The read-outs of :class:`~payload.sim.driver.SimDriver` (its base; see the module)."""

    def read(self) -> PayloadState:
        """Measured positions, velocities and actuator efforts of the payload.

        Health: OVERLOAD when an actuator is at its force bound, LIMIT when one of the 17
        manipulation coordinates is at or beyond an end of its range.
        """
        self._check_open()
        kernel = self._readout
        return self._read_numpy() if kernel is None else self._read_kernel(kernel)

    def _read_kernel(self, kernel: Any) -> PayloadState:
        """:meth:`read` through the read-out kernel."""
        out, health = kernel.read()
        out.setflags(write=False)  # the read-out's own buffer: its parts are the state's
        part = kernel.payload
        return PayloadState.of_frozen(
            out[part["q"]],
            float(out[part["deploy"].start]),
            float(self.data.time),
            out[part["dq"]],
            out[part["effort"]],
            HEALTHS[health] if 0 <= health < len(HEALTHS) else Health(health),
        )

    def _read_numpy(self) -> PayloadState:
        """:meth:`read` in numpy (what the read-out kernel is checked against)."""
        w, d = self.world, self.data
        effort = d.actuator_force[w.ctrl]
        health = Health.OK
        if (np.abs(d.actuator_force[self._ctrl]) >= self._overload).any():
            health |= Health.OVERLOAD
        q = d.qpos[w.qpos]
        if (q <= self._limit_lo).any() or (q >= self._limit_hi).any():
            health |= Health.LIMIT
        return PayloadState(
            q=q.copy(),
            deploy=float(d.qpos[w.stage_qpos]),
            stamp=float(d.time),
            dq=d.qvel[w.dof].copy(),
            effort=effort.copy(),
            health=health,
        )

    @property
    def _readout(self) -> Any:
        """:meth:`_world_state_numpy` and :meth:`_read_numpy` compiled for the current data
        (:mod:`payload.sim.readout_c`, checked when built), or None."""
        kernel = self.__dict__.get("_readouts")
        if kernel is None or kernel[0] is not self.data:
            from payload.sim.readout_c import CompiledReadout, compiled_readout

            w, d = self.world, self.data

            def make(lib: Any, gemv: int) -> CompiledReadout:
                return CompiledReadout(
                    lib, gemv, d, w.astrobee, w.astrobee_qpos, w.astrobee_dof, w.ctb_qpos,
                    w.qpos, w.dof, w.stage_qpos, w.ctrl, self._ctrl, self._overload,
                    self._limit_lo, self._limit_hi,
                )  # fmt: skip

            made = compiled_readout(make, self._check_readout)
            kernel = self.__dict__["_readouts"] = (d, made)
        return kernel[1]

    def _check_readout(self, kernel: Any, probes: int) -> bool:
        """Whether ``kernel`` reads what :meth:`_world_state_numpy` and :meth:`_read_numpy`
        read, to the bit, in ``probes`` random states written into the data (positions,
        velocities, rotations and actuator forces; some at a force bound, at a joint limit,
        or not a number), which is restored afterwards."""
        d = self.data
        names = ("qpos", "qvel", "xmat", "actuator_force")
        saved = [getattr(d, n).copy() for n in names]
        rng = np.random.default_rng(0)
        body, n = self.world.astrobee, kernel.n
        bound = np.broadcast_to(self._overload, self._ctrl.shape)
        try:
            for k in range(probes):
                d.qpos[:] = rng.normal(size=d.qpos.shape)
                d.qvel[:] = rng.normal(size=d.qvel.shape)
                q = rng.normal(size=4)
                mujoco.mju_quat2Mat(d.xmat[body], q / np.linalg.norm(q))
                d.actuator_force[:] = rng.normal(scale=bound.max(), size=d.actuator_force.shape)
                if k % 7 == 3:  # at a joint limit (either end) or a force bound
                    d.qpos[self.world.qpos[k % n]] = (self._limit_lo, self._limit_hi)[k % 2][k % n]
                    j = k % len(self._ctrl)
                    d.actuator_force[self._ctrl[j]] = -bound[j]
                if k % 31 == 5:
                    d.qpos[self.world.qpos[k % n]] = np.nan
                    d.qvel[self.world.dof[k % n]] = np.inf
                mine, theirs = self._world_state_kernel(kernel), self._world_state_numpy()
                if not all(
                    np.asarray(getattr(mine, f), dtype=float).tobytes()
                    == np.asarray(getattr(theirs, f), dtype=float).tobytes()
                    for f in ("time", *WORLD_SLICES)
                    if getattr(mine, f) is not None or getattr(theirs, f) is not None
                ):
                    return False
                try:  # a coordinate not a number: both refuse the state alike
                    a = self._read_kernel(kernel)
                except SchemaError as exc:
                    a = str(exc)
                try:
                    b = self._read_numpy()
                except SchemaError as exc:
                    b = str(exc)
                if isinstance(a, str) or isinstance(b, str):
                    if a != b:
                        return False
                    continue
                if a.health != b.health or not all(
                    np.asarray(x, dtype=float).tobytes() == np.asarray(y, dtype=float).tobytes()
                    for x, y in ((a.q, b.q), (a.dq, b.dq), (a.effort, b.effort),
                                 (a.deploy, b.deploy), (a.stamp, b.stamp))
                ):  # fmt: skip
                    return False
            return True
        finally:
            for name, values in zip(names, saved):
                getattr(d, name)[:] = values

    def world_state(self) -> WorldState:
        """Astrobee pose and twist, CTB pose, fingertip contacts, indicator, module."""
        self._check_open()
        kernel = self._readout
        return self._world_state_numpy() if kernel is None else self._world_state_kernel(kernel)

    def _world_state_kernel(self, kernel: Any) -> WorldState:
        """:meth:`world_state` through the read-out kernel."""
        out = kernel.world()
        pos, quat, lin, ang, ctb_pos, ctb_quat = self._world_parts  # WORLD_LAYOUT's order
        return self._world_state(
            out[pos], out[quat], out[lin], out[ang],
            None if ctb_pos is None else out[ctb_pos], None if ctb_quat is None else out[ctb_quat],
        )  # fmt: skip

    def _world_state_numpy(self) -> WorldState:
        """:meth:`world_state` in numpy (what the read-out kernel is checked against)."""
        w, d = self.world, self.data
        a, c = w.astrobee_qpos, w.ctb_qpos
        lin, ang = self._body_twist()
        return self._world_state(
            d.qpos[a : a + 3].copy(),
            d.qpos[a + 3 : a + 7].copy(),
            lin,
            ang,
            d.qpos[c : c + 3].copy() if w.ctb >= 0 else None,
            d.qpos[c + 3 : c + 7].copy() if w.ctb >= 0 else None,
        )

    def _world_state(self, pos: np.ndarray, *rest: np.ndarray | None) -> WorldState:
        """The world state of Astrobee's position and the other read-out fields
        (:data:`~payload.sim.readout_c.WORLD_LAYOUT`'s order, WorldState's), with the
        data's time, contacts and module and the wrench held."""
        d, held = self.data, self._wrench
        touching = self.monitor.touching(d)
        return WorldState(
            float(d.time), pos, *rest, touching, opposing(touching),
            self.world.layout.module_at(pos), Wrench(held.force.copy(), held.torque.copy()),
        )  # fmt: skip


__all__ = ["DriverReadout", "WorldState"]
