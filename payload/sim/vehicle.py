"""Astrobee's vehicle controller: a bounded body wrench tracking a commanded body twist.

The commanded twist is shaped into a reference with bounded speed, acceleration and jerk
(per axis); a feedforward plus velocity-feedback law turns the reference into a body-frame
force and torque, each clipped per axis to the propulsion limits of the flight mode.
The controller knows the mass properties of what it carries (Astrobee, payload and, when
told, the CTB). A force at Astrobee's centre of mass pitches or rolls a stack whose centre
of mass hangs below it, so the force bound per axis is the smaller of the mode's and what
the torque bound can balance; the reference acceleration stays within the mode's bound and
a share of that force bound over the carried mass. Runs at the 50 Hz control rate.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from payload.design.vehicle import DEFAULT_FLIGHT_MODE, FLIGHT_MODES, FlightMode
from payload.errors import PayloadError
from payload.schema import VehicleTwist
from payload.sim.propulsion import Allocation, shared_propulsion
from payload.vecmath import norm, read_only


class VehicleError(PayloadError):
    """Bad vehicle-controller parameters or commands."""


PROPULSION_MODELS: tuple[str, ...] = ("nozzles", "box")
"""``nozzles``: the 12-nozzle allocation (:mod:`payload.sim.propulsion`), force and torque
drawn from the same non-negative thrusts; ``box``: the older model, force and torque
clipped per axis independently."""

DEFAULT_PROPULSION = "nozzles"

JERK_RISE_S = 0.5
"""ASSUMPTION (not published): the jerk bounds reach the nominal flight mode's acceleration
limits in this time [s]."""

JERK_LINEAR = FLIGHT_MODES["nominal"].accel / JERK_RISE_S
"""Linear jerk bound [m/s^3]: the nominal flight mode's acceleration in
:data:`JERK_RISE_S`."""

JERK_ANGULAR = FLIGHT_MODES["nominal"].alpha / JERK_RISE_S
"""Angular jerk bound [rad/s^3]: the nominal flight mode's angular acceleration in
:data:`JERK_RISE_S`."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs tens of microseconds per call)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


class _Fixed:
    """A setting given when its object is made and read-only afterwards (an array's values
    too): the bounds derived from it and its compiled step (:mod:`payload.sim.vehicle_c`,
    which copies what it needs when built) would otherwise go on with the old value while
    numpy's code took the new one."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.slot = name, "_" + name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        try:
            return obj.__dict__[self.slot]
        except KeyError:
            raise AttributeError(f"{type(obj).__name__}.{self.name} is not set yet") from None

    def __set__(self, obj: Any, value: Any) -> None:
        if self.slot in obj.__dict__:
            kind = type(obj).__name__
            raise VehicleError(
                f"{kind}.{self.name} is fixed when the {kind} is made (its bounds and its "
                f"compiled step derive from it): make a new {kind}"
            )
        if isinstance(value, np.ndarray):  # a read-only copy: the caller's stays theirs
            value = value.copy()
            value.setflags(write=False)
        obj.__dict__[self.slot] = value


def flight_mode(mode: str | FlightMode) -> FlightMode:
    """The :class:`FlightMode` named ``mode`` (or ``mode`` itself)."""
    if isinstance(mode, FlightMode):
        return mode
    try:
        return FLIGHT_MODES[mode]
    except KeyError:
        raise VehicleError(
            f"unknown flight mode {mode!r} (expected one of {', '.join(FLIGHT_MODES)})"
        ) from None


class MassProperties(NamedTuple):
    """Rigid mass properties of what the vehicle moves, in the Astrobee body frame.

    Attributes:
        mass: Total mass [kg].
        com: Centre of mass relative to Astrobee's centre of mass, shape (3,) [m].
        inertia: Inertia about that centre of mass, shape (3, 3) [kg m^2].
    """

    mass: float
    com: np.ndarray
    inertia: np.ndarray


class Wrench(NamedTuple):
    """A body-frame wrench applied at Astrobee's centre of mass.

    Attributes:
        force: Shape (3,) [N].
        torque: Shape (3,) [N m].
    """

    force: np.ndarray
    torque: np.ndarray


def min_time_to_speed(speed: float, accel: float, jerk: float) -> float:
    """Shortest time from rest to ``speed`` under acceleration and jerk bounds [s].

    Closed form: ``v/a + a/j`` when the acceleration bound is reached (``v >= a^2/j``),
    else ``2 sqrt(v/j)``.
    """
    if speed < 0 or accel <= 0 or jerk <= 0:
        raise VehicleError("min_time_to_speed: speed >= 0, accel > 0 and jerk > 0 required")
    if speed >= accel * accel / jerk:
        return speed / accel + accel / jerk
    return 2.0 * math.sqrt(speed / jerk)


class JerkLimitedProfile:
    """Per-axis velocity reference that moves toward a target with bounded a and j.

    Args:
        accel: Acceleration bound per axis, shape (n,).
        jerk: Jerk bound per axis, shape (n,).
    """

    accel = _Fixed()
    """Acceleration bound per axis (n,), fixed when the profile is made."""
    jerk = _Fixed()
    """Jerk bound per axis (n,), fixed when the profile is made."""

    def __init__(self, accel: np.ndarray, jerk: np.ndarray) -> None:
        accel, jerk = np.array(accel, dtype=float), np.array(jerk, dtype=float)
        if accel.shape != jerk.shape or np.any(accel <= 0) or np.any(jerk <= 0):
            raise VehicleError("JerkLimitedProfile: positive accel and jerk of equal shape needed")
        self.accel, self.jerk = accel, jerk
        self.velocity = np.zeros_like(self.accel)
        self.acceleration = np.zeros_like(self.accel)

    def reset(self, velocity: np.ndarray | None = None) -> None:
        """Restart from ``velocity`` (default zero) with zero acceleration."""
        self.velocity = np.zeros_like(self.accel) if velocity is None else np.array(velocity, float)
        self.acceleration = np.zeros_like(self.accel)

    def step(self, target: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance by ``dt`` [s] toward ``target`` (n,); returns (velocity, acceleration).

        Each step picks the acceleration ``x`` (within one jerk step of the current one and
        within the acceleration bound) from which ramping down at the jerk bound lands
        exactly on the target: ``x|x|/(2j) + (a + x) dt/2 = |e|`` in the direction of the
        velocity error ``e``. Far from the target this saturates at the bounds (the
        closed-form minimum-time profile); near it, it lands without overshoot.
        """
        target = np.broadcast_to(np.asarray(target, float), self.velocity.shape)
        # per axis on Python floats: the same IEEE operations, in the same order, as the
        # array form (x = up if const <= 0 else down, clipped to the jerk step and the
        # acceleration bound), without the overhead of two dozen numpy calls at 50 Hz
        lin = 0.5 * dt
        vel, acc = [], []
        for tg, v, a0, j, a_max in zip(
            target.tolist(),
            self.velocity.tolist(),
            self.acceleration.tolist(),
            self.jerk.tolist(),
            self.accel.tolist(),
        ):
            e = tg - v
            s = 1.0 if e >= 0.0 else -1.0
            a = s * a0  # current acceleration toward the target
            dist = abs(e)
            quad = 1.0 / (2.0 * j)
            const = a * lin - dist
            if const <= 0.0:
                x = (-lin + math.sqrt(lin * lin - 4.0 * quad * min(const, 0.0))) / (2.0 * quad)
            else:
                x = (lin - math.sqrt(lin * lin + 4.0 * quad * max(const, 0.0))) / (2.0 * quad)
            x = min(max(x, a - j * dt), a + j * dt)
            x = min(max(x, -a_max), a_max)
            v_new = v + s * 0.5 * (a + x) * dt
            a_new = s * x
            arrived = abs(tg - v_new) <= 1e-12 + 1e-9 * abs(tg) and abs(a_new) <= j * dt
            vel.append(tg if arrived else v_new)
            acc.append(0.0 if arrived else a_new)
        self.velocity = np.array(vel)
        self.acceleration = np.array(acc)
        return self.velocity.copy(), self.acceleration.copy()


class VehicleController:
    """Bounded-wrench body-twist tracking for Astrobee.

    Runs at the control rate (50 Hz); the wrench it returns is held over the physics steps
    of one control period.

    Bounds, per body axis i:

    * force: ``|F_i| <= F_bound_i = min(F_max_i, share * tau_max_j / |(c x e_i)_j|)`` over
      j, i.e. no larger than what the torque bound can balance (with ``torque_share`` of
      it) of the moment ``c x F`` the force makes about the carried centre of mass ``c``;
    * torque: ``|tau_i| <= tau_max_i``;
    * reference acceleration: ``a_i <= min(a_mode, reference_share * F_bound_i / m)``,
      leaving the rest of the force for velocity feedback;
    * reference angular acceleration: ``alpha_i <= min(alpha_mode, share * tau_max_i / I_ii)``;
    * reference jerk: ``jerk_linear``, ``jerk_angular``;
    * commanded twist: speed and rate of the mode, and a turn rate whose centripetal
      acceleration ``omega x v`` stays within ``reference_share`` of the acceleration bound.

    Args:
        plant: Mass properties of what the wrench moves (vehicle + payload [+ CTB]).
        mode: Flight mode name or object (default ``nominal``).
        jerk_linear: Linear jerk bound [m/s^3].
        jerk_angular: Angular jerk bound [rad/s^3].
        gain_linear: Velocity feedback gain [1/s].
        gain_angular: Angular-rate feedback gain [1/s].
        torque_share: Fraction of the torque bound the cargo moment of the force may use,
            in (0, 1]; the rest stays for attitude-rate feedback.
        reference_share: Fraction of the force bound the reference acceleration may use,
            in (0, 1].
        propulsion: ``nozzles`` (default) or ``box``. With nozzles the bounds come from
            the reachable wrench polytope instead of the per-axis figures: the force bound
            along body axis i is ``torque_share`` of the largest ``f`` for which the wrench
            ``f (e_i, c x e_i)`` (the force and the torque that balances its moment about
            the carried centre of mass) is reachable in both directions, the torque bound
            the largest pure torque per axis; the wrench is not clipped per axis but
            allocated to the nozzles (:attr:`allocation`), scaled down along its own
            direction when it lies outside the polytope.

    The settings (the arguments, and the bounds and profile derived from them) are fixed
    when the controller is made: setting one afterwards raises :class:`VehicleError`, and
    their arrays are read-only (make a new controller for other settings). What moves is
    the state: the profile's velocity and acceleration, and :attr:`allocation`.
    """

    mode = _Fixed()
    propulsion = _Fixed()
    nozzles = _Fixed()
    plant = _Fixed()
    gain_linear = _Fixed()
    gain_angular = _Fixed()
    reference_share = _Fixed()
    torque_max = _Fixed()
    force_max = _Fixed()
    accel_max = _Fixed()
    alpha_max = _Fixed()
    jerk = _Fixed()
    profile = _Fixed()

    def __init__(
        self,
        plant: MassProperties,
        mode: str | FlightMode = DEFAULT_FLIGHT_MODE,
        *,
        jerk_linear: float = JERK_LINEAR,
        jerk_angular: float = JERK_ANGULAR,
        gain_linear: float = 1.0,
        gain_angular: float = 2.0,
        torque_share: float = 0.8,
        reference_share: float = 0.8,
        propulsion: str = DEFAULT_PROPULSION,
    ) -> None:
        self.mode = flight_mode(mode)
        if propulsion not in PROPULSION_MODELS:
            raise VehicleError(
                f"unknown propulsion model {propulsion!r} (expected one of "
                f"{', '.join(PROPULSION_MODELS)})"
            )
        self.propulsion = propulsion
        self.nozzles = (
            shared_propulsion(tuple(self.mode.force)) if propulsion == "nozzles" else None
        )
        self.allocation: Allocation | None = None
        inertia, com = read_only(plant.inertia), read_only(plant.com)  # the controller's own
        if not (math.isfinite(plant.mass) and plant.mass > 0):
            raise VehicleError(f"VehicleController: plant mass must be positive, got {plant.mass}")
        if com.shape != (3,) or inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)):
            raise VehicleError("VehicleController: plant com must be (3,) and inertia (3, 3)")
        if np.any(np.diag(inertia) <= 0):
            raise VehicleError("VehicleController: plant inertia must be positive definite")
        for name, value in (
            ("torque_share", torque_share),
            ("reference_share", reference_share),
        ):
            if not 0.0 < value <= 1.0:
                raise VehicleError(f"VehicleController.{name}: must be in (0, 1], got {value}")
        for name, value in (
            ("jerk_linear", jerk_linear),
            ("jerk_angular", jerk_angular),
            ("gain_linear", gain_linear),
            ("gain_angular", gain_angular),
        ):
            if not (math.isfinite(value) and value > 0):
                raise VehicleError(f"VehicleController.{name}: must be positive, got {value}")
        self.plant = MassProperties(float(plant.mass), com, inertia)
        if self.nozzles is None:
            self.torque_max = np.array(self.mode.torque)
        else:
            self.torque_max = self.nozzles.pure_torque_max()
        self.gain_linear = gain_linear
        self.gain_angular = gain_angular
        self.reference_share = reference_share
        if self.nozzles is None:
            self.force_max = self._force_bounds(torque_share)
        else:
            self.force_max = self._polytope_force_bounds(torque_share)
        self.accel_max = np.minimum(
            self.mode.accel, reference_share * self.force_max / self.plant.mass
        )
        self.alpha_max = np.minimum(
            self.mode.alpha, torque_share * self.torque_max / np.diag(inertia)
        )
        self.jerk = np.concatenate([np.full(3, jerk_linear), np.full(3, jerk_angular)])
        self.profile = JerkLimitedProfile(
            np.concatenate([self.accel_max, self.alpha_max]), self.jerk
        )

    def _force_bounds(self, share: float) -> np.ndarray:
        bounds = np.array(self.mode.force, dtype=float)
        c = self.plant.com
        for i in range(3):
            e = np.zeros(3)
            e[i] = 1.0
            moment = np.abs(np.cross(c, e))  # moment about the carried CoM per newton along i
            for j in range(3):
                if moment[j] > 1e-12:
                    bounds[i] = min(bounds[i], share * self.torque_max[j] / moment[j])
        return bounds

    def _polytope_force_bounds(self, share: float) -> np.ndarray:
        assert self.nozzles is not None
        c = self.plant.com
        bounds = np.empty(3)
        for i in range(3):
            e = np.zeros(3)
            e[i] = 1.0
            w = np.concatenate([e, np.cross(c, e)])
            bounds[i] = share * min(self.nozzles.max_along(w), self.nozzles.max_along(-w))
        return bounds

    @property
    def limits(self) -> dict[str, list[float]]:
        """The bounds in force: force, torque, accelerations, jerks, speed, rate."""
        return {
            "force": self.force_max.tolist(),
            "torque": self.torque_max.tolist(),
            "accel": self.accel_max.tolist(),
            "alpha": self.alpha_max.tolist(),
            "jerk": self.jerk.tolist(),
            "speed": [self.mode.speed],
            "omega": [self.mode.omega],
            "propulsion": [self.propulsion],
        }

    def reset(self, linear: np.ndarray | None = None, angular: np.ndarray | None = None) -> None:
        """Restart the reference from the given body twist (default rest)."""
        lin = np.zeros(3) if linear is None else np.asarray(linear, float)
        ang = np.zeros(3) if angular is None else np.asarray(angular, float)
        self.profile.reset(np.concatenate([lin, ang]))

    def clamp(self, twist: VehicleTwist) -> np.ndarray:
        """The commanded twist within the bounds, shape (6,) (linear, angular).

        Speed and rate are scaled to the mode's; then the rate is scaled down until the
        centripetal acceleration ``omega x v`` of the commanded motion fits within
        ``reference_share`` of the acceleration bound on every axis.
        """
        lin, ang = np.asarray(twist.linear, float), np.asarray(twist.angular, float)
        s, w = float(norm(lin)), float(norm(ang))
        if s > self.mode.speed:
            lin = lin * (self.mode.speed / s)
        if w > self.mode.omega:
            ang = ang * (self.mode.omega / w)
        centripetal = np.abs(_cross(ang, lin))
        budget = self.reference_share * self.accel_max
        over = centripetal > budget
        if np.any(over):
            ang = ang * float(np.min(budget[over] / centripetal[over]))
        return np.concatenate([lin, ang])

    @cached_property
    def _kernel(self) -> Any:
        """The nozzle controller's step compiled (:mod:`payload.sim.vehicle_c`: numpy's
        bits, checked when built), or None to run :meth:`_update_numpy`."""
        if self.nozzles is None:
            return None
        from payload.sim.vehicle_c import compiled_control

        return compiled_control(self)

    def update(
        self, command: VehicleTwist, linear: np.ndarray, angular: np.ndarray, dt: float
    ) -> Wrench:
        """One control step (:meth:`_update_numpy`, compiled when it can be: :attr:`_kernel`).

        Args:
            command: Requested body twist.
            linear: Measured body-frame linear velocity of Astrobee's centre, (3,) [m/s].
            angular: Measured body-frame angular velocity, (3,) [rad/s].
            dt: Control period [s].
        """
        kernel = self._kernel
        if kernel is not None:
            return self._update_kernel(kernel, command, linear, angular, dt)
        return self._update_numpy(command, linear, angular, dt)

    def _update_kernel(
        self, kernel: Any, command: VehicleTwist, linear: np.ndarray, angular: np.ndarray, dt: float
    ) -> Wrench:
        """:meth:`_update_numpy` through the compiled step ``kernel``
        (:class:`~payload.sim.vehicle_c.CompiledControl`)."""
        code, *out = kernel.step(command, linear, angular, dt)
        return self._finish_kernel(code, out)

    def _finish_kernel(self, code: int, out: list) -> Wrench:
        """The allocation and wrench of a kernel's control step that gave ``code`` and
        ``out`` (:meth:`~payload.sim.vehicle_c.CompiledControl.step`'s result)."""
        assert self.nozzles is not None
        if code == 0:
            self.allocation = Allocation(*out)
        elif code == 1:
            self.allocation = Allocation.zero()
        elif code == 4:
            self.nozzles.allocate(out[0][:3], out[0][3:])  # raises: a non-finite wrench
            raise VehicleError("the control step found a non-finite wrench")  # pragma: no cover
        else:
            self.allocation = self.nozzles._finish(*out)
        return Wrench(self.allocation.force.copy(), self.allocation.torque.copy())

    def _update_numpy(
        self, command: VehicleTwist, linear: np.ndarray, angular: np.ndarray, dt: float
    ) -> Wrench:
        """One control step in numpy (the arguments of :meth:`update`).

        Returns:
            The body-frame wrench to hold over the next period: within the per-axis
            bounds (box), or what the allocated nozzle thrusts make (nozzles; the thrusts
            are in :attr:`allocation`).
        """
        target = self.clamp(command)
        ref, acc = self.profile.step(target, dt)
        v, w = np.asarray(linear, float), np.asarray(angular, float)
        m, c, inertia = self.plant
        force = m * (acc[:3] + self.gain_linear * (ref[:3] - v) + _cross(w, v))
        if self.nozzles is None:
            force = np.clip(force, -self.force_max, self.force_max)
        alpha = acc[3:] + self.gain_angular * (ref[3:] - w)
        torque = inertia @ alpha + _cross(w, inertia @ w) + _cross(c, force)
        if self.nozzles is None:
            torque = np.clip(torque, -self.torque_max, self.torque_max)
            return Wrench(force, torque)
        self.allocation = self.nozzles.allocate(force, torque)
        return Wrench(self.allocation.force.copy(), self.allocation.torque.copy())


__all__ = [
    "DEFAULT_FLIGHT_MODE",
    "DEFAULT_PROPULSION",
    "FLIGHT_MODES",
    "JERK_ANGULAR",
    "JERK_LINEAR",
    "JERK_RISE_S",
    "PROPULSION_MODELS",
    "FlightMode",
    "JerkLimitedProfile",
    "MassProperties",
    "VehicleController",
    "VehicleError",
    "Wrench",
    "flight_mode",
    "min_time_to_speed",
]
