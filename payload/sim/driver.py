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

The read-outs (:meth:`SimDriver.world_state`, :meth:`SimDriver.read`) are
:mod:`payload.sim.readout` and the control period (:meth:`SimDriver.step`) is
:mod:`payload.sim.control_period`, both bases of :class:`SimDriver`.
"""

from __future__ import annotations

from collections.abc import Callable
from types import TracebackType

import mujoco
import numpy as np

from payload.schema import N_MANIPULATION, PayloadCommand, VehicleTwist
from payload.sim.contact import Contact, ContactMonitor
from payload.sim.control_period import DriverControlPeriod
from payload.sim.readout import DriverReadout, WorldState
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
from payload.vecmath import clip

_AT_LIMIT = 1e-4  # [rad or m] a coordinate this close to a range end is at its limit
_WARNING_NAMES = tuple(
    name
    for name, value in sorted(mujoco.mjtWarning.__members__.items(), key=lambda kv: int(kv[1]))
    if name != "mjNWARNING"
)


class SimDriver(DriverControlPeriod, DriverReadout):
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
