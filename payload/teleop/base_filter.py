"""The base safety filter: a control-barrier QP between the base channel and the vehicle.

Every collision shape that moves with the vehicle (Astrobee, the deployed payload, the
held CTB: from the first opposing contact of the pinch until a second after the last) is
sampled as points on the surface of its oriented bounding box (corners,
then edges and faces at :attr:`SafetyConfig.spacing`), placed from the poses MuJoCo
measures each control step. The obstacles are the complement of the keep-in union
(:meth:`payload.sim.zones.StationZones.obstacles`) plus the keep-out boxes. For a sample
point ``p`` at distance ``d`` from an obstacle box, with ``n`` the unit vector from the
box's closest point to ``p`` (so at the hatch's rim it points diagonally), the barrier
asks that the point's closing speed be one the vehicle can still stop from::

    n . (v + w e_z x r)  >=  -v_stop(d - margin)

and, in a second row, ``n . v >= -v_stop(d - margin)``: a turn that carries the point
toward the obstacle adds to its closing speed, one that carries it away buys the vehicle
no closer approach (the turn ends, or brings another corner round, long before the
loaded stack has stopped). ``v`` the world linear velocity, ``w`` the yaw rate,
``r = p - c`` (``c`` Astrobee's centre), and ``v_stop(s)`` the largest speed from which
the chain after the filter (the jerk-limited output stage at the base channel's bounds,
then the vehicle controller's reference with the acceleration the nozzle polytope gives
the loaded stack, :attr:`payload.sim.vehicle.VehicleController.accel_max`) stops within
``s`` (:func:`stop_speed`). Inside the margin the point must move out at a small speed.

The filter solves ``min |x - x_req|_W`` over ``x = (v, w)`` under those constraints with
DAQP (a dual active-set solver for small dense QPs). When the request already meets every
constraint and the output stage has caught up with it, the filter returns the request
object itself: far from every wall it is exactly the identity. Its output is scaled to the
base channel's speed and yaw-rate caps and passes through jerk limiters with the channel's
acceleration and jerk bounds, so it never asks more than the channel would.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import daqp
import mujoco
import numpy as np

from payload.schema import CONTROL_DT, VehicleTwist
from payload.sim.contact import ContactMonitor
from payload.sim.zones import StationZones, station_zones
from payload.teleop.barrier_c import geometry_kernels
from payload.teleop.channels import BaseConfig, JerkLimiter
from payload.teleop.filter_kernel import stop_speed_many

_INF = 1e30

MARGIN_TOLERANCE = 0.01
"""What the least distance to the station may fall below the margin [m], as MuJoCo
measures it: the filter samples each box at 0.1 m, acts once per control step (4 mm at
0.2 m/s) and does not model the bag's swing in the pinch between two steps. The tests
and ``analyses/filter_sweep.py`` judge the filter by it."""


@dataclass(frozen=True)
class SafetyConfig:
    """Settings of the base safety filter.

    Attributes:
        margin: Least distance [m] every vehicle, payload and CTB shape keeps from the
            keep-in boundary. Default 0.05: Astrobee's flight software pads its 0.28 m
            radius by 0.02 m for a robot flown by its own planner; a teleoperated stack
            with a bag held in a pinch swings by about 25 mm under a strike and moves up
            to 4 mm per control step at 0.2 m/s, so 0.05 m keeps room for both while the
            hatch (1.3 m) still leaves 0.24 m above and below the loaded stack.
        spacing: Largest spacing of the sample points on a shape's box [m].
        recovery_gain: Inside the margin, the outward speed asked per metre of
            intrusion [1/s].
        recovery_speed: Cap on that outward speed [m/s].
        yaw_weight: Length that weighs a yaw-rate change against a velocity change in
            the QP's cost [m] (about the stack's reach from Astrobee's centre).
    """

    margin: float = 0.05
    spacing: float = 0.1
    recovery_gain: float = 0.5
    recovery_speed: float = 0.02
    yaw_weight: float = 0.5

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"SafetyConfig.{name}: must be a positive number, got {value!r}")


def stop_speed(
    distance: np.ndarray, accel: np.ndarray | float, jerk: float, lag: float
) -> np.ndarray:
    """Largest closing speed [m/s] from which a jerk-limited brake stops within
    ``distance`` [m] (0 for distances <= 0).

    Worst case: the stage is accelerating toward the wall at ``accel`` and keeps doing so
    for ``lag`` [s] before the brake starts ramping the acceleration down at ``jerk``. The
    speed grows to at most ``u = v + accel lag + accel^2 / (2 jerk)``; the lag and the two
    ramps (``accel / jerk`` each) cover at most ``u (lag + 2 accel / jerk)`` and the full
    deceleration ``u^2 / (2 accel)``. That bound is solved here for ``v``.
    """
    return np.asarray(stop_speed_many(distance, accel, float(jerk), float(lag)), float)


def _grid(n: int) -> np.ndarray:
    return np.linspace(-1.0, 1.0, n + 1)


def box_samples(counts: tuple[int, int, int]) -> np.ndarray:
    """Points on the surface of the unit box [-1, 1]^3: a grid of ``counts`` (3,)
    intervals per axis on each face (corners and edges included).

    Returns:
        Shape (K, 3), to be scaled by a box's half-extents.
    """
    pts = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        gu, gv = np.meshgrid(_grid(counts[u]), _grid(counts[v]), indexing="ij")
        for side in (-1.0, 1.0):
            p = np.zeros((gu.size, 3))
            p[:, axis] = side
            p[:, u] = gu.ravel()
            p[:, v] = gv.ravel()
            pts.append(p)
    return np.unique(np.round(np.vstack(pts), 12), axis=0)


def _moving_geoms(world: Any, which: str) -> np.ndarray:
    m = world.model
    out = []
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if not (m.geom_contype[g] or m.geom_conaffinity[g]):
            continue
        if which == "ctb" and b == world.ctb and world.ctb >= 0:
            out.append(g)
        elif which == "astrobee" and b == world.astrobee:
            out.append(g)
        elif which == "payload" and b != world.astrobee and m.body_rootid[b] == world.astrobee:
            out.append(g)
    return np.array(out, dtype=int)


class _Shape:
    """One box moving with the vehicle: the oriented box enclosing the collision geoms of
    Astrobee, of the payload, or of the CTB, in the frame of its reference body."""

    def __init__(
        self, world: Any, kind: str, spacing: float, enclosing_box: Callable[..., tuple]
    ) -> None:
        m = world.model
        self._enclosing_box = enclosing_box  # filter_kernel.enclosing_box, compiled
        self.kind = kind
        self.body = world.ctb if kind == "ctb" else world.astrobee
        self.geoms = _moving_geoms(world, kind)
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        aabb = m.geom_aabb[self.geoms]  # (G, 6): centre, half-extent in the geom frame
        corners = (aabb[:, None, :3] + signs[None] * aabb[:, None, 3:]).reshape(-1, 3)
        self.corners = np.ascontiguousarray(corners)  # as the compiled pass reads them
        self.corner_geom = np.repeat(self.geoms, 8)  # the geom of each corner
        self.spacing = spacing
        self.unit: np.ndarray | None = None
        self.refresh_steps = 10 if kind == "payload" else 0
        self.local_centre = np.zeros(3)
        self.half = np.zeros(3)
        self._age = 0

    def refresh(self, data: mujoco.MjData) -> None:
        """Measure the enclosing box in the reference body's frame from the geoms' poses."""
        lo, hi = self._enclosing_box(
            data.geom_xpos,
            data.geom_xmat,
            self.corner_geom,
            self.corners,
            data.xpos[self.body],
            data.xmat[self.body].reshape(3, 3),
        )
        self.local_centre = (lo + hi) / 2.0
        self.half = (hi - lo) / 2.0
        if self.unit is None:  # the sampling grid is set by the first box
            counts = tuple(max(1, math.ceil(2.0 * h / self.spacing)) for h in self.half)
            self.unit = box_samples(counts)  # type: ignore[arg-type]
        self._age = 0

    def box(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre (3,), rotation (3, 3), half-extents (3,)) of the enclosing box [m],
        world frame. Astrobee's and the CTB's boxes are rigid in their bodies; the
        payload's (its fingers and rail move) is measured again every ``refresh_steps``
        calls."""
        if self.unit is None or (self.refresh_steps and self._age >= self.refresh_steps):
            self.refresh(data)
        self._age += 1
        frame = data.xmat[self.body].reshape(3, 3)
        return data.xpos[self.body] + frame @ self.local_centre, frame, self.half

    def points(self, centre: np.ndarray, rot: np.ndarray, half: np.ndarray) -> np.ndarray:
        """World positions of the sample points, shape (K, 3) [m]."""
        assert self.unit is not None
        return centre + (self.unit * half) @ rot.T


class FilterStatus(NamedTuple):
    """What the filter did at one control step (recorded per step).

    Attributes:
        active: The filter changed the command (or its output stage was catching up).
        clearance: Least distance from any sample point to an obstacle within reach
            [m] (``reach`` when none is within it).
        shape: Kind of the shape closest to an obstacle (``astrobee``, ``payload``,
            ``ctb``), or ``""`` when none is within reach.
        face: The obstacle it is closest to (``<keep-in box> <axis><sign>``).
        change: Norm of the change of the world linear velocity [m/s].
        yaw_change: Change of the yaw rate [rad/s].
        constraints: Constraints in the QP (0 when not solved).
        solve_us: Time of the whole filter step [us].
    """

    active: bool
    clearance: float
    shape: str
    face: str
    change: float
    yaw_change: float
    constraints: int
    solve_us: float


class BaseSafetyFilter:
    """The base safety filter (see the module docstring).

    Each step's geometry is one compiled pass over every shape, sample point and obstacle
    box (:func:`payload.teleop.filter_kernel.barrier_rows`); what is constant for the
    filter's life (the shapes' local sample points, the QP's cost matrix and bounds, the
    braking constants) is computed once, here or when a shape's box is measured again.

    Args:
        world: The simulator's :class:`~payload.sim.world.World`.
        base: The base channel's settings (speed, acceleration and jerk bounds).
        vehicle_accel: Linear acceleration the vehicle controller gives the loaded stack
            per body axis, shape (3,) [m/s^2] (its ``accel_max``, from the nozzle
            polytope and the carried mass).
        vehicle_jerk: The controller's linear jerk bound [m/s^3].
        zones: Keep-in and keep-out boxes (default: the world's layout).
        config: Filter settings.
        per_face: Sample points kept per (shape, obstacle box) pair, the most binding
            at the request; each gives two constraints (with and without the yaw term).
    """

    def __init__(
        self,
        world: Any,
        base: BaseConfig,
        vehicle_accel: np.ndarray,
        vehicle_jerk: float,
        zones: StationZones | None = None,
        config: SafetyConfig | None = None,
        per_face: int = 4,
    ) -> None:
        self.world = world
        self.base = base
        self.config = config or SafetyConfig()
        self.zones = zones or station_zones(world.layout)
        self.obs_lo, self.obs_hi, self.obs_names = self.zones.obstacles()
        kinds = ("astrobee", "payload", "ctb") if world.ctb >= 0 else ("astrobee", "payload")
        # the geometry's compiled pass: C, else Numba (payload.teleop.barrier_c)
        self._barrier_rows, self._enclosing_box = geometry_kernels()
        self.all_shapes = [
            _Shape(world, k, self.config.spacing, self._enclosing_box) for k in kinds
        ]
        self.shapes = self.all_shapes
        # the CTB moves with the vehicle only while the pinch holds it: it counts from the
        # first opposing contact until ``release_s`` after the last one
        self.contacts = ContactMonitor(world) if world.ctb >= 0 else None
        self.release_s = 1.0
        self._held_until = -math.inf
        self.per_face = per_face
        # braking: the output stage (channel bounds) and the controller (polytope bounds)
        self.body_accel = np.minimum(np.asarray(vehicle_accel, float), base.max_accel)
        self.jerk = min(base.max_jerk, vehicle_jerk)
        # how long the chain may keep accelerating toward a wall once the filter brakes:
        # two control periods, the output stage's own ramp down from the channel's
        # acceleration, and the controller's reference's ramp down from the stack's
        self.lag = (
            2.0 * CONTROL_DT
            + base.max_accel / base.max_jerk
            + float(self.body_accel.max()) / vehicle_jerk
        )
        self.weights = np.array([1.0, 1.0, 1.0, self.config.yaw_weight**2])
        # the channel's caps less its limiters' landing margins: capped at the channel's
        # speed and yaw rate themselves, a limiter's discrete landing overshoots them
        self.speed_cap = base.speed_cap(CONTROL_DT)
        self.yaw_rate_cap = base.yaw_rate_cap(CONTROL_DT)
        self.linear = JerkLimiter(3, base.max_accel, base.max_jerk, self.speed_cap)
        self.yaw = JerkLimiter(1, base.max_yaw_accel, base.max_yaw_jerk, self.yaw_rate_cap)
        self.engaged = False
        self._last: np.ndarray | None = None
        self.status = FilterStatus(False, math.inf, "", "", 0.0, 0.0, 0, 0.0)
        # constant per filter: the QP's cost and bounds, the shapes' bodies, the obstacles,
        # the braking constants, the output arrays of the compiled pass
        c = self.config
        most = 2 * per_face * len(kinds) * len(self.obs_names)  # rows of one step, at most
        self._hessian = np.diag(self.weights)
        self._minus_weights = -self.weights
        self._upper = np.full(most, _INF)
        bodies = np.array([s.body for s in self.all_shapes], dtype=np.int64)
        self._bodies = [bodies[:n] for n in range(len(kinds) + 1)]  # of the first n shapes
        self._obs = np.stack([self.obs_lo, self.obs_hi])  # (2, M, 3)
        braking = [c.margin, self.jerk, self.lag, c.recovery_gain, c.recovery_speed]
        self._params = np.array([*braking, *self.body_accel])
        self._rows = np.empty((most, 4))  # the rows A of a step
        self._out = np.empty((2, most))  # their bounds b and slack
        self._lower = [np.empty((n, len(self.obs_names))) for n in range(len(kinds) + 1)]
        self._packed = False  # the arrays below follow the shapes' measured boxes
        self._boxes = np.zeros((2, len(kinds), 3))  # each box's centre (body frame), half
        self._local = np.zeros((0, 3))  # every sample point, its body's frame (K, 3)
        self._scratch = np.zeros((0, 3))  # the sample points in the world (K, 3)
        self._n_points = np.zeros(len(kinds) + 1, dtype=np.int64)  # of the first i shapes
        self._warm_up()

    def _warm_up(self) -> None:
        """Call the compiled functions once with empty inputs of the step's types, so that
        the first control step does not wait (Numba's load them from its disk cache, or
        compile them, at their first call)."""
        empty, none = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        rot = np.eye(3)
        self._enclosing_box(empty, np.zeros((0, 9)), none, empty, np.zeros(3), rot)
        self._barrier_rows(
            rot.reshape(1, 9),
            np.zeros((1, 3)),
            0,
            none,
            np.zeros((2, 0, 3)),
            empty,
            self._n_points[:1],
            self._obs,
            np.zeros(4),
            self._params,
            self.per_face,
            self._rows,
            self._out,
            self._lower[0],
            empty,
        )

    def __call__(self, twist: VehicleTwist, data: mujoco.MjData) -> VehicleTwist:
        """The filtered body twist for the request ``twist`` at the state in ``data``."""
        start = time.perf_counter()
        if self.contacts is not None:
            now = float(data.time)
            if self.contacts.opposing(data):
                self._held_until = now + self.release_s
            held = now <= self._held_until
            self.shapes = self.all_shapes if held else self.all_shapes[:2]
        rot = data.xmat[self.world.astrobee].reshape(3, 3)
        centre = data.xpos[self.world.astrobee]
        ang = rot @ twist.angular
        req = np.empty(4)  # world velocity and yaw rate
        np.matmul(rot, twist.linear, out=req[:3])
        req[3] = ang[2]
        rows, b, least, clearance, shape, face = self._constraints(data, rot, centre, req)
        violated = least < 0.0
        if not violated and not self.engaged:
            self._follow(req)
            self.status = FilterStatus(
                False, clearance, shape, face, 0.0, 0.0, 0, (time.perf_counter() - start) * 1e6
            )
            return twist
        target = req
        used = 0
        if violated:
            used = int(b.size)
            target = self._solve(req, rows, b)
        out = np.empty(4)
        out[:3] = self.linear.step(target[:3], CONTROL_DT)
        out[3] = self.yaw.step(target[3:], CONTROL_DT)[0]
        self.engaged = violated or out.tolist() != req.tolist()
        if not self.engaged:
            self._follow(req)
            out = req
        self._last = out
        ang[2] = out[3]
        lin, ang = rot.T @ out[:3], rot.T @ ang
        lin.setflags(write=False)  # the twist's own: taken as they are
        ang.setflags(write=False)
        filtered = VehicleTwist.of_frozen(lin, ang, twist.stamp)
        change = out[:3] - req[:3]
        self.status = FilterStatus(
            True,
            clearance,
            shape,
            face,
            math.sqrt(change @ change),
            float(out[3] - req[3]),
            used,
            (time.perf_counter() - start) * 1e6,
        )
        return filtered

    def _follow(self, req: np.ndarray) -> None:
        """Keep the output stage on the request (rate from the last two outputs)."""
        rate = np.zeros(4) if self._last is None else (req - self._last) / CONTROL_DT
        self.linear.value, self.linear.rate = req[:3].copy(), rate[:3].copy()
        self.yaw.value, self.yaw.rate = req[3:].copy(), rate[3:].copy()
        self._last = req

    def _measure(self, data: mujoco.MjData, n: int) -> None:
        """Measure again the boxes of the first ``n`` shapes that are due (see
        :meth:`_Shape.box`), and pack every shape's box and sample points in arrays."""
        changed = not self._packed
        for shape in self.all_shapes[:n]:
            if shape.unit is None or (shape.refresh_steps and shape._age >= shape.refresh_steps):
                shape.refresh(data)
                changed = True
            shape._age += 1
        if not changed:
            return
        ready = [s for s in self.all_shapes if s.unit is not None]
        if self._packed and len(self._local) == self._n_points[len(ready)]:
            # the same sample points, measured again: update each shape's in place
            for i, s in enumerate(ready):
                a, b = self._n_points[i], self._n_points[i + 1]
                self._local[a:b] = s.local_centre + s.unit * s.half  # type: ignore[operator]
                self._boxes[0, i], self._boxes[1, i] = s.local_centre, s.half
            return
        for i, s in enumerate(ready):
            self._boxes[0, i], self._boxes[1, i] = s.local_centre, s.half
        local = [s.local_centre + s.unit * s.half for s in ready]  # type: ignore[operator]
        self._local = np.vstack(local)
        self._scratch = np.empty_like(self._local)
        self._n_points[: len(ready) + 1] = np.cumsum([0, *(len(p) for p in local)])
        self._packed = True

    def _constraints(
        self, data: mujoco.MjData, rot: np.ndarray, centre: np.ndarray, req: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float, float, str, str]:
        """Rows ``A x >= b`` of the (point, obstacle) pairs that could bind, their least
        slack at the request (inf: no row), and the least clearance with its shape and
        obstacle.

        A (shape, obstacle) pair is skipped when the two are separated along a world
        axis by more than the margin and the request's closing speed along that axis
        (translation plus the yaw rate times the shape's lever) is one the stack stops
        from within the separation; when every pair is skipped (the conservative bound
        that decides the identity) no row is built. The others are checked at every
        sample point of the shape, and the ``per_face`` rows of least slack kept
        (:func:`payload.teleop.filter_kernel.barrier_rows`, one compiled pass).
        """
        n = len(self.shapes)
        self._measure(data, n)
        lower = self._lower[n]
        count, least = self._barrier_rows(
            data.xmat,
            data.xpos,
            self.world.astrobee,
            self._bodies[n],
            self._boxes,
            self._local,
            self._n_points,
            self._obs,
            req,
            self._params,
            self.per_face,
            self._rows,
            self._out,
            lower,
            self._scratch,
        )
        si, mi = divmod(int(lower.argmin()), lower.shape[1])
        return (
            self._rows[:count],
            self._out[0, :count],
            least,
            float(lower[si, mi]),
            self.shapes[si].kind,
            self.obs_names[mi],
        )

    def _solve(self, req: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The least (weighted) change of ``req`` meeting ``a x >= b``, then capped to the
        channel's speed and yaw rate; rest if even holding every distance is infeasible."""
        h = self._hessian
        f = self._minus_weights * req
        upper = self._upper[: b.size]
        x, _, flag, _ = daqp.solve(h, f, a, upper, b.copy())
        if flag != 1:  # conflicting recoveries: hold every distance instead
            x, _, flag, _ = daqp.solve(h, f, a, upper, np.minimum(b, 0.0))
        if flag != 1:
            return np.zeros(4)
        speed, rate = math.sqrt(x[:3] @ x[:3]), abs(float(x[3]))
        scale = min(1.0, self.speed_cap / max(speed, 1e-12))
        scale = min(scale, self.yaw_rate_cap / max(rate, 1e-12))
        return x * scale  # scaling toward rest keeps every b <= 0 row met

    def reset(self) -> None:
        """Forget the output stage's state (a new session)."""
        self.engaged = False
        self._last = None
        self._held_until = -math.inf
        for shape in self.all_shapes:
            shape.unit = None
        self._packed = False
        self.linear.reset()
        self.yaw.reset()


__all__ = [
    "MARGIN_TOLERANCE",
    "BaseSafetyFilter",
    "FilterStatus",
    "SafetyConfig",
    "box_samples",
    "stop_speed",
]
