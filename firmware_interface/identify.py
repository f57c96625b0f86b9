"""``payload hw identify``: fit each servo's armature, friction and torque constant from its
responses, through the driver (dynamixel_sdk on a serial device or the emulator's pty).

Per servo, the others holding still: (1) saturated steps across the joint's range with
Goal Current raised to the servo's Current Limit, so that the supply voltage, not the
current cap, bounds the current at speed; (2) a chirp (0.5 to 6 Hz) and (3) small steps at
the design's Goal Current. Present current, velocity and position are read after every
goal write, as fast as the bus answers.

Two linear least-squares fits (docs/servo.md):

- dynamics, integrated over windows of about 40 ms so nothing is differentiated:
  ``(J / kt) dw + (b / kt) dtheta + (c / kt) int sign(w) dt = int i dt`` (windows where the
  shaft moves one way throughout), giving ``J / kt``, ``b / kt``, ``c / kt``;
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
import re
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from dynamixel_sdk import COMM_SUCCESS

from firmware_interface.control_table import ADDR, VELOCITY_UNIT_RPM, VOLTAGE_UNIT_V
from firmware_interface.driver import FEEDBACK_ADDR, FEEDBACK_LEN, DynamixelDriver
from firmware_interface.errors import CommError
from firmware_interface.servo_map import ServoSpec
from payload.design.servo import CURRENT_UNIT_A, KPP_DIV, TICKS_PER_RAD, kind_of, load_inertia
from payload.design.tree import build_tree

WINDOW_S = 0.04
"""Integration window of the dynamics fit [s]."""
MIN_SPEED = 0.3
"""Windows and samples slower than this are left out (static friction is ambiguous) [rad/s]."""
MARGIN_RAD = 0.25
"""The saturated steps stop this far inside the joint's limits [rad of the servo shaft]."""
SUGGESTED = ("kt", "resistance", "armature", "coulomb", "viscous")
_RPM_TO_RAD_S = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0


@dataclass
class Record:
    """Samples of one servo: time [s], shaft position [rad], speed [rad/s], current [A],
    goal [ticks], the cap in force [A], and whether a saturated step was running."""

    t: list[float]
    pos: list[float]
    vel: list[float]
    cur: list[float]
    goal: list[float]
    cap: list[float]
    sat: list[bool]


def _feedback(drv: DynamixelDriver, dxl_id: int) -> tuple[float, float, float]:
    """(current [A], speed [rad/s], position [ticks]) of one servo."""
    for _ in range(drv.retries + 1):
        data, result, _ = drv.packet.readTxRx(drv.port, dxl_id, FEEDBACK_ADDR, FEEDBACK_LEN)
        if result == COMM_SUCCESS:
            cur, vel, pos = struct.unpack("<hii", bytes(data))
            return cur * CURRENT_UNIT_A, vel * _RPM_TO_RAD_S, float(pos)
    raise CommError(f"servo {dxl_id}: reading feedback: {drv.packet.getTxRxResult(result)}")


def _run(drv: DynamixelDriver, dxl_id: int, rec: Record, goals, seconds: float, cap: float,
         sat: bool) -> None:  # fmt: skip
    """Drive ``goals(t)`` [ticks] for ``seconds`` and append the samples to ``rec``."""
    t0 = time.monotonic()
    last = None
    while (t := time.monotonic() - t0) < seconds:
        goal = round(goals(t))
        if goal != last:
            drv._write(dxl_id, "goal_position", goal)
            last = goal
        stamp = time.monotonic()
        cur, vel, pos = _feedback(drv, dxl_id)
        rec.t.append(stamp)
        rec.pos.append(pos / TICKS_PER_RAD)
        rec.vel.append(vel)
        rec.cur.append(cur)
        rec.goal.append(goal)
        rec.cap.append(cap)
        rec.sat.append(sat)


def excite(drv: DynamixelDriver, spec: ServoSpec) -> tuple[Record, float]:
    """Run the three experiments on one servo; returns its record and supply voltage [V]."""
    i = spec.id
    lo, hi = sorted((spec.to_ticks(spec.lower), spec.to_ticks(spec.upper)))
    margin = MARGIN_RAD * TICKS_PER_RAD
    a, b = lo + margin, hi - margin
    centre = 0.5 * (lo + hi)
    rec = Record([], [], [], [], [], [], [])
    cap_design = drv.map.current_limit_ma
    limit = drv._read_reg(i, ADDR["current_limit"], 2)
    volts = drv._read_reg(i, ADDR["present_input_voltage"], 2) * VOLTAGE_UNIT_V
    start = _feedback(drv, i)[2]
    _run(drv, i, rec, lambda t: start + (centre - start) * min(1.0, t / 0.5), 0.8,
         cap_design * CURRENT_UNIT_A, False)  # fmt: skip
    drv._write(i, "goal_current", limit)
    for target in (b, a, b, a):
        _run(drv, i, rec, lambda t, g=target: g, 0.7, limit * CURRENT_UNIT_A, True)
    _run(drv, i, rec, lambda t: centre, 0.6, limit * CURRENT_UNIT_A, False)
    drv._write(i, "goal_current", cap_design)
    amp = min(0.15 * TICKS_PER_RAD, 0.25 * (hi - lo))
    f0, f1, dur = 0.5, 6.0, 4.0
    chirp = lambda t: (
        centre + amp * math.sin(2 * math.pi * (f0 * t + (f1 - f0) * t * t / (2 * dur)))
    )  # noqa: E731,E501
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
        ws = w[seg]
        if m > k + 1 and np.all(np.abs(ws) > MIN_SPEED) and abs(np.sign(ws).sum()) == len(ws):
            ts = t[seg]
            rows.append([w[m] - w[k], th[m] - th[k], _trapezoid(np.sign(ws), ts)])
            rhs.append(_trapezoid(cur[seg], ts))
        k = m
    a_dyn, b_dyn = np.array(rows), np.array(rhs)
    x_dyn, *_ = np.linalg.lstsq(a_dyn, b_dyn, rcond=None)
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
    j_kt, b_kt, c_kt = x_dyn
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


def identify(drv: DynamixelDriver, joints: list[str] | None = None) -> dict[str, Any]:
    """Bring up, excite and fit each named servo (default: all); the report as plain data."""
    specs = [s for s in drv.map.servos if joints is None or s.joint in joints]
    design = drv.design
    tree = build_tree(design)
    drv.bring_up()
    out = []
    for spec in specs:
        kind = kind_of(spec.joint)
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
    """Replace ``key = number`` lines of the ``[servo]`` table (comments kept).

    Raises:
        ValueError: A key is not in the table.
    """
    p = Path(design_path)
    lines = p.read_text(encoding="utf-8").splitlines(keepends=True)
    table = None
    done = set()
    for n, line in enumerate(lines):
        head = re.match(r"\s*\[([^\]]+)\]", line)
        if head:
            table = head.group(1).strip()
            continue
        m = re.match(r"(\s*)([A-Za-z_]+)(\s*=\s*)([-+0-9.eE]+)(.*)", line, re.S)
        if table == "servo" and m and m.group(2) in values:
            lines[n] = f"{m.group(1)}{m.group(2)}{m.group(3)}{values[m.group(2)]:.6g}{m.group(5)}"
            done.add(m.group(2))
    missing = set(values) - done
    if missing:
        raise ValueError(f"{p}: [servo] has no {', '.join(sorted(missing))}")
    p.write_text("".join(lines), encoding="utf-8")


__all__ = ["Record", "excite", "fit", "identify", "write_servo_values"]
