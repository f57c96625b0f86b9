"""The simulated driver's control period: the vehicle's forces, the servos' targets and the
physics steps.

:class:`DriverControlPeriod` is a base of :class:`~payload.sim.driver.SimDriver`: each
control period (:meth:`~DriverControlPeriod.step`) the vehicle controller's wrench (with
the twist filter) is applied as nozzle thrusts or a clipped wrench, the servos' targets
slew toward their goals, the CTB's external forces are watched, and the physics runs
(``mujoco.mj_step``, looked up on the ``mujoco`` module at each period). The period runs
compiled (:mod:`payload.sim.period_c`, the thrusts :mod:`payload.sim.vehicle_c`, both
checked against the numpy code here when built) or in numpy. It reads the driver's data,
world, controller and settings (set by ``SimDriver.__init__``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np

from payload.schema import VehicleTwist
from payload.sim.propulsion import Allocation
from payload.sim.readout import WorldState
from payload.sim.world import CONTROL_DT, SimError
from payload.vecmath import clip, max_reduce


class DriverControlPeriod:
    """The control period of :class:`~payload.sim.driver.SimDriver` (its base; see the
    module)."""

    def step(self, control_steps: int = 1) -> WorldState:
        """Advance ``control_steps`` control periods (20 physics steps of 1 ms each at the
        default step; ``WorldConfig.substeps`` in general)."""
        self._check_open()
        if control_steps < 1:
            raise SimError(f"step: control_steps must be >= 1, got {control_steps}")
        m, d = self.model, self.data
        period = self._period_kernel
        for _ in range(control_steps):
            if period is not None:
                self._control_compiled(period)
            else:
                self._control_python()
            mujoco.mj_step(m, d, nstep=self._substeps)
        return self.world_state()

    def _control_python(self) -> None:
        """A control period's work before the physics: the vehicle controller (with the
        twist filter) and its forces, the servo targets' slew and controls, the CTB watch."""
        d, w = self.data, self.world
        if self._twist is not None:
            twist = self._twist
            if self.twist_filter is not None:
                twist = self.twist_filter(twist, d)
            lin, ang = self._body_twist()
            self._wrench = self.controller.update(twist, lin, ang, CONTROL_DT)
            if self.controller.allocation is not None:
                self.apply_thrusts(self.controller.allocation)
            else:
                rot = d.xmat[w.astrobee].reshape(3, 3)
                d.xfrc_applied[w.astrobee, :3] = rot @ self._wrench.force
                d.xfrc_applied[w.astrobee, 3:] = rot @ self._wrench.torque
        self._target += clip(self._goal - self._target, -self._step_max, self._step_max)
        d.ctrl[self._ctrl] = self._target
        self._watch_ctb()

    def _control_compiled(self, period: Any) -> None:
        """:meth:`_control_python` through the compiled period (:mod:`payload.sim.period_c`);
        a control step that did not allocate is finished here, as the controller does."""
        if self._twist is not None:
            twist = self._twist
            if self.twist_filter is not None:
                twist = self.twist_filter(twist, self.data)
            code, *out = period.vehicle(twist, CONTROL_DT)
            self._wrench = self.controller._finish_kernel(code, out)
            if code != 0:
                self.apply_thrusts(self.controller.allocation)
        period.servos()

    @property
    def _period_kernel(self) -> Any:
        """:meth:`_control_python` compiled for the current data, goals, targets and
        controller (:func:`payload.sim.period_c.compiled_period`, checked when built), or
        None (the box propulsion model, no controller or thrusts kernel, or a refusal)."""
        made = self.__dict__.get("_period")
        key = (self.data, self._goal, self._target, self.controller)
        if made is not None and all(a is b for a, b in zip(made[0], key)):
            return made[1]
        kernel = None
        control = self.controller._kernel if self.controller.nozzles is not None else None
        thrusts = self._thrust_kernel if control is not None else None
        if thrusts is not None:
            from payload.sim.period_c import CompiledPeriod, compiled_period

            w = self.world
            ctb = (w.ctb, w.ctb_dof) if w.ctb >= 0 else None

            def make(lib: Any, gemv: int) -> CompiledPeriod:
                return CompiledPeriod(
                    lib, gemv, control, thrusts, self.data, w.astrobee, w.astrobee_dof,
                    self._goal, self._target, self._step_max, self._ctrl, ctb, self._ctb_max,
                )  # fmt: skip

            kernel = compiled_period(make, self._check_period)
        self.__dict__["_period"] = (key, kernel)
        return kernel

    def apply_thrusts(self, allocation: Allocation) -> None:
        """Apply nozzle thrusts as forces at the nozzle positions on Astrobee's body
        (``mj_applyFT`` into ``qfrc_applied``), held over the next control period."""
        if self.controller.nozzles is None:
            raise SimError("apply_thrusts: the box propulsion model has no nozzles")
        self._clear_vehicle_forces()
        kernel = self._thrust_kernel
        if kernel is not None:
            kernel(allocation.thrust)
        else:
            self._apply_thrusts_numpy(allocation.thrust, self.data.qfrc_applied)

    @property
    def _thrust_kernel(self) -> Any:
        """:meth:`_apply_thrusts_numpy` compiled for the current data
        (:func:`payload.sim.vehicle_c.compiled_thrusts`, checked when built), or None."""
        kernel = self.__dict__.get("_thrusts")
        if kernel is None or kernel[0] is not self.data:
            from payload.sim.vehicle_c import compiled_thrusts

            made = compiled_thrusts(
                self.model,
                self.data,
                self.world.astrobee,
                self.controller.nozzles,
                self._apply_thrusts_numpy,
            )
            kernel = self.__dict__["_thrusts"] = (self.data, made)
        return kernel[1]

    def _apply_thrusts_numpy(self, thrust: np.ndarray, qfrc: np.ndarray) -> None:
        """Add the thrusts' generalised forces to ``qfrc`` (``mj_applyFT`` per open nozzle)."""
        w, d = self.world, self.data
        nozzles = self.controller.nozzles
        rot = d.xmat[w.astrobee].reshape(3, 3)
        origin = d.xipos[w.astrobee]
        torque = np.zeros(3)
        model, body = self.model, w.astrobee
        directions, positions = nozzles.directions, nozzles.positions
        for k in np.flatnonzero(thrust > 0.0).tolist():  # Python ints: cheaper indexing
            force = rot @ (directions[k] * thrust[k])
            point = origin + rot @ positions[k]
            mujoco.mj_applyFT(model, d, force, torque, point, body, qfrc)

    def _check_period(self, kernel: Any, probes: int) -> bool:
        """Whether ``kernel``'s period does what :meth:`_control_python` does, to the bit, in
        ``probes`` random states (Astrobee's pose and velocity, the applied forces, the
        controls, the servos' goals and targets, some equal or signed zeros, CTB forces that
        are not a number, the controller's profile, commands at rest, within and beyond the
        flight mode's speed, a zero wrench, the controller off), compared on every array the
        period writes and on the controller's allocation and wrench, or on the error both
        raise. Everything is restored."""
        d, w, c = self.data, self.world, self.controller
        prof = c.profile
        arrays = (d.qvel, d.xmat, d.xipos, d.xfrc_applied, d.qfrc_applied, d.ctrl)
        arrays += (self._goal, self._target, self._ctb_max)
        saved = [a.copy() for a in arrays]
        state = (prof.velocity.copy(), prof.acceleration.copy(), c.allocation, self._wrench)
        twist, twist_filter = self._twist, self.twist_filter
        rng = np.random.default_rng(5)
        mode = c.mode

        def run(control: Callable[[], None]) -> list[bytes]:
            try:
                control()
            except Exception as exc:  # both alike, or the kernel is refused
                return [type(exc).__name__.encode(), str(exc).encode()]
            return outcome()

        def outcome() -> list[bytes]:
            alloc = c.allocation
            parts = [a.tobytes() for a in arrays[3:]] + [prof.velocity.tobytes()]
            parts += [prof.acceleration.tobytes(), self._wrench.force.tobytes()]
            parts += [self._wrench.torque.tobytes()]
            if alloc is not None:
                parts += [alloc.thrust.tobytes(), alloc.force.tobytes(), alloc.torque.tobytes()]
                parts.append(np.float64(alloc.scale).tobytes())
            return parts

        self.twist_filter = None  # the filter is the same Python call either way
        try:
            for k in range(probes):
                q = rng.normal(size=4)
                mujoco.mju_quat2Mat(d.xmat[w.astrobee], q / np.linalg.norm(q))
                d.xipos[w.astrobee] = rng.normal(size=3)
                dof = slice(w.astrobee_dof, w.astrobee_dof + 6)
                d.qvel[dof] = rng.normal(scale=0.05, size=6)
                d.xfrc_applied[:] = rng.normal(size=d.xfrc_applied.shape) * (k % 3 == 0)
                d.qfrc_applied[:] = rng.normal(size=d.qfrc_applied.shape) * (k % 4 == 1)
                d.ctrl[:] = rng.normal(size=d.ctrl.shape)
                self._target[:] = rng.normal(scale=0.1, size=self._target.shape)
                self._goal[:] = self._target + rng.normal(scale=0.05, size=self._goal.shape)
                if k % 5 == 2:  # at the goal, and signed zeros
                    self._goal[::2] = self._target[::2]
                    self._target[1::4], self._goal[1::4] = 0.0, -0.0
                if w.ctb >= 0 and k % 11 == 7:  # a force not a number, beside others
                    d.xfrc_applied[w.ctb] = rng.normal(size=6)
                    d.xfrc_applied[w.ctb, k % 6] = np.nan
                if w.ctb >= 0 and k % 13 == 9:
                    d.qfrc_applied[w.ctb_dof : w.ctb_dof + 6] = rng.normal(size=6)
                    d.qfrc_applied[w.ctb_dof + k % 6] = np.nan
                self._ctb_max[0] = abs(rng.normal())
                prof.velocity[:] = rng.normal(scale=0.02, size=6)
                prof.acceleration[:] = rng.normal(scale=0.005, size=6)
                if k % 2:  # flying as planned: the allocation inside the polytope
                    rot = d.xmat[w.astrobee].reshape(3, 3)
                    d.qvel[dof] = np.concatenate((rot @ prof.velocity[:3], prof.velocity[3:]))
                    d.qvel[dof] += rng.normal(scale=1e-4, size=6)
                scale = (0.0, 0.5, 1.0, 2.0, 4.0)[k % 5]
                self._twist = (
                    None
                    if k % 7 == 3
                    else VehicleTwist(
                        rng.normal(size=3) * mode.speed * scale,
                        rng.normal(size=3) * mode.omega * scale,
                        0.0,
                    )
                )
                if k % 17 == 4:  # at rest and asked for nothing: a zero wrench
                    d.qvel[dof] = 0.0
                    prof.velocity[:], prof.acceleration[:] = 0.0, 0.0
                    self._twist = VehicleTwist.zero()
                start = [a.copy() for a in arrays] + [prof.velocity.copy()]
                start.append(prof.acceleration.copy())
                held = (c.allocation, self._wrench)
                want = run(self._control_python)
                for a, b in zip(arrays, start):
                    a[:] = b
                prof.velocity[:], prof.acceleration[:] = start[-2], start[-1]
                c.allocation, self._wrench = held
                if run(lambda: self._control_compiled(kernel)) != want:
                    return False
            return True
        finally:
            for a, b in zip(arrays, saved):
                a[:] = b
            prof.velocity[:], prof.acceleration[:] = state[0], state[1]
            c.allocation, self._wrench = state[2], state[3]
            self._twist, self.twist_filter = twist, twist_filter

    def _clear_vehicle_forces(self) -> None:
        w, d = self.world, self.data
        d.xfrc_applied[w.astrobee] = 0.0
        d.qfrc_applied[w.astrobee_dof : w.astrobee_dof + 6] = 0.0

    @property
    def ctb_external_max(self) -> float:
        """Largest applied force or generalised force on the CTB seen at any control step
        (0 when the CTB is moved by contacts only)."""
        return float(self._ctb_max[0])

    @ctb_external_max.setter
    def ctb_external_max(self, value: float) -> None:
        self._ctb_max[0] = value

    def _watch_ctb(self) -> None:
        w, d = self.world, self.data
        if w.ctb < 0:
            return
        ext = max(  # ndarray.max's reduction, without its wrappers
            float(max_reduce(np.abs(d.xfrc_applied[w.ctb]), axis=None)),
            float(max_reduce(np.abs(d.qfrc_applied[w.ctb_dof : w.ctb_dof + 6]), axis=None)),
        )
        self.ctb_external_max = max(self.ctb_external_max, ext)


__all__ = ["DriverControlPeriod"]
