"""``SimDriver``: the simulated payload behind the ``PayloadDriver`` protocol, plus the vehicle.

One control step (:meth:`SimDriver.step`) is 20 physics steps of 1 ms under a 50 Hz loop:
the vehicle controller computes a bounded body wrench for the commanded twist and holds it
on Astrobee (the 12 allocated nozzle forces at the nozzle positions through
``qfrc_applied``, or with ``propulsion="box"`` the clipped wrench through
``xfrc_applied``), the payload position targets move toward the last
:class:`~payload.schema.PayloadCommand` no faster than the servos turn (XC330 no-load
speed), and the actuators push no harder than the servos' current-capped torque.

Typical use by a 50 Hz loop::

    with SimDriver() as sim:
        for k in range(n):
            sim.send(command)              # payload joints (paper order) and deployment
            sim.command_twist(twist)       # vehicle body twist
            state = sim.step()             # WorldState: poses, twist, CTB, contacts
            measured = sim.read()          # PayloadState
"""

from __future__ import annotations

from collections.abc import Callable
from types import TracebackType
from typing import Any, NamedTuple

import mujoco
import numpy as np

from payload.schema import (
    HEALTHS,
    N_MANIPULATION,
    Health,
    PayloadCommand,
    PayloadState,
    SchemaError,
    VehicleTwist,
)
from payload.sim.contact import Contact, ContactMonitor, opposing
from payload.sim.propulsion import Allocation
from payload.sim.readout_c import WORLD_LAYOUT, WORLD_SLICES
from payload.sim.vehicle import (
    DEFAULT_FLIGHT_MODE,
    DEFAULT_PROPULSION,
    FlightMode,
    MassProperties,
    VehicleController,
    Wrench,
)
from payload.sim.world import (
    CONTROL_DT,
    IssModule,
    SimError,
    World,
    WorldConfig,
    build_world,
)
from payload.vecmath import clip, max_reduce

_AT_LIMIT = 1e-4  # [rad or m] a coordinate this close to a range end is at its limit
_WARNING_NAMES = tuple(
    name
    for name, value in sorted(mujoco.mjtWarning.__members__.items(), key=lambda kv: int(kv[1]))
    if name != "mjNWARNING"
)


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

    Every active contact with names and forces is :meth:`SimDriver.contacts` (built on
    request: the loop does not need it at every step).
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


class SimDriver:
    """The MuJoCo ISS world behind the ``PayloadDriver`` protocol.

    Args:
        world: A built :class:`World`, a :class:`WorldConfig` to build, or None (default
            world: single CTB below the deployed payload at the start of the route).
        flight_mode: Astrobee flight mode for the vehicle controller (default nominal).
        carrying: Whether the vehicle controller plans for the CTB's mass (default: when
            the world has a CTB; the trials carry it).
        keyframe: Initial state, ``home`` (deployed) or ``stowed``.
        contact_links: Fingertip geoms of the indicator, ``pad`` or ``distal``.
        propulsion: ``nozzles`` (default: the 12 nozzle forces applied at the nozzle
            positions through ``qfrc_applied``) or ``box`` (the per-axis clipped wrench at
            Astrobee's centre of mass through ``xfrc_applied``).
    """

    def __init__(
        self,
        world: World | WorldConfig | None = None,
        *,
        flight_mode: str | FlightMode = DEFAULT_FLIGHT_MODE,
        carrying: bool | None = None,
        keyframe: str = "home",
        contact_links: str = "pad",
        propulsion: str = DEFAULT_PROPULSION,
    ) -> None:
        self.world = world if isinstance(world, World) else build_world(world)
        self.model = self.world.model
        self.data = self.world.make_data(keyframe)
        self.monitor = ContactMonitor(self.world, contact_links)
        if carrying is None:
            carrying = self.world.ctb >= 0
        if carrying and self.world.ctb < 0:
            raise SimError("SimDriver: carrying=True but the world has no CTB")
        self.carrying = carrying
        self.controller = VehicleController(
            self.mass_properties(carrying), flight_mode, propulsion=propulsion
        )
        self.propulsion = propulsion
        self._ctb_max = np.zeros(1)  # ctb_external_max (the compiled period writes it)
        self._ctrl = self.world.ctrl_all
        self._ctrl_range = self.model.actuator_ctrlrange[self._ctrl].copy()
        self._goal = self.data.ctrl[self._ctrl].copy()
        self._target = self._goal.copy()
        self._step_max = self.world.slew_rate * CONTROL_DT
        self._substeps = self.world.config.substeps
        self._overload = 0.999 * self.world.force_limit
        self._limit_lo = self._ctrl_range[:N_MANIPULATION, 0] + _AT_LIMIT
        self._limit_hi = self._ctrl_range[:N_MANIPULATION, 1] - _AT_LIMIT
        self._twist: VehicleTwist | None = None
        self.twist_filter: Callable[[VehicleTwist, mujoco.MjData], VehicleTwist] | None = None
        """Called with the requested twist and the data each control step, before the
        vehicle controller (the base safety filter, on the robot's side); None: none."""
        self._wrench = Wrench(np.zeros(3), np.zeros(3))
        self._world_parts = tuple(  # the world read-out's fields (None: no CTB in this world)
            None if name.startswith("ctb") and self.world.ctb < 0 else WORLD_SLICES[name]
            for name, _ in WORLD_LAYOUT  # WorldState's fields after the time, in order
        )
        self._closed = False

    # -- protocol ----------------------------------------------------------------------------
    def send(self, command: PayloadCommand) -> None:
        """Set the payload position targets (17 coordinates in the paper's order + deploy).

        Values beyond a joint's range are clipped to it (as the servos' position limits do).
        """
        self._check_open()
        if not isinstance(command, PayloadCommand):
            raise SimError(f"send: expected a PayloadCommand, got {type(command).__name__}")
        goal = np.concatenate((command.q, (command.deploy,)))  # np.append's, sooner
        clip(goal, self._ctrl_range[:, 0], self._ctrl_range[:, 1], out=self._goal)

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

    def close(self) -> None:
        """Release the driver (idempotent)."""
        self._closed = True

    def __enter__(self) -> SimDriver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- vehicle and world ---------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulation time [s]."""
        return float(self.data.time)

    def command_twist(self, twist: VehicleTwist | None) -> None:
        """Request an Astrobee body twist; None switches the vehicle controller off (drift).

        The reference restarts from the measured twist when the controller comes on.
        """
        self._check_open()
        if twist is not None and not isinstance(twist, VehicleTwist):
            raise SimError(f"command_twist: expected a VehicleTwist, got {type(twist).__name__}")
        if twist is not None and self._twist is None:
            lin, ang = self._body_twist()
            self.controller.reset(lin, ang)
        self._twist = twist
        if twist is None:
            self._wrench = Wrench(np.zeros(3), np.zeros(3))
            self._clear_vehicle_forces()

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

    def contacts(self) -> tuple[Contact, ...]:
        """Every active contact now (geom names, point, normal force, distance)."""
        self._check_open()
        return self.monitor.contacts(self.data)

    def module_at(self, point: np.ndarray) -> IssModule | None:
        """Which ISS module contains ``point`` (3,) [m, world frame], None outside."""
        return self.world.layout.module_at(point)

    def warnings(self) -> dict[str, int]:
        """MuJoCo warnings raised so far (name -> count), empty when clean."""
        return {
            name: int(self.data.warning[i].number)
            for i, name in enumerate(_WARNING_NAMES)
            if self.data.warning[i].number
        }

    def reset(self, keyframe: str = "home") -> None:
        """Back to a keyframe, controller off, targets at the keyframe's."""
        self._check_open()
        self.data = self.world.make_data(keyframe)
        self._goal = self.data.ctrl[self._ctrl].copy()
        self._target = self._goal.copy()
        self._twist = None
        self._wrench = Wrench(np.zeros(3), np.zeros(3))
        self.ctb_external_max = 0.0

    def mass_properties(self, include_ctb: bool) -> MassProperties:
        """Mass properties of Astrobee + payload (+ CTB) in the current state, body frame.

        Returns:
            Mass [kg], centre of mass relative to Astrobee's (3,) [m], inertia about it
            (3, 3) [kg m^2], all in Astrobee's body frame.
        """
        m, d, w = self.model, self.data, self.world
        bodies = [b for b in range(1, m.nbody) if m.body_rootid[b] == w.astrobee]
        if include_ctb and w.ctb >= 0:
            bodies.append(w.ctb)
        rot = d.xmat[w.astrobee].reshape(3, 3)
        origin = d.xipos[w.astrobee]
        masses = m.body_mass[bodies]
        pts = (d.xipos[bodies] - origin) @ rot  # body-frame positions of each body's CoM
        total = float(masses.sum())
        com = (masses[:, None] * pts).sum(axis=0) / total
        inertia = np.zeros((3, 3))
        for b, mass, p in zip(bodies, masses, pts):
            r_b = rot.T @ d.ximat[b].reshape(3, 3)
            inertia += r_b @ np.diag(m.body_inertia[b]) @ r_b.T
            r = p - com
            inertia += mass * (np.dot(r, r) * np.eye(3) - np.outer(r, r))
        return MassProperties(total, com, inertia)

    # -- internals -----------------------------------------------------------------------------
    def _body_twist(self) -> tuple[np.ndarray, np.ndarray]:
        w, d = self.world, self.data
        v = w.astrobee_dof
        rot = d.xmat[w.astrobee].reshape(3, 3)
        return rot.T @ d.qvel[v : v + 3], d.qvel[v + 3 : v + 6].copy()

    def _check_open(self) -> None:
        if self._closed:
            raise SimError("the SimDriver is closed")


__all__ = ["SimDriver", "WorldState"]
