"""``payload hw identify``: fit each servo's armature, friction and torque constant from its
responses, through the driver (dynamixel_sdk on a serial device or the emulator's pty).

Per servo, the others holding still: (1) saturated steps across the joint's range with
Goal Current raised to the servo's Current Limit, so that the supply voltage, not the
current cap, bounds the current at speed; (2) a chirp (0.5 to 6 Hz) and (3) small steps at
the design's Goal Current, after goal ramps across the range at steady speeds (friction at
several velocities). Present current, velocity and position are read after every
goal write, as fast as the bus answers, with the servo's Realtime Tick (its own
millisecond clock) as their time stamp.

Two linear least-squares fits (docs/servo.md):

- dynamics, integrated over windows of about 40 ms so nothing is differentiated:
  ``(J / kt) dw + (b / kt) dtheta + (c / kt) int sign(w) dt = int i dt`` (windows where the
  shaft moves one way throughout, without a pause of the host; each weighted by its
  current impulse), giving ``b / kt``, ``c / kt``; then ``J / kt`` alone, unweighted,
  friction fixed (the saturated steps' large velocity changes decide it);
- the voltage bound, on samples of the saturated steps where the current stays under the
  cap while the position error asks for more: ``sign(w) V = R i + kt w``, giving ``R`` and
  ``kt`` (``V`` from Present Input Voltage).

``kt`` then scales the first fit. The residual of each fit is reported relative to the RMS
of its right-hand side. The suggested ``[servo]`` values are the median over the
identified servos (the armature is the fitted inertia less the design's load inertia of
the joint); they are written into the design only with ``--write``.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from dynamixel_sdk import COMM_SUCCESS

from firmware_interface.control_table import ADDR, VELOCITY_UNIT_RPM, VOLTAGE_UNIT_V
from firmware_interface.driver import (
    FEEDBACK_ADDR,
    FEEDBACK_LEN,
    DynamixelDriver,
    bring_up_notice,
    failed_start,
)
from firmware_interface.errors import CommError
from firmware_interface.servo_map import ServoSpec
from payload.design.edit import set_in_text
from payload.design.servo import CURRENT_UNIT_A, KPP_DIV, TICKS_PER_RAD, kind_of
from payload.design.tree import build_tree, load_inertia
from payload.errors import PayloadError
from payload.safeio import replace_file

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

WINDOW_S = 0.04
"""Integration window of the dynamics fit [s]."""
MAX_GAP_S = 0.015
"""Windows with a longer pause between samples are left out (the trapezoid would guess
what happened in it; a loaded host pauses) [s]."""
CURRENT_FLOOR_A = 0.01
"""Current added to a window's mean in its weight (keeps slow windows finite) [A]."""
MIN_SPEED = 0.3
"""Windows and samples slower than this are left out (static friction is ambiguous) [rad/s]."""
MARGIN_RAD = 0.25
"""The saturated steps stop this far inside the joint's limits [rad of the servo shaft]."""
RAMP_SPEEDS = (0.7, 1.5, 3.0)
"""Goal ramps across the range at these speeds [rad/s], each way."""
SUGGESTED = ("kt", "resistance", "armature", "coulomb", "viscous")
_RPM_TO_RAD_S = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
_TICK_ADDR = ADDR["realtime_tick"]
_STAMPED = struct.Struct("<HBBhhii")  # Realtime Tick ... Present Position (120-135)
assert _TICK_ADDR + _STAMPED.size == FEEDBACK_ADDR + FEEDBACK_LEN
_TICK_WRAP = 32768  # Realtime Tick range [ms]


@dataclass
class Record:
    """Samples of one servo: time [s], shaft position [rad], speed [rad/s], current [A],
    goal [ticks], the cap in force [A], whether a saturated step was running, and the speed
    of the goal ramp running [rad/s] (0 outside the ramps)."""

    t: list[float]
    pos: list[float]
    vel: list[float]
    cur: list[float]
    goal: list[float]
    cap: list[float]
    sat: list[bool]
    ramp: list[float]


def _feedback(drv: DynamixelDriver, dxl_id: int) -> tuple[int, float, float, float]:
    """(Realtime Tick [ms, modulo 32768], current [A], speed [rad/s], position [ticks]) of
    one servo, in one read: the servo's own clock stamps the sample."""
    for _ in range(drv.retries + 1):
        data, result, _ = drv.packet.readTxRx(drv.port, dxl_id, _TICK_ADDR, _STAMPED.size)
        if result == COMM_SUCCESS:
            tick, _, _, _, cur, vel, pos = _STAMPED.unpack(bytes(data))
            return tick, cur * CURRENT_UNIT_A, vel * _RPM_TO_RAD_S, float(pos)
    raise CommError(f"servo {dxl_id}: reading feedback: {drv.packet.getTxRxResult(result)}")


def _run(drv: DynamixelDriver, dxl_id: int, rec: Record, goals, seconds: float, cap: float,
         sat: bool, ramp: float = 0.0) -> None:  # fmt: skip
    """Drive ``goals(t)`` [ticks] for ``seconds`` and append the samples to ``rec``."""
    t0 = time.monotonic()
    last = None
    while (t := time.monotonic() - t0) < seconds:
        goal = round(goals(t))
        if goal != last:
            drv._write(dxl_id, "goal_position", goal)
            last = goal
        tick, cur, vel, pos = _feedback(drv, dxl_id)
        stamp = tick * 1e-3
        if rec.t:  # unwrap the servo's millisecond clock
            stamp += round((rec.t[-1] - stamp) * 1e3 / _TICK_WRAP) * _TICK_WRAP * 1e-3
        rec.t.append(stamp)
        rec.pos.append(pos / TICKS_PER_RAD)
        rec.vel.append(vel)
        rec.cur.append(cur)
        rec.goal.append(goal)
        rec.cap.append(cap)
        rec.sat.append(sat)
        rec.ramp.append(ramp)


def excite(drv: DynamixelDriver, spec: ServoSpec) -> tuple[Record, float]:
    """Run the three experiments on one servo; returns its record and supply voltage [V]."""
    i = spec.id
    lo, hi = sorted((spec.to_ticks(spec.lower), spec.to_ticks(spec.upper)))
    margin = MARGIN_RAD * TICKS_PER_RAD
    a, b = lo + margin, hi - margin
    centre = 0.5 * (lo + hi)
    rec = Record([], [], [], [], [], [], [], [])
    cap_design = drv.map.current_limit_ma
    limit = drv._read_reg(i, ADDR["current_limit"], 2)
    volts = drv._read_reg(i, ADDR["present_input_voltage"], 2) * VOLTAGE_UNIT_V
    start = _feedback(drv, i)[3]
    _run(drv, i, rec, lambda t: start + (centre - start) * min(1.0, t / 0.5), 0.8,
         cap_design * CURRENT_UNIT_A, False)  # fmt: skip
    drv._write(i, "goal_current", limit)
    for target in (b, a, b, a):
        _run(drv, i, rec, lambda t, g=target: g, 0.7, limit * CURRENT_UNIT_A, True)
    _run(drv, i, rec, lambda t: centre, 0.6, limit * CURRENT_UNIT_A, False)
    drv._write(i, "goal_current", cap_design)
    for speed in RAMP_SPEEDS:  # steady speeds: friction at several velocities
        span = (b - a) / (speed * TICKS_PER_RAD)
        for g0, g1 in ((a, b), (b, a)):
            ramp = math.copysign(speed, g1 - g0)
            _run(drv, i, rec, lambda t, g0=g0, g1=g1, s=span: g0 + (g1 - g0) * min(1.0, t / s),
                 span, cap_design * CURRENT_UNIT_A, False, ramp)  # fmt: skip
    amp = min(0.15 * TICKS_PER_RAD, 0.25 * (hi - lo))
    f0, f1, dur = 0.5, 6.0, 4.0

    def chirp(t: float) -> float:
        return centre + amp * math.sin(2 * math.pi * (f0 * t + (f1 - f0) * t * t / (2 * dur)))

    _run(drv, i, rec, chirp, dur, cap_design * CURRENT_UNIT_A, False)
    for target in (centre + amp, centre - amp, centre):
        _run(drv, i, rec, lambda t, g=target: g, 0.5, cap_design * CURRENT_UNIT_A, False)
    return rec, volts


def _trapezoid(y: np.ndarray, t: np.ndarray) -> float:
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(t)))


def fit(rec: Record, volts: float, p_gain: float) -> dict[str, Any]:
    """The two least-squares fits of the module docstring on one servo's record."""
    t, th, w, cur = (np.asarray(x, dtype=float) for x in (rec.t, rec.pos, rec.vel, rec.cur))
    rows, rhs = [], []
    k = 0
    while k < len(t) - 1:
        m = int(np.searchsorted(t, t[k] + WINDOW_S))
        m = min(m, len(t) - 1)
        seg = slice(k, m + 1)
        ws, ts = w[seg], t[seg]
        steady = m > k + 1 and np.diff(ts).max() <= MAX_GAP_S  # no stall of the host inside
        if steady and np.all(np.abs(ws) > MIN_SPEED) and abs(np.sign(ws).sum()) == len(ws):
            rows.append([w[m] - w[k], th[m] - th[k], _trapezoid(np.sign(ws), ts)])
            rhs.append(_trapezoid(cur[seg], ts))
        k = m
    a_dyn, b_dyn = np.array(rows), np.array(rhs)
    if len(b_dyn) < 10:
        raise ValueError(f"only {len(b_dyn)} usable windows (is the host pausing?)")
    # relative errors: each window's equation divided by its current impulse (plus a floor),
    # so that the slow windows where friction shows weigh as much as the saturated ones
    scale = 1.0 / (np.abs(b_dyn) + CURRENT_FLOOR_A * WINDOW_S)
    x_dyn, *_ = np.linalg.lstsq(a_dyn * scale[:, None], b_dyn * scale, rcond=None)
    _, b_kt, c_kt = (float(v) for v in x_dyn)
    # the inertia again, unweighted, friction fixed: the large velocity changes decide it
    rest = b_dyn - a_dyn[:, 1] * b_kt - a_dyn[:, 2] * c_kt
    j_kt = float(a_dyn[:, 0] @ rest / (a_dyn[:, 0] @ a_dyn[:, 0]))
    x_dyn = np.array([j_kt, b_kt, c_kt])
    res_dyn = np.sqrt(np.mean((a_dyn @ x_dyn - b_dyn) ** 2)) / np.sqrt(np.mean(b_dyn**2))
    # the voltage bound: under the cap although the error asks for more than the cap
    err = np.abs(np.asarray(rec.goal) - th * TICKS_PER_RAD)
    demand = p_gain / KPP_DIV * err * CURRENT_UNIT_A
    cap = np.asarray(rec.cap)
    use = (np.asarray(rec.sat) & (np.abs(cur) < 0.9 * cap) & (demand > 2.0 * cap)
           & (np.abs(w) > MIN_SPEED))  # fmt: skip
    a_v = np.column_stack([cur[use], w[use]])
    b_v = np.sign(w[use]) * volts
    if len(b_v) < 5:
        raise ValueError("too few voltage-bound samples (the saturated steps never saturated)")
    (r_fit, kt), *_ = np.linalg.lstsq(a_v, b_v, rcond=None)
    res_v = np.sqrt(np.mean((a_v @ np.array([r_fit, kt]) - b_v) ** 2)) / volts
    return {
        "inertia": float(j_kt * kt),
        "viscous": float(b_kt * kt),
        "coulomb": float(c_kt * kt),
        "kt": float(kt),
        "resistance": float(r_fit),
        "residual": {"dynamics": float(res_dyn), "voltage": float(res_v)},
        "windows": len(b_dyn),
        "voltage_samples": len(b_v),
    }


class EmulatedBusError(PayloadError):
    """An identification meant for real servos found the emulator at the far end."""


def identify(
    drv: DynamixelDriver,
    joints: list[str] | None = None,
    say: Callable[[str], None] | None = None,
    refuse_emulated: str | None = None,
) -> dict[str, Any]:
    """Bring up, excite and fit each named servo (default: all); the report as plain data.

    ``say``: told each stage as it starts (the bring-up, then each servo's excitation, which
    moves its joint across its range: 15 to 20 s a servo), for a terminal's progress.
    ``refuse_emulated``: a bus that answers as the emulator (its servos' Model Information)
    raises :class:`EmulatedBusError` with this text after the bring-up, before any servo
    moves (an identification to be written into a design must be of real servos)."""
    specs = [s for s in drv.map.servos if joints is None or s.joint in joints]
    design = drv.design
    tree = build_tree(design)
    if say is not None:
        say(bring_up_notice(drv.device))
    with failed_start(drv.device):
        drv.bring_up()
    if refuse_emulated is not None and drv.emulated:
        raise EmulatedBusError(f"{drv.device} answers as the emulator: {refuse_emulated}")
    for i in drv.ids:
        # one servo is talked to at a time: the others would trip their Bus Watchdog (and
        # hold, as they do anyway); without it, a pause of the host cannot stop the test
        drv._write(i, "bus_watchdog", 0)
    out = []
    for n, spec in enumerate(specs, 1):
        kind = kind_of(spec.joint)
        if say is not None:
            say(f"servo {n} of {len(specs)}: {spec.joint} (ID {spec.id}), steps and a chirp "
                "across its range")  # fmt: skip
        rec, volts = excite(drv, spec)
        p_gain = drv._read_reg(spec.id, ADDR["position_p_gain"], 2)
        got = fit(rec, volts, p_gain)
        r = 1.0 if kind in ("finger", "abduction") else spec.units_per_tick * TICKS_PER_RAD
        load = load_inertia(tree, kind) * r**2
        got["armature"] = got["inertia"] - load
        out.append({"joint": spec.joint, "id": spec.id, "kind": kind, "load_inertia": load,
                    "supply_voltage": volts, "samples": len(rec.t), "fit": got})  # fmt: skip
    s = design.servo
    current = {k: getattr(s, k) for k in SUGGESTED}
    suggested = {k: float(np.median([o["fit"][k] for o in out])) for k in SUGGESTED}
    return {"servos": out, "design": current, "suggested": suggested}


def write_servo_values(design_path: str | Path, values: dict[str, float]) -> None:
    """Set ``key = number`` in the design's ``[servo]`` table, to six significant digits
    (every other byte kept, comments included: :func:`payload.design.edit.set_in_text`),
    replacing the file whole (:func:`payload.safeio.replace_file`).

    Raises:
        ValueError: A key is not in the table (nothing written).
    """
    p = Path(design_path)
    text = p.read_text(encoding="utf-8")
    servo = tomllib.loads(text).get("servo", {})
    missing = sorted(set(values) - set(servo))
    if missing:
        raise ValueError(f"{p}: [servo] has no {', '.join(missing)}")
    for key, value in values.items():
        text = set_in_text(text, f"servo.{key}", float(f"{value:.6g}"))
    replace_file(p, text)


__all__ = ["Record", "excite", "fit", "identify", "write_servo_values"]
