"""``payload bench sim``: real-time factor of the full CTB scene under the 50 Hz loop.

A scripted operator drives the scene, so the figure is the simulator's own cost: it
pinches the CTB handle with fixed joint commands, then flies the cargo route with
body-twist commands (carrot following, braking to stop at the end). Every control step
does the simulator's part of the teleoperation loop: read the payload, read the world
state (poses, contacts, indicator), send a payload command and a vehicle twist, advance
20 physics steps. ``payload bench trial`` measures the whole path with the teleoperation
pipeline, the synthetic operator and the recorder.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.rotations import quat_to_matrix, yaw_of_matrix
from payload.schema import PayloadCommand, VehicleTwist
from payload.sim.driver import SimDriver, WorldState
from payload.sim.vehicle import DEFAULT_FLIGHT_MODE, DEFAULT_PROPULSION, FLIGHT_MODES
from payload.sim.world import CONTROL_DT, PHYSICS_DT, SimError, World, WorldConfig, build_world


class RouteFollower:
    """Body-twist commands that fly Astrobee along a polyline and stop at its end.

    Carrot following: translate toward a point ``lookahead`` ahead on the route, head
    along the carrot's leg, brake (``sqrt(2 b d)``) into every turn sharper than
    ``corner`` and into the end, creeping through the turns.

    Args:
        waypoints: Route, shape (n, 3) [m, world frame].
        speed: Cruise speed [m/s].
        brake: Deceleration planned for stopping [m/s^2].
        omega: Yaw-rate bound [rad/s].
        lookahead: Carrot distance along the route [m].
        yaw_gain: Heading feedback gain [1/s].
        creep: Speed through sharp turns [m/s].
        corner: Turn angle from which the follower brakes into a waypoint [rad].
    """

    def __init__(
        self,
        waypoints: np.ndarray,
        speed: float,
        brake: float,
        omega: float,
        lookahead: float = 0.5,
        yaw_gain: float = 0.5,
        creep: float = 0.01,
        corner: float = 0.35,
    ) -> None:
        self.waypoints = np.asarray(waypoints, float)
        if self.waypoints.ndim != 2 or self.waypoints.shape[0] < 2 or self.waypoints.shape[1] != 3:
            raise SimError("RouteFollower: waypoints must have shape (n >= 2, 3)")
        for name, value in (("speed", speed), ("brake", brake), ("omega", omega)):
            if not (math.isfinite(value) and value > 0):
                raise SimError(f"RouteFollower.{name}: must be positive, got {value}")
        self.speed, self.brake, self.omega = speed, brake, omega
        self.lookahead, self.yaw_gain, self.creep = lookahead, yaw_gain, creep
        seg = np.diff(self.waypoints, axis=0)
        self._len = np.linalg.norm(seg, axis=1)
        if np.any(self._len <= 0):
            raise SimError("RouteFollower: repeated waypoint")
        self._dir = seg / self._len[:, None]
        self._cum = np.concatenate([[0.0], np.cumsum(self._len)])
        self.length = float(self._cum[-1])
        turns = np.arccos(np.clip(np.sum(self._dir[:-1] * self._dir[1:], axis=1), -1.0, 1.0))
        self._stops = np.append(self._cum[1:-1][turns > corner], self.length)

    def progress(self, pos: np.ndarray) -> float:
        """Arc length [m] of the route point nearest to ``pos`` (3,)."""
        best, best_d = 0.0, np.inf
        for i in range(len(self._len)):
            s = float(np.clip(np.dot(pos - self.waypoints[i], self._dir[i]), 0.0, self._len[i]))
            d = float(np.linalg.norm(self.waypoints[i] + s * self._dir[i] - pos))
            if d < best_d:
                best, best_d = self._cum[i] + s, d
        return best

    def point(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Route point and unit direction at arc length ``s`` [m]."""
        s = float(np.clip(s, 0.0, self.length))
        i = int(min(np.searchsorted(self._cum, s, side="right") - 1, len(self._len) - 1))
        return self.waypoints[i] + (s - self._cum[i]) * self._dir[i], self._dir[i]

    def twist(self, pos: np.ndarray, quat: np.ndarray, stamp: float) -> VehicleTwist:
        """The body twist to command at pose (``pos`` (3,), ``quat`` (4,) w x y z)."""
        s = self.progress(pos)
        end, _ = self.point(self.length)
        if self.length - s < 0.01 and np.linalg.norm(end - pos) < 0.05:
            return VehicleTwist.zero(stamp)
        stop = float(self._stops[np.searchsorted(self._stops, s + 1e-3)])
        floor = self.creep if stop < self.length else 0.0
        speed = min(self.speed, max(floor, math.sqrt(2.0 * self.brake * max(stop - s, 0.0))))
        carrot, heading = self.point(s + self.lookahead)
        to_carrot = carrot - pos
        dist = float(np.linalg.norm(to_carrot))
        v_world = to_carrot / dist * min(speed, dist) if dist > 1e-9 else np.zeros(3)
        rot = quat_to_matrix(quat)
        v_body = rot.T @ v_world
        err = math.atan2(heading[1], heading[0]) - yaw_of_matrix(rot)
        err = (err + math.pi) % (2.0 * math.pi) - math.pi
        wz = float(np.clip(self.yaw_gain * err, -self.omega, self.omega))
        return VehicleTwist(v_body, np.array([0.0, 0.0, wz]), stamp)


class ScriptedOperator:
    """Stands in for the teleoperation pipeline: grasp the handle, then fly the route.

    Phases: hold the home posture for ``settle`` s, pre-shape the pinch for ``preshape`` s,
    close it for ``close`` s, then follow the route (vehicle controller on).

    Args:
        world: The world (its pinch grasp and route are used).
        brake: Deceleration for stopping at the route's end [m/s^2].
        speed: Cruise speed [m/s] (default: the default flight mode's speed cap).
        omega: Yaw-rate bound [rad/s] (default: the default flight mode's rate cap).
    """

    def __init__(
        self,
        world: World,
        brake: float,
        speed: float = FLIGHT_MODES[DEFAULT_FLIGHT_MODE].speed,
        omega: float = FLIGHT_MODES[DEFAULT_FLIGHT_MODE].omega,
        settle: float = 0.5,
        preshape: float = 1.0,
        close: float = 1.5,
    ) -> None:
        self.world = world
        pinch = world.pinch
        home = world.design.home
        self._home = np.array([*home.finger * 4, home.rail])
        self._open = pinch.command_q(False)
        self._closed = pinch.command_q(True)
        self._stage = pinch.stage
        self.t_preshape = settle
        self.t_close = settle + preshape
        self.t_fly = settle + preshape + close
        self.route = RouteFollower(world.layout.route(), speed, brake, omega)

    def __call__(self, state: WorldState) -> tuple[PayloadCommand, VehicleTwist | None]:
        """Payload command and vehicle twist (None = controller off) for this step."""
        t = state.time
        if t < self.t_preshape:
            q = self._home
        elif t < self.t_close:
            q = self._open
        else:
            q = self._closed
        twist = None
        if t >= self.t_fly:
            twist = self.route.twist(state.astrobee_pos, state.astrobee_quat, t)
        return PayloadCommand(q, self._stage, t), twist


@dataclass(frozen=True)
class BenchResult:
    """Figures of one ``payload bench sim`` run.

    ``realtime_factor`` = simulated / wall seconds of the control loop (world building
    excluded); ``cpu_realtime_factor`` = simulated / process CPU seconds, the same figure
    undisturbed by other processes sharing the core.
    """

    sim_seconds: float
    wall_seconds: float
    realtime_factor: float
    physics_hz: float
    control_hz: float
    cpu_seconds: float
    cpu_realtime_factor: float
    control_steps: int
    flight_mode: str
    ctb: str | None
    propulsion: str
    accel_max: list[float]
    pinned_cpu: int | None
    opposing_contact_fraction: float
    vehicle_distance: float
    ctb_displacement: float
    module: str | None
    warnings: dict[str, int]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the issue's field names first)."""
        return dict(self.__dict__)


@contextmanager
def _one_core(pin: bool):
    """Restrict this process to one CPU (Linux) for the duration; yields the CPU or None."""
    if not pin or not hasattr(os, "sched_setaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpu = min(before)
    os.sched_setaffinity(0, {cpu})
    try:
        yield cpu
    finally:
        os.sched_setaffinity(0, before)


def run_bench(
    seconds: float = 60.0,
    *,
    config: WorldConfig | None = None,
    flight_mode: str = "nominal",
    pin: bool = False,
    progress: Callable[[float], None] | None = None,
    propulsion: str = DEFAULT_PROPULSION,
) -> BenchResult:
    """Run the full CTB scene under the scripted 50 Hz loop and time it.

    Args:
        seconds: Simulated time [s].
        config: World to build (default: single CTB).
        flight_mode: Astrobee flight mode.
        pin: Restrict the run to one CPU core (Linux). The loop is single-threaded either
            way; ``cpu_seconds`` (process CPU time) gives the one-core figure free of other
            processes' load, ``wall_seconds`` the elapsed time.
        progress: Called with the simulated time every 50 control steps.
        propulsion: ``nozzles`` or ``box`` (:mod:`payload.sim.vehicle`).

    Returns:
        The figures; the wall time covers the control loop only (not building the world).
    """
    if not (math.isfinite(seconds) and seconds > 0):
        raise SimError(f"--seconds must be a positive number of seconds, got {seconds}")
    world = build_world(config)
    with SimDriver(world, flight_mode=flight_mode, propulsion=propulsion) as sim:
        operator = ScriptedOperator(world, brake=0.8 * float(sim.controller.accel_max[0]))
        steps = max(1, round(seconds / CONTROL_DT))
        state = sim.world_state()
        start_pos = state.astrobee_pos.copy()
        start_ctb = None if state.ctb_pos is None else state.ctb_pos.copy()
        contact_steps = fly_steps = 0
        with _one_core(pin) as cpu:
            t0, c0 = time.perf_counter(), time.process_time()
            for k in range(steps):
                sim.read()
                command, twist = operator(state)
                sim.send(command)
                sim.command_twist(twist)
                state = sim.step()
                if state.time >= operator.t_fly:
                    fly_steps += 1
                    contact_steps += state.opposing_contact
                if progress is not None and k % 50 == 49:
                    progress(state.time)
            wall = time.perf_counter() - t0
            cpu_time = time.process_time() - c0
        sim_seconds = steps * CONTROL_DT
        return BenchResult(
            sim_seconds=sim_seconds,
            wall_seconds=wall,
            realtime_factor=sim_seconds / wall,
            physics_hz=1.0 / PHYSICS_DT,
            control_hz=1.0 / CONTROL_DT,
            cpu_seconds=cpu_time,
            cpu_realtime_factor=sim_seconds / cpu_time if cpu_time > 0 else math.inf,
            control_steps=steps,
            flight_mode=sim.controller.mode.name,
            ctb=world.config.ctb,
            propulsion=sim.propulsion,
            accel_max=[float(a) for a in sim.controller.accel_max],
            pinned_cpu=cpu,
            opposing_contact_fraction=contact_steps / fly_steps if fly_steps else 0.0,
            vehicle_distance=float(np.linalg.norm(state.astrobee_pos - start_pos)),
            ctb_displacement=(
                float(np.linalg.norm(state.ctb_pos - start_ctb)) if start_ctb is not None else 0.0
            ),
            module=state.module.value if state.module is not None else None,
            warnings=sim.warnings(),
        )


__all__ = ["BenchResult", "RouteFollower", "ScriptedOperator", "run_bench"]
