"""One servo model: the XC330's physics and firmware law, mapped to every consumer.

The design's ``[servo]`` table holds the output-side physics (``kt``, ``resistance``,
``armature``, ``coulomb``, ``viscous``, ``supply_voltage``) and the controller the
hardware runs (Operating Mode 5, Position P/I/D per joint kind, the Goal Current cap
``current_limit``). In mode 5 the firmware's position PID outputs a current command
(e-Manual: ``KPP = P / 128``, ``KPD = D / 16``, constants that "include the sampling
time"), clamped by Goal Current; an inner loop drives the motor to that current while
the supply voltage allows it:

    i = clamp(KPP e + KPD (e_k - e_(k-1)), -I_goal, I_goal) x CURRENT_UNIT_A
    |R i + kt w| <= V                                    (the voltage headroom)
    (armature + J_load) dw/dt = kt i - viscous w - coulomb sign(w)

with ``e`` the position error in encoder ticks and the difference taken per
``control_period`` (the sampling time is not published: ASSUMPTION). ``kt`` is the
output torque per ampere with the gear losses in it (datasheet stall torque / stall
current; BAM's identified ``kt`` is output-side too), so no gear efficiency multiplies
it, and ``armature`` is already the rotor inertia seen at the output (BAM identifies it
there; MuJoCo Playground's 1.7e-8 x 288^2 = 1.49e-3 is the same quantity), so no
``gear_ratio^2`` multiplies it either.

MuJoCo's position actuator (force ``kp (ctrl - q) - kv qdot`` clamped to
``forcerange``) then takes, per radian of output:

    kp = kt CURRENT_UNIT_A (P / 128) TICKS_PER_RAD          [N m/rad]
    kv = kt CURRENT_UNIT_A (D / 16) control_period TICKS_PER_RAD   [N m s/rad]
    damping = viscous; armature = armature; frictionloss = coulomb
    forcerange = kt current_limit

The back-EMF ``kt^2 / R`` is not a damping here: the current loop cancels it while it
has voltage headroom, and once it has not the back-EMF caps the speed instead (the
no-load speed ``V / kt``); the emulator models that cap, MuJoCo's actuator cannot (the
fingers stay far below it). The rail and the stage drive a rack through a pinion of
radius ``r`` (servo on the pinion): force = torque / r and x = r theta, so ``kp``,
``kv``, ``damping`` and ``armature`` divide by ``r^2``, ``frictionloss`` and the force
cap by ``r``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from payload.design.params import Design

TICKS_PER_REV = 4096
"""Encoder ticks per output turn (XC330 e-Manual)."""
TICKS_PER_RAD = TICKS_PER_REV / (2.0 * math.pi)
CURRENT_UNIT_A = 0.001
"""Goal Current and Present Current unit on the XC330 [A]; the PID's output unit."""
KPP_DIV, KPI_DIV, KPD_DIV = 128.0, 65536.0, 16.0
"""e-Manual: internal gain = control-table gain / divisor (Position P, I, D)."""

JOINT_KINDS = ("finger", "abduction", "rail", "stage")
"""Joint kinds with their own gains: finger flexion (MCP flexion, PIP, DIP), MCP
abduction, the rail pinion, the stage pinion."""


def kind_of(joint: str) -> str:
    """The joint kind of an actuated joint name (``A_mcp_abd`` -> ``abduction``)."""
    if joint in ("rail", "stage"):
        return joint
    return "abduction" if joint.endswith("mcp_abd") else "finger"


@dataclass(frozen=True)
class JointServo:
    """One joint kind's servo in joint units (rad or m).

    Attributes:
        kind: Joint kind (:data:`JOINT_KINDS`).
        gains: Position (P, I, D) control-table values.
        scale: Joint units per output radian (1 for a hinge, the pinion radius [m]).
        kp: Stiffness [N m/rad or N/m].
        kv: Velocity feedback inside the force clamp [N m s/rad or N s/m].
        damping: Passive viscous damping [N m s/rad or N s/m].
        armature: Reflected rotor inertia [kg m^2 or kg].
        frictionloss: Coulomb friction [N m or N].
        torque_cap: Torque (force) at the Goal Current cap [N m or N].
    """

    kind: str
    gains: tuple[int, int, int]
    scale: float
    kp: float
    kv: float
    damping: float
    armature: float
    frictionloss: float
    torque_cap: float


def gains_of(design: Design, kind: str) -> tuple[int, int, int]:
    """Position (P, I, D) control-table gains of a joint kind."""
    p, i, d = getattr(design.servo.gains, kind)
    return int(p), int(i), int(d)


def scale_of(design: Design, kind: str) -> float:
    """Joint units per output radian: 1 for hinges, the pinion radius for rail and stage."""
    if kind == "rail":
        return design.rail.drive_radius
    if kind == "stage":
        return design.stage.drive_radius
    return 1.0


def shaft_gains(kt: float, p: float, d: float, control_period: float) -> tuple[float, float]:
    """Output-shaft ``(kp [N m/rad], kv [N m s/rad])`` of firmware gains P and D."""
    amps_per_tick = CURRENT_UNIT_A / KPP_DIV * p
    kp = kt * amps_per_tick * TICKS_PER_RAD
    kv = kt * CURRENT_UNIT_A * d / KPD_DIV * control_period * TICKS_PER_RAD
    return kp, kv


def dead_band_ticks(design: Design, kind: str) -> float:
    """Static friction dead band of a servo of joint kind ``kind`` [encoder ticks].

    With no I gain, a shaft at rest stays put while the proportional current's torque
    ``kt (P / 128) e`` is below the Coulomb friction: it can stop anywhere within
    ``coulomb / (kt CURRENT_UNIT_A P / 128)`` ticks of its goal (8.5 ticks at P 600,
    11.3 at P 450 with the packaged design). Infinite for P = 0.
    """
    s = design.servo
    p = gains_of(design, kind)[0]
    if p <= 0:
        return math.inf
    return s.coulomb / (s.kt * CURRENT_UNIT_A * p / KPP_DIV)


def joint_servo(design: Design, kind: str) -> JointServo:
    """The servo of joint kind ``kind`` as MuJoCo takes it (module docstring)."""
    if kind not in JOINT_KINDS:
        raise ValueError(f"unknown joint kind {kind!r} (expected one of {JOINT_KINDS})")
    s = design.servo
    gains = gains_of(design, kind)
    kp, kv = shaft_gains(s.kt, gains[0], gains[2], s.control_period)
    r = scale_of(design, kind)
    return JointServo(
        kind=kind,
        gains=gains,
        scale=r,
        kp=kp / r**2,
        kv=kv / r**2,
        damping=s.viscous / r**2,
        armature=s.armature / r**2,
        frictionloss=s.coulomb / r,
        torque_cap=s.kt * s.current_limit / r,
    )


def no_load_speed(design: Design) -> float:
    """Output speed [rad/s] at which the supply voltage balances the back-EMF and the
    friction: ``(V - R c / kt) / (kt + R b / kt)`` (a check against the datasheet's)."""
    s = design.servo
    return (s.supply_voltage - s.resistance * s.coulomb / s.kt) / (
        s.kt + s.resistance * s.viscous / s.kt
    )


__all__ = [
    "CURRENT_UNIT_A",
    "JOINT_KINDS",
    "KPD_DIV",
    "KPI_DIV",
    "KPP_DIV",
    "TICKS_PER_RAD",
    "TICKS_PER_REV",
    "JointServo",
    "dead_band_ticks",
    "gains_of",
    "joint_servo",
    "kind_of",
    "no_load_speed",
    "scale_of",
    "shaft_gains",
]
