"""The rail and base channels of the teleoperation pipeline (they bypass the retargeter).

- Rail: calibrated inter-wrist distance maps directly (and monotonically) to the rail.
- Base: a virtual sphere centred at the neutral left-wrist position. Outside it the left
  wrist sets the travel direction, and its displacement beyond the boundary scales the
  requested speed up to the nominal flight mode's 0.20 m/s (the paper's top speed). The
  vehicle turns toward the requested direction while translating. Acceleration and jerk
  are bounded. Braking is the paper's rule: when both wrists are back in their neutral
  spheres (each centred on its calibrated neutral position, same radius) the request is
  zero and the limiter brakes smoothly to rest. When the left wrist is back inside but
  the right wrist is still outside its sphere the channel *holds*: the request is the
  velocity already commanded, so the vehicle neither speeds up nor brakes (and keeps
  turning toward its travel direction) until the right wrist returns too or the left
  wrist leaves again. A lost hand (``None``) always brakes.

Directions are in the operator frame (workbench axes, X forward), which calibration
aligns with the vehicle's heading at the start; the channel outputs a body-frame twist.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.design.vehicle import DEFAULT_FLIGHT_MODE, FLIGHT_MODES
from payload.errors import PayloadError
from payload.rotations import yaw_matrix
from payload.schema import CONTROL_DT, VehicleTwist
from payload.vecmath import norm


class ChannelError(PayloadError):
    """A channel was given an invalid input (non-finite wrist, bad calibration)."""


class RailOrderError(ChannelError):
    """A rail calibration whose open distance is not larger than its closed one.

    Attributes:
        d_min: The closed (together) inter-wrist distance [m].
        d_max: The open (apart) one [m].
    """

    def __init__(self, d_min: float, d_max: float) -> None:
        self.d_min, self.d_max = d_min, d_max
        super().__init__(
            f"rail calibration: open distance {d_max:.3f} m must exceed closed "
            f"distance {d_min:.3f} m"
        )


@dataclass(frozen=True)
class RailConfig:
    """Rail channel mapping.

    Attributes:
        d_min: Inter-wrist distance mapped to rail 0 [m].
        d_max: Inter-wrist distance mapped to full travel [m].
        travel: Rail travel [m].
    """

    d_min: float
    d_max: float
    travel: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.d_min) and math.isfinite(self.d_max)):
            raise ChannelError("rail calibration: distances must be finite")
        if not self.d_max > self.d_min:
            raise RailOrderError(self.d_min, self.d_max)
        if not self.travel > 0:
            raise ChannelError("rail travel must be positive")


def rail_command(config: RailConfig, left_wrist: np.ndarray, right_wrist: np.ndarray) -> float:
    """Rail position [m] in [0, travel], non-decreasing in the inter-wrist distance."""
    d = float(norm(np.asarray(right_wrist) - np.asarray(left_wrist)))
    if not math.isfinite(d):
        raise ChannelError("rail channel: wrist position is not finite")
    s = (d - config.d_min) / (config.d_max - config.d_min)
    return config.travel * min(1.0, max(0.0, s))


@dataclass(frozen=True)
class BaseConfig:
    """Base channel settings (defaults: Astrobee's nominal flight mode, the paper's 0.20 m/s).

    Attributes:
        sphere_radius: Radius of the neutral sphere around the neutral left wrist [m].
        full_speed_offset: Displacement beyond the sphere that requests full speed [m].
        max_speed: Requested speed cap [m/s]: the nominal flight mode's speed (0.20, the
            paper's top speed too).
        max_accel: Linear acceleration bound [m/s^2]: the nominal flight mode's (0.0175).
        max_jerk: Linear jerk bound [m/s^3].
        max_yaw_rate: [rad/s] (Astrobee nominal: 0.1745).
        max_yaw_accel: [rad/s^2].
        max_yaw_jerk: [rad/s^3].
        yaw_gain: Heading error -> yaw rate [1/s].
        turn_min_speed: Requests slower than this do not turn the vehicle [m/s].
    """

    sphere_radius: float = 0.05
    full_speed_offset: float = 0.12
    max_speed: float = FLIGHT_MODES[DEFAULT_FLIGHT_MODE].speed
    max_accel: float = FLIGHT_MODES[DEFAULT_FLIGHT_MODE].accel
    max_jerk: float = 0.02
    max_yaw_rate: float = 0.1
    max_yaw_accel: float = 0.02
    max_yaw_jerk: float = 0.02
    yaw_gain: float = 0.4
    turn_min_speed: float = 0.02

    def speed_cap(self, dt: float) -> float:
        """The linear limiter's cap [m/s]: the speed cap less the limiter's landing margin
        (20 jerk steps of ``dt`` [s]), so the limited speed never overshoots ``max_speed``."""
        return self.max_speed - 20 * self.max_jerk * dt * dt

    def yaw_rate_cap(self, dt: float) -> float:
        """The yaw request's bound [rad/s]: the yaw-rate cap less the limiter's landing
        margin (10 jerk steps of ``dt`` [s]), so the limited rate never overshoots
        ``max_yaw_rate``."""
        return self.max_yaw_rate - 10.0 * self.max_yaw_jerk * dt * dt


class JerkLimiter:
    """Tracks a requested vector with bounded magnitude of rate and of rate change.

    Each step moves the internal acceleration toward the landing profile
    ``a* = e/|e| * min(a_max, sqrt(2 j_max |e|))`` by at most ``j_max dt``, so the output
    approaches the request without overshoot beyond the discretisation and its first and
    second differences stay within ``a_max`` and ``j_max``.
    """

    ZERO_ERROR = 1e-15
    """Below this magnitude of the braked error the landing acceleration is zero."""
    ZERO_VALUE = 1e-12
    """Below this magnitude of the value it has no outward direction for the cap."""

    def __init__(
        self, dim: int, max_rate: float, max_jerk: float, max_value: float | None = None
    ) -> None:
        self.value = np.zeros(dim)
        self.rate = np.zeros(dim)
        self.max_rate = max_rate
        self.max_jerk = max_jerk
        self.max_value = max_value
        self._bound: tuple[Any, Any, Any, Any] | None = None

    def settings(self) -> tuple:
        """The settings a compiled step is made for (a change to any makes it again): the
        bounds and the two zero thresholds (class constants, or an instance's own)."""
        return (self.max_rate, self.max_jerk, self.max_value, self.ZERO_ERROR, self.ZERO_VALUE)

    def reset(self, value: np.ndarray | None = None) -> None:
        self.value = np.zeros_like(self.value) if value is None else np.array(value, float)
        self.rate = np.zeros_like(self.rate)

    def step(self, target: np.ndarray, dt: float) -> np.ndarray:
        """Advance one step of ``dt`` [s] toward ``target`` (shape (dim,)); the new value."""
        if self.value.shape == (1,):
            return self._step_scalar(float(np.asarray(target, dtype=float).reshape(1)[0]), dt)
        step = self._stepper()
        if step is not None and np.shape(target) == self.value.shape:
            step(target, dt)  # the compiled step: value and rate updated in place
            return self.value.copy()
        return self._step_vector(target, dt)

    def _stepper(self) -> Any:
        """The compiled vector step (:mod:`payload.teleop.limiter_c`) bound to this
        limiter's current value and rate arrays, or None to run :meth:`_step_vector`."""
        bound = self._bound
        limits = self.settings()
        if (
            bound is not None
            and bound[0] is self.value
            and bound[1] is self.rate
            and bound[3] == limits
        ):
            return bound[2]
        from payload.teleop.limiter_c import compiled_limiter

        kernel = compiled_limiter(JerkLimiter)
        if kernel is not None:  # arrays of the limiter's own that the kernel updates
            self.value, self.rate = np.array(self.value, float), np.array(self.rate, float)
        step = kernel.stepper(self) if kernel is not None else None  # takes the limits now
        self._bound = (self.value, self.rate, step, limits)
        return step

    def _step_scalar(self, t: float, dt: float) -> np.ndarray:
        """:meth:`_step_vector` for one dimension in Python floats: the same operations in
        the same order (a 1-vector's norm is ``sqrt(x * x)``, its dot product one product),
        so the same bits, without numpy's per-call cost on one-element arrays."""
        value, rate = float(self.value[0]), float(self.rate[0])
        mj, mv = self.max_jerk, self.max_value
        if mv is not None:
            tn = math.sqrt(t * t)
            if tn > mv:
                t = t * (mv / tn)
        e = t - value
        jdt = mj * dt
        if e == 0.0 and math.sqrt(rate * rate) <= jdt:
            self.rate = np.zeros(1)
            return np.array([value])
        landing = e / dt
        if (
            math.sqrt(landing * landing) <= jdt
            and math.sqrt((landing - rate) * (landing - rate)) <= jdt
        ):
            self.rate = np.array([landing])
            self.value = np.array([t])
            return np.array([t])
        lead = rate * math.sqrt(rate * rate) / (2 * mj)
        e_eff = e - lead
        n = math.sqrt(e_eff * e_eff)
        a_target = (
            0.0 if n < self.ZERO_ERROR else e_eff / n * min(self.max_rate, math.sqrt(2 * mj * n))
        )
        da = a_target - rate
        vn = math.sqrt(value * value)
        if mv is not None and vn > self.ZERO_VALUE:
            u = value / vn
            cap = math.sqrt(2 * mj * max(0.0, mv - vn))
            radial_now = rate * u
            radial_want = min(a_target * u, cap)
            dr = min(max(radial_want - radial_now, -jdt), jdt)
            tangential = da - (da * u) * u
            budget = math.sqrt(max(0.0, jdt * jdt - dr * dr))
            tn = math.sqrt(tangential * tangential)
            if tn > budget:
                tangential *= budget / tn
            da = dr * u + tangential
            new = rate + da
            nn = math.sqrt(new * new)
            if nn > self.max_rate:
                da = new * (self.max_rate / nn) - rate
        else:
            dn = math.sqrt(da * da)
            if dn > jdt:
                da *= jdt / dn
        rate = rate + da
        value = value + rate * dt
        self.rate = np.array([rate])
        self.value = np.array([value])
        return np.array([value])

    def _step_vector(self, target: np.ndarray, dt: float) -> np.ndarray:
        target = np.asarray(target, dtype=float)
        if self.max_value is not None:
            tn = float(norm(target))
            if tn > self.max_value:
                target = target * (self.max_value / tn)
        e = target - self.value
        jdt = self.max_jerk * dt
        if not np.any(e) and float(norm(self.rate)) <= jdt:
            self.rate = np.zeros_like(self.rate)  # at rest on the target
            return self.value.copy()
        landing = e / dt
        if float(norm(landing)) <= jdt and float(norm(landing - self.rate)) <= jdt:
            # land exactly this step; the next step's return to zero rate is within jdt too
            self.rate = landing
            self.value = target.copy()
            return self.value.copy()
        # brake the acceleration already under way: the value still moves by a^2/(2j)
        lead = self.rate * norm(self.rate) / (2 * self.max_jerk)
        e_eff = e - lead
        n = float(norm(e_eff))
        if n < self.ZERO_ERROR:
            a_target = np.zeros_like(e)
        else:
            a_target = e_eff / n * min(self.max_rate, math.sqrt(2 * self.max_jerk * n))
        da = a_target - self.rate
        vn = float(norm(self.value))
        if self.max_value is not None and vn > self.ZERO_VALUE:
            # keep the magnitude below its cap: the outward rate follows a landing profile
            # onto the cap and gets the jerk budget first, so it is eased off in time
            u = self.value / vn
            cap = math.sqrt(2 * self.max_jerk * max(0.0, self.max_value - vn))
            radial_now = float(self.rate @ u)
            radial_want = min(float(a_target @ u), cap)
            dr = min(max(radial_want - radial_now, -jdt), jdt)  # np.clip's result
            tangential = da - float(da @ u) * u
            budget = math.sqrt(max(0.0, jdt * jdt - dr * dr))
            tn = float(norm(tangential))
            if tn > budget:
                tangential *= budget / tn
            da = dr * u + tangential
            new = self.rate + da
            nn = float(norm(new))
            if nn > self.max_rate:  # projecting onto the ball moves it by at most |da|
                da = new * (self.max_rate / nn) - self.rate
        else:
            dn = float(norm(da))
            if dn > jdt:
                da *= jdt / dn
        self.rate = self.rate + da
        self.value = self.value + self.rate * dt
        return self.value.copy()


@dataclass(frozen=True)
class BaseCommand:
    """Output of the base channel at one step.

    Attributes:
        v_request: Requested velocity before limiting, operator/world frame [m/s].
        v_world: Limited velocity command, world frame, shape (3,) [m/s].
        yaw_rate: Limited yaw-rate command [rad/s].
        twist: The body-frame twist for the vehicle controller.
        outside: Whether the left wrist is outside the neutral sphere.
        mode: ``drive`` (left wrist outside), ``hold`` (only the right wrist outside) or
            ``brake`` (both wrists in neutral, or a hand lost).
    """

    v_request: np.ndarray
    v_world: np.ndarray
    yaw_rate: float
    twist: VehicleTwist
    outside: bool
    mode: str = "brake"


class BaseChannel:
    """Virtual-sphere base channel with a jerk-limited output.

    Args:
        config: Settings.
        neutral_left: Neutral left-wrist position from calibration, shape (3,) [m].
        heading0: World yaw of the operator's forward direction [rad] (the vehicle's
            heading at calibration).
        dt: Control period [s].
        neutral_right: Neutral right-wrist position, shape (3,) [m]; None: the right
            wrist is not consulted (it always counts as in neutral).
    """

    def __init__(
        self,
        config: BaseConfig,
        neutral_left: np.ndarray,
        heading0: float = 0.0,
        dt: float = CONTROL_DT,
        neutral_right: np.ndarray | None = None,
    ) -> None:
        neutral = np.asarray(neutral_left, dtype=float)
        if neutral.shape != (3,) or not np.all(np.isfinite(neutral)):
            raise ChannelError("base channel: neutral wrist must be 3 finite numbers")
        right = None if neutral_right is None else np.asarray(neutral_right, dtype=float)
        if right is not None and (right.shape != (3,) or not np.all(np.isfinite(right))):
            raise ChannelError("base channel: neutral right wrist must be 3 finite numbers")
        self.config = config
        self.neutral = neutral
        self.neutral_right = right
        self.heading0 = heading0
        self.dt = dt
        # the limiter aims a hair below the cap so its discrete landing never overshoots it
        self.linear = JerkLimiter(3, config.max_accel, config.max_jerk, config.speed_cap(dt))
        self.yaw = JerkLimiter(1, config.max_yaw_accel, config.max_yaw_jerk)

    def request(self, left_wrist: np.ndarray | None) -> tuple[np.ndarray, bool]:
        """Requested world velocity for a left-wrist position (``None`` = brake)."""
        c = self.config
        if left_wrist is None:
            return np.zeros(3), False
        w = np.asarray(left_wrist, dtype=float)
        if w.shape != (3,) or not np.all(np.isfinite(w)):
            raise ChannelError("base channel: left wrist is not 3 finite numbers")
        disp = w - self.neutral
        dist = float(norm(disp))
        beyond = dist - c.sphere_radius
        if beyond <= 0:
            return np.zeros(3), False
        speed = c.max_speed * min(1.0, beyond / c.full_speed_offset)
        return yaw_matrix(self.heading0) @ (disp / dist) * speed, True

    def right_outside(self, right_wrist: np.ndarray | None) -> bool:
        """Whether the right wrist is outside its neutral sphere (False when it is not
        consulted: no right neutral, or no right wrist)."""
        if self.neutral_right is None or right_wrist is None:
            return False
        w = np.asarray(right_wrist, dtype=float)
        if w.shape != (3,) or not np.all(np.isfinite(w)):
            raise ChannelError("base channel: right wrist is not 3 finite numbers")
        return float(norm(w - self.neutral_right)) > self.config.sphere_radius

    def step(
        self,
        left_wrist: np.ndarray | None,
        vehicle_rotation: np.ndarray | None = None,
        right_wrist: np.ndarray | None = None,
        stamp: float = 0.0,
    ) -> BaseCommand:
        """One control step (:meth:`_step_numpy`, compiled when it can be:
        :mod:`payload.teleop.base_c`, the same bits; the settings, the neutral wrists and
        the heading are taken at the first step).

        Args:
            left_wrist: Filtered left-wrist position (operator frame) or ``None`` to brake.
            vehicle_rotation: Vehicle body -> world rotation, shape (3, 3) (identity if None).
            right_wrist: Filtered right-wrist position (operator frame); with the left
                wrist in neutral, the right one outside its sphere holds the velocity.
            stamp: The twist's time stamp [s].
        """
        step = self._compiled_step
        if step is not None:
            out = step(left_wrist, vehicle_rotation, right_wrist, stamp)
            if out is not None:
                return BaseCommand(*out)
        return self._step_numpy(left_wrist, vehicle_rotation, right_wrist, stamp)

    @property
    def yaw_cap(self) -> float:
        """The yaw request's bound [rad/s]: the yaw-rate cap less the limiter's landing
        margin (10 jerk steps), so the limited rate never overshoots the cap."""
        return self.config.yaw_rate_cap(self.dt)

    @functools.cached_property
    def _compiled_step(self) -> Any:
        from payload.teleop.base_c import compiled_base

        kernel = compiled_base(_base_channel)
        return None if kernel is None else kernel.stepper(self)

    def _step_numpy(
        self,
        left_wrist: np.ndarray | None,
        vehicle_rotation: np.ndarray | None = None,
        right_wrist: np.ndarray | None = None,
        stamp: float = 0.0,
    ) -> BaseCommand:
        """:meth:`step` in numpy."""
        c = self.config
        rot = np.eye(3) if vehicle_rotation is None else np.asarray(vehicle_rotation, float)
        v_req, outside = self.request(left_wrist)
        mode = "drive" if outside else "brake"
        if not outside and left_wrist is not None and self.right_outside(right_wrist):
            v_req, mode = self.linear.value.copy(), "hold"
        v = self.linear.step(v_req, self.dt)
        speed_req = float(norm(v_req[:2]))
        yaw_req = 0.0
        if speed_req > c.turn_min_speed:
            heading = math.atan2(rot[1, 0], rot[0, 0])
            desired = math.atan2(v_req[1], v_req[0])
            err = (desired - heading + math.pi) % (2 * math.pi) - math.pi
            cap = self.yaw_cap
            yaw_req = max(-cap, min(cap, c.yaw_gain * err))
        yaw_rate = float(self.yaw.step(np.array([yaw_req]), self.dt)[0])
        twist = VehicleTwist(rot.T @ v, rot.T @ np.array([0.0, 0.0, yaw_rate]), stamp)
        return BaseCommand(v_req, v, yaw_rate, twist, outside, mode)


def _base_channel(
    neutral_left: np.ndarray, heading0: float, neutral_right: np.ndarray | None
) -> BaseChannel:
    """A base channel with the default settings (the compiled step's self-check)."""
    return BaseChannel(BaseConfig(), neutral_left, heading0, CONTROL_DT, neutral_right)
