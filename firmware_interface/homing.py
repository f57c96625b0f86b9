"""Homing of the rail and the stage: a current-limited move to the stowed hard stop.

The XC330's encoder is absolute over one turn only: after power-up or a REBOOT, Present
Position reads the shaft angle within one turn plus the Homing Offset, the multi-turn
count is lost (ROBOTIS e-Manual, XC330: Homing Offset (20), Present Position (132),
Extended Position Control Mode). The rail and the stage span several turns (the rail
ticks 1024 to 6456, the stage 1024 to -7125), so their absolute position is unknown
until homed. The method the e-Manual supports: the servo is driven under a low current
cap (Goal Current, current-based position mode) toward the stowed end (joint value 0) by
more than the whole travel plus a turn; when it stalls against the hard stop its torque
goes off, Homing Offset is set so that Present Position reads the stop's tick (the map's
``zero``) and the full current cap restored. The offset is written only then: a homing
cut short leaves the last one, which a power-up's reading needs.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from firmware_interface.control_table import ADDR, TICKS_PER_REV, to_signed
from firmware_interface.errors import HomingError
from firmware_interface.servo_map import ServoSpec

HOMING_CURRENT_FRACTION = 0.5
"""Goal Current while homing, as a fraction of the design's current cap (ASSUMPTION: low
enough that the stop is met at half the running force, high enough to overcome the
drive's friction)."""
STALL_TICKS = 1  # a homing servo that moved no more than this ...
STALL_S = 0.06  # ... for this long [s], at its current cap, is at the stop
POLL_S = 0.01  # feedback read period while homing [s]
FREE_CHECK_FRACTION = 0.1
"""The free-travel check: each servo found stalled is driven off it by this fraction of
its joint's travel, under the homing current, and must cover at least half of it
(ASSUMPTION: a tenth of the travel is far enough to tell a free drive from a blocked one
and short enough not to matter where the payload stands). A stall alone cannot tell the
hard stop from a jammed drive: a drive that stalls and then does not move off it is
refused, not homed. An obstacle short of the stop on the stowed side, which the drive can
back away from, still reads as the stop (docs/hardware.md)."""
FREE_CHECK_S = 0.5
"""The longest wait for the free-travel move [s] (ASSUMPTION: the move is 0.13 to 0.2
of a turn, about 0.1 s at the XC330's speed; a blocked servo stops pushing at its cap
well before an overload protection time of the order of a second trips it, the
emulator's ``servo_model.OVERLOAD_S``)."""


def home_linear(
    write: Callable[[int, str, int], None],
    read_reg: Callable[[int, int, int], int],
    feedback: Callable[[], tuple[np.ndarray, np.ndarray]],
    ids: list[int],
    specs: list[ServoSpec],
    span_ticks: dict[int, int],
    cap_ma: int,
    timeout: float = 6.0,
) -> dict[int, int]:
    """Home the rail and/or the stage (the driver homes them one at a time, the rail
    first); returns ID -> Homing Offset written.

    Each servo is driven to its stowed stop until it stalls, driven off the stall by
    :data:`FREE_CHECK_FRACTION` of its travel (the free-travel check) and back to the
    stop; Homing Offset is then set from where it stalls (until then it keeps the last
    homing's).

    Args:
        write: Writes one register (``write(id, name, value)``), status checked.
        read_reg: Reads one register (``read_reg(id, address, size)``), unsigned.
        feedback: One feedback read of every mapped servo: ``(current [mA], position
            [ticks])``, each shape (n,), in the order of ``ids``.
        ids: Every mapped servo ID (the order of ``feedback``).
        specs: The servos to home (the rail, the stage).
        span_ticks: ID -> the joint's travel [ticks].
        cap_ma: The design's current cap [mA] (restored after homing).
        timeout: Longest time to wait for the stops [s].

    Raises:
        HomingError: A servo did not reach its stop within ``timeout``, or did not move
            off where it stalled (blocked); its torque is left off.
    """
    i_home = max(1, round(HOMING_CURRENT_FRACTION * cap_ma))
    index = {spec.id: ids.index(spec.id) for spec in specs}
    # the Homing Offset stays the last homing's until this one has found the stop: one cut
    # short (a blocked drive, a timeout, the power lost) leaves the offset a power-up's
    # one-turn reading is read with (firmware_interface.deployment.linear_positions)
    kept = {s.id: to_signed(read_reg(s.id, ADDR["homing_offset"], 4), 4) for s in specs}
    for spec in specs:
        i = spec.id
        write(i, "torque_enable", 0)
        write(i, "goal_current", i_home)
    stalled = _to_the_stops(write, read_reg, feedback, index, specs, span_ticks, i_home,
                            timeout)  # fmt: skip
    _free_check(write, feedback, index, specs, span_ticks, stalled)
    _to_the_stops(write, read_reg, feedback, index, specs, span_ticks, i_home, timeout)
    offsets = {}
    for spec in specs:
        i = spec.id
        raw = to_signed(read_reg(i, ADDR["present_position"], 4), 4)  # the count + kept
        offsets[i] = kept[i] + spec.zero - raw
        write(i, "torque_enable", 0)
        write(i, "homing_offset", offsets[i])
        write(i, "goal_current", cap_ma)
        write(i, "torque_enable", 1)
        write(i, "goal_position", spec.zero)
    return offsets


def _to_the_stops(
    write: Callable[[int, str, int], None],
    read_reg: Callable[[int, int, int], int],
    feedback: Callable[[], tuple[np.ndarray, np.ndarray]],
    index: dict[int, int],
    specs: list[ServoSpec],
    span_ticks: dict[int, int],
    i_home: int,
    timeout: float,
) -> dict[int, int]:
    """Drive each servo toward joint value 0 under ``i_home`` until it stalls, its
    torque then turned off; returns ID -> the position it stalled at [ticks]."""
    for spec in specs:
        i = spec.id
        write(i, "torque_enable", 1)
        raw = to_signed(read_reg(i, ADDR["present_position"], 4), 4)
        # toward joint value 0 by more than the whole travel and a turn
        write(i, "goal_position", raw - spec.direction * (span_ticks[i] + TICKS_PER_REV))
    still_since: dict[int, float] = {}
    last: dict[int, int] = {}
    stopped: dict[int, int] = {}
    t0 = time.monotonic()
    while len(stopped) < len(specs):
        if time.monotonic() - t0 > timeout:
            missing = [s for s in specs if s.id not in stopped]
            for s in missing:
                write(s.id, "torque_enable", 0)
            raise HomingError(f"homing: {', '.join(s.joint for s in missing)} did not reach "
                              f"the hard stop within {timeout} s")  # fmt: skip
        time.sleep(POLL_S)
        cur, pos = feedback()
        now = time.monotonic()
        for spec in specs:
            i = spec.id
            if i in stopped:
                continue
            p, c = int(pos[index[i]]), float(cur[index[i]])
            if i not in last or abs(p - last[i]) > STALL_TICKS:
                last[i], still_since[i] = p, now
            elif now - still_since[i] >= STALL_S and abs(c) >= 0.9 * i_home:
                stopped[i] = p
                # stop pushing (the overload would trip) by turning the torque off: a goal
                # rewritten to p would step the error from the whole travel to 0 and the
                # D term's kick (D/16 per tick of that step) would pull the shaft off the
                # stop by a fraction of a tick, where the friction then holds it
                write(i, "torque_enable", 0)
    return stopped


def _free_check(
    write: Callable[[int, str, int], None],
    feedback: Callable[[], tuple[np.ndarray, np.ndarray]],
    index: dict[int, int],
    specs: list[ServoSpec],
    span_ticks: dict[int, int],
    stalled: dict[int, int],
) -> None:
    """The free-travel check: drive each servo off where it stalled, away from joint
    value 0, by :data:`FREE_CHECK_FRACTION` of its travel; it must cover half of that
    within :data:`FREE_CHECK_S`. Leaves every servo torque off.

    Raises:
        HomingError: Servos that did not (named, with how far they went).
    """
    out = {s.id: round(FREE_CHECK_FRACTION * span_ticks[s.id]) for s in specs}
    for spec in specs:
        i = spec.id
        write(i, "torque_enable", 1)
        write(i, "goal_position", stalled[i] + spec.direction * out[i])
    moved = {s.id: 0 for s in specs}
    t0 = time.monotonic()
    while time.monotonic() - t0 <= FREE_CHECK_S:
        time.sleep(POLL_S)
        _, pos = feedback()
        for spec in specs:
            i = spec.id
            moved[i] = max(moved[i], spec.direction * (int(pos[index[i]]) - stalled[i]))
        if all(2 * moved[s.id] >= out[s.id] for s in specs):
            break
    for spec in specs:
        write(spec.id, "torque_enable", 0)
    stuck = [s for s in specs if 2 * moved[s.id] < out[s.id]]
    if stuck:
        said = ", ".join(
            f"{s.joint} ({1e3 * moved[s.id] * s.units_per_tick:.1f} of "
            f"{1e3 * out[s.id] * s.units_per_tick:.1f} mm)"
            for s in stuck
        )
        raise HomingError(
            f"homing: {said} did not move off where it stalled when driven out: the drive "
            f"is jammed, or blocked on its way out; check the drive, then bring up again"
        )
