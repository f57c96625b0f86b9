"""One emulated XC330 servo: its control table, write rules, dynamics and hardware errors.

Dynamics (current-based position mode): the design's servo model, a second-order shaft
driven by the firmware's PID current law under the Goal Current cap and the supply
voltage (:mod:`firmware_interface.servo_dynamics`, docs/servo.md). A blocked output (an injected
obstacle) cannot move: its current sits at the cap and after ``OVERLOAD_S`` at the cap
the overload bit trips, as the servo's overload protection does.

Power-up and REBOOT (e-Manual, Extended Position Control Mode and Homing Offset): the
servo's absolute encoder covers one turn, so after power-up or a REBOOT the multi-turn
count is lost and Present Position reads the shaft angle within one turn (0..4095) plus
the Homing Offset (an EEPROM register, kept). The model keeps the physical output
position (``pos + origin``, in the servo map's tick frame) apart from the count the
servo reports (``pos``); ``origin`` is a whole number of turns fixed at power-up.

Constraints applied after the motion law (kept apart from it): hard stops (the rail's
and the stage's travel ends, physical ticks) and an external load on the output (the
grasp's contact torque, as the current it takes to hold it [mA]). An output pushed into
a stop, or against a load its current cap cannot overcome, does not move; its current
sits at the cap and the overload bit trips after ``OVERLOAD_S``, as with ``blocked``.
"""

from __future__ import annotations

import math
import struct

from firmware_interface import protocol as P
from firmware_interface.control_table import (
    ADDR,
    BY_ADDRESS,
    BY_NAME,
    EEPROM_END,
    EMULATOR_MODEL_INFORMATION,
    HW_ERROR_BITS,
    REGISTERS,
    TABLE_SIZE,
    TICKS_PER_REV,
    VELOCITY_UNIT_RPM,
    VOLTAGE_UNIT_V,
    WATCHDOG_UNIT_S,
    decode,
)
from firmware_interface.servo_dynamics import Plant, ServoDynamics, default_plant
from payload.design.servo import TICKS_PER_RAD

OVERLOAD_S = 1.0  # [s] at the current cap while stalled before the overload bit trips
_FMT = {
    r.name: (r.address, struct.Struct("<" + {1: "b", 2: "h", 4: "i"}[r.size]
                                      if r.signed else "<" + {1: "B", 2: "H", 4: "I"}[r.size]))
    for r in REGISTERS
}  # fmt: skip
_GOAL_REGS = {ADDR["goal_pwm"], ADDR["goal_current"], ADDR["goal_velocity"], ADDR["goal_position"]}


class ServoModel:
    """An emulated servo.

    Args:
        dxl_id: Its ID.
        position: Initial output position [ticks].
        now: Current time [s] (monotonic).
        stops: Hard stops ``(low, high)`` of the output [physical ticks], or None.
        plant: Its output shaft (default: an unloaded servo of the packaged design).
    """

    def __init__(
        self,
        dxl_id: int,
        position: float = 2048.0,
        now: float = 0.0,
        stops: tuple[float, float] | None = None,
        plant: Plant | None = None,
    ) -> None:
        self.table = bytearray(TABLE_SIZE)
        for reg in REGISTERS:
            self._set(reg.name, reg.default)
        self._set("id", dxl_id)
        self._set("model_information", EMULATOR_MODEL_INFORMATION)
        self.pos = float(position)
        self.origin = 0.0  # physical position of count 0 [ticks], whole turns
        self.stops = stops
        self.load_ma = 0.0  # external load on the output, as holding current [mA]
        self.stop_stall = 0.0  # time pushed into a stop or a load at the cap [s]
        self.vel = 0.0  # [ticks/s]
        self.current = 0.0  # [mA]
        self.blocked = False
        self.stall_time = 0.0
        self.t = now
        self.last_rx = now
        self.watchdog_start = now
        self.watchdog_trip: float | None = None
        self.reboots = 0
        self.power_ups = 0
        self._power_up()
        self.dynamics = ServoDynamics(plant or default_plant(), self.pos)
        self._refresh()

    # -- table access ------------------------------------------------------------------------
    def get(self, name: str) -> int:
        """A register's value (signed registers as two's complement)."""
        addr, fmt = _FMT[name]
        return fmt.unpack_from(self.table, addr)[0]

    def _set(self, name: str, value: int) -> None:
        addr, fmt = _FMT[name]
        fmt.pack_into(self.table, addr, value)

    @property
    def id(self) -> int:
        return self.table[ADDR["id"]]

    @property
    def hw_error(self) -> int:
        return self.table[ADDR["hardware_error_status"]]

    @property
    def torque(self) -> bool:
        return bool(self.table[ADDR["torque_enable"]])

    @property
    def return_delay(self) -> float:
        """Return Delay Time [s] (unit 2 us)."""
        return self.table[ADDR["return_delay_time"]] * 2e-6

    def alert(self) -> int:
        """The alert bit for status packets (set while a hardware error is latched)."""
        return P.ALERT if self.hw_error else 0

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """READ: (error, data)."""
        if length == 0 or address + length > TABLE_SIZE:
            return P.ERR_DATA_RANGE | self.alert(), b""
        return self.alert(), bytes(self.table[address : address + length])

    def write(self, address: int, data: bytes) -> int:
        """WRITE with the servo's rules; returns the status error (nothing written on error).

        Access error: a read-only register, or the EEPROM area with torque on. Data range
        error: a value outside the register's range, or a goal written while the Bus
        Watchdog has tripped. Data length error: a write that cuts a register.
        """
        regs = []
        a, end = address, address + len(data)
        if end > TABLE_SIZE or not data:
            return P.ERR_DATA_RANGE | self.alert()
        while a < end:
            reg = BY_ADDRESS.get(a)
            if reg is None:  # reserved byte: skipped like the servo does
                a += 1
                continue
            if a + reg.size > end:
                return P.ERR_DATA_LENGTH | self.alert()
            regs.append((reg, decode(reg, data[a - address : a - address + reg.size])))
            a += reg.size
        for reg, value in regs:
            if not reg.writable:
                return P.ERR_ACCESS | self.alert()
            if reg.address < EEPROM_END and self.torque:
                return P.ERR_ACCESS | self.alert()
            err = self._check_value(reg.name, reg.address, value)
            if err:
                return err | self.alert()
        for reg, value in regs:
            self._apply(reg.name, value)
        return self.alert()

    def _check_value(self, name: str, address: int, value: int) -> int:
        reg = BY_NAME[name]
        if name == "bus_watchdog" and value == 0:
            return 0
        if not reg.lo <= value <= reg.hi:
            return P.ERR_DATA_RANGE
        if address in _GOAL_REGS and self.watchdog_trip is not None:
            return P.ERR_DATA_RANGE
        if name == "goal_current" and abs(value) > self.get("current_limit"):
            return P.ERR_DATA_LIMIT
        if name == "goal_position" and self.get("operating_mode") == 3:
            if not self.get("min_position_limit") <= value <= self.get("max_position_limit"):
                return P.ERR_DATA_LIMIT
        if name == "torque_enable" and value == 1 and self.hw_error:
            return P.ERR_RESULT_FAIL
        return 0

    def _apply(self, name: str, value: int) -> None:
        if name == "torque_enable":
            if value and not self.torque:
                # torque on: hold where it is, restart the watchdog
                self._set("goal_position", round(self.pos) + self.get("homing_offset"))
                self.watchdog_start = self.t
            if not value:
                self._clear_watchdog()
        if name == "bus_watchdog":
            if value == 0:
                self._clear_watchdog()
            self.watchdog_start = self.t
        self._set(name, value)

    def _clear_watchdog(self) -> None:
        self.watchdog_trip = None
        if self.table[ADDR["bus_watchdog"]] == 0xFF:
            self._set("bus_watchdog", 0)

    # -- events ------------------------------------------------------------------------------
    def heard(self, now: float) -> None:
        """An instruction for this servo arrived (resets the Bus Watchdog interval)."""
        self.last_rx = now

    def set_error(self, bit_name: str) -> None:
        """Latch a hardware error bit; shutdown bits turn the torque off."""
        bit = HW_ERROR_BITS[bit_name]
        self._set("hardware_error_status", self.hw_error | (1 << bit))
        if self.get("shutdown") & (1 << bit):
            self._set("torque_enable", 0)
            self._clear_watchdog()

    def reboot(self) -> None:
        """REBOOT: RAM back to its defaults, EEPROM kept, errors cleared, torque off."""
        for reg in REGISTERS:
            if reg.address >= EEPROM_END:
                self._set(reg.name, reg.default)
        self.watchdog_trip = None
        self.stall_time = self.stop_stall = 0.0
        self.vel = 0.0
        self.current = 0.0
        self.dynamics.reset()
        self.reboots += 1
        self._power_up()
        self._refresh()

    def _power_up(self) -> None:
        """The multi-turn count is lost: the count restarts within one turn of the encoder."""
        phys = self.pos + self.origin
        self.origin = TICKS_PER_REV * math.floor(phys / TICKS_PER_REV)
        self.pos = phys - self.origin
        self.power_ups += 1

    def power_cycle(self) -> None:
        """Power off and on: RAM back to its defaults (EEPROM kept), count within one turn."""
        self.reboot()
        self.reboots -= 1

    @property
    def physical(self) -> float:
        """The output's physical position [ticks of the servo map's frame]."""
        return self.pos + self.origin

    # -- dynamics ----------------------------------------------------------------------------
    def advance(self, now: float) -> None:
        """Integrate the output and the watchdog up to ``now``."""
        if now <= self.t:
            return
        wd = self.table[ADDR["bus_watchdog"]]
        if self.torque and 0 < wd < 0x80 and self.watchdog_trip is None:
            trip = max(self.last_rx, self.watchdog_start) + wd * WATCHDOG_UNIT_S
            if now > trip:
                # move until the trip, then stop: hold there, the register reads -1
                if trip > self.t:
                    self._step(trip - self.t)
                    self.t = trip
                self.watchdog_trip = trip
                self._set("bus_watchdog", -1 & 0xFF)
                self._set("goal_position", round(self.pos) + self.get("homing_offset"))
        dt = now - self.t
        self.t = now
        if self.torque:
            self._step(dt)
        else:
            self.vel, self.current, self.stall_time, self.stop_stall = 0.0, 0.0, 0.0, 0.0
            self.dynamics.reset()
        self._refresh()

    def _step(self, dt: float) -> None:
        """The motion law, then the constraints on the output (stops, load)."""
        before = self.pos
        self._move(dt)
        self._constrain(before, dt)

    def _constrain(self, before: float, dt: float) -> None:
        cap = float(abs(self.get("goal_current")))
        held = False
        push = self.current
        if self.stops is not None:
            lo, hi = self.stops[0] - self.origin, self.stops[1] - self.origin
            if self.pos < lo or (self.pos <= lo and push < 0):
                self.pos, held = lo, True
            elif self.pos > hi or (self.pos >= hi and push > 0):
                self.pos, held = hi, True
        if self.load_ma and push * self.load_ma < 0 and cap <= abs(self.load_ma):
            self.pos, held = before, True  # the load holds the output where it was
        if not held:
            self.stop_stall = 0.0
            return
        self.vel = (self.pos - before) / dt if dt > 0 else 0.0
        self.dynamics.pos, self.dynamics.vel = self.pos, 0.0  # the stop or load took it
        if cap > 0 and abs(push) >= cap:
            self.stop_stall += dt
            if self.stop_stall >= OVERLOAD_S:
                self.set_error("overload")
        else:
            self.stop_stall = 0.0

    def _move(self, dt: float) -> None:
        if dt <= 0.0:
            return
        # after a Bus Watchdog trip the goal is the position at the trip (written then,
        # goals refused since): the shaft brakes back to it, it does not drift
        goal = self.get("goal_position") - self.get("homing_offset")
        gains = (self.get("position_p_gain"), self.get("position_i_gain"),
                 self.get("position_d_gain"))  # fmt: skip
        cap = float(abs(self.get("goal_current")))
        dyn = self.dynamics
        dyn.pos = self.pos
        dyn.advance(dt, goal, gains, cap, self.blocked)
        self.pos, self.current = dyn.pos, dyn.current
        self.vel = dyn.vel * TICKS_PER_RAD  # [ticks/s]
        if self.blocked:
            if cap > 0 and abs(dyn.demand) >= cap:
                self.stall_time += dt
                if self.stall_time >= OVERLOAD_S:
                    self.set_error("overload")
            return
        self.stall_time = 0.0

    def _refresh(self) -> None:
        """Present registers from the state (the supply's voltage too: a REBOOT's RAM
        defaults do not change the supply)."""
        self._set("present_input_voltage", round(self.dynamics.plant.voltage / VOLTAGE_UNIT_V))
        self._set("present_position", round(self.pos) + self.get("homing_offset"))
        self._set("present_velocity", round(self.vel / TICKS_PER_REV * 60.0 / VELOCITY_UNIT_RPM))
        self._set("present_current", round(self.current))
        threshold = self.get("moving_threshold") * VELOCITY_UNIT_RPM / 60 * TICKS_PER_REV
        moving = abs(self.vel) > threshold
        self.table[ADDR["moving"]] = int(moving)
        self._set("realtime_tick", int(self.t * 1000) % 32768)
