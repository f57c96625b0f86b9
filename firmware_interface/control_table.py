"""The XC330-M288-T control table (Protocol 2.0): addresses, sizes, access, ranges, units.

Addresses and units follow the ROBOTIS e-Manual (``docs/sources.md``). Registers below
address 64 are the EEPROM area: writable only while torque is off. Defaults and ranges
the project does not depend on are typical XC330 values; the ones it does depend on
(model number, the bring-up registers, the feedback registers) are the documented ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from payload.design.servo import CURRENT_UNIT_A as CURRENT_UNIT_A  # re-exported
from payload.design.servo import TICKS_PER_REV

MODEL_NUMBER = 1240  # XC330-M288-T
FIRMWARE_VERSION = 52  # ASSUMPTION: a current XC330 firmware, reported by PING
EMULATOR_MODEL_INFORMATION = int.from_bytes(b"EMU1", "little")
"""Model Information (address 2) the emulator's servos report, so a host can tell it from
a payload (a real XC330 reports its own value there)."""
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
VELOCITY_UNIT_RPM = 0.229
VOLTAGE_UNIT_V = 0.1
WATCHDOG_UNIT_S = 0.020
EEPROM_END = 64
TABLE_SIZE = 147

BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}  # fmt: skip
"""Baud Rate register value -> bits per second."""

OPERATING_MODES = {0: "current", 1: "velocity", 3: "position", 4: "extended position",
                   5: "current-based position", 16: "PWM"}  # fmt: skip

# hardware error status bits (address 70)
HW_ERROR_BITS = {
    "input_voltage": 0,
    "overheating": 2,
    "encoder": 3,
    "electrical_shock": 4,
    "overload": 5,
}
HW_ERROR_NAMES = {bit: name for name, bit in HW_ERROR_BITS.items()}


@dataclass(frozen=True)
class Register:
    """One control-table entry.

    Attributes:
        name: Register name (snake case).
        address: First byte.
        size: 1, 2 or 4 bytes (little endian).
        writable: Whether the host may write it.
        default: Value after power-up or REBOOT.
        lo: Smallest value a write may set.
        hi: Largest value a write may set.
        signed: Two's complement.
    """

    name: str
    address: int
    size: int
    writable: bool
    default: int = 0
    lo: int = 0
    hi: int = 0
    signed: bool = False

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END


def _r(name: str, address: int, size: int, default: int = 0) -> Register:
    return Register(name, address, size, False, default, signed=size > 1)


def _rw(name: str, address: int, size: int, default: int, lo: int, hi: int) -> Register:
    return Register(name, address, size, True, default, lo, hi, signed=lo < 0)


REGISTERS: tuple[Register, ...] = (
    Register("model_number", 0, 2, False, MODEL_NUMBER),
    Register("model_information", 2, 4, False, 0),
    Register("firmware_version", 6, 1, False, FIRMWARE_VERSION),
    _rw("id", 7, 1, 1, 0, 252),
    _rw("baud_rate", 8, 1, 1, 0, 7),
    _rw("return_delay_time", 9, 1, 250, 0, 254),
    _rw("drive_mode", 10, 1, 0, 0, 13),
    _rw("operating_mode", 11, 1, 3, 0, 16),
    _rw("secondary_id", 12, 1, 255, 0, 255),
    _rw("protocol_type", 13, 1, 2, 1, 2),
    _rw("homing_offset", 20, 4, 0, -1_044_479, 1_044_479),
    _rw("moving_threshold", 24, 4, 10, 0, 1023),
    _rw("temperature_limit", 31, 1, 70, 0, 100),
    _rw("max_voltage_limit", 32, 2, 70, 31, 70),
    _rw("min_voltage_limit", 34, 2, 35, 31, 70),
    _rw("pwm_limit", 36, 2, 885, 0, 885),
    _rw("current_limit", 38, 2, 1750, 0, 1750),
    _rw("velocity_limit", 44, 4, 1023, 0, 2047),
    _rw("max_position_limit", 48, 4, 4095, 0, 4095),
    _rw("min_position_limit", 52, 4, 0, 0, 4095),
    _rw("startup_configuration", 60, 1, 0, 0, 3),
    _rw("shutdown", 63, 1, 52, 0, 255),
    _rw("torque_enable", 64, 1, 0, 0, 1),
    _rw("led", 65, 1, 0, 0, 1),
    _rw("status_return_level", 68, 1, 2, 0, 2),
    Register("registered_instruction", 69, 1, False, 0),
    Register("hardware_error_status", 70, 1, False, 0),
    _rw("velocity_i_gain", 76, 2, 1600, 0, 16383),
    _rw("velocity_p_gain", 78, 2, 180, 0, 16383),
    _rw("position_d_gain", 80, 2, 0, 0, 16383),
    _rw("position_i_gain", 82, 2, 0, 0, 16383),
    _rw("position_p_gain", 84, 2, 400, 0, 16383),
    _rw("bus_watchdog", 98, 1, 0, 0, 127),
    _rw("goal_pwm", 100, 2, 885, -885, 885),
    _rw("goal_current", 102, 2, 1750, -1750, 1750),
    _rw("goal_velocity", 104, 4, 0, -1023, 1023),
    _rw("profile_acceleration", 108, 4, 0, 0, 32767),
    _rw("profile_velocity", 112, 4, 0, 0, 32767),
    _rw("goal_position", 116, 4, 0, -1_048_575, 1_048_575),
    _r("realtime_tick", 120, 2),
    Register("moving", 122, 1, False),
    Register("moving_status", 123, 1, False),
    _r("present_pwm", 124, 2),
    _r("present_current", 126, 2),
    _r("present_velocity", 128, 4),
    _r("present_position", 132, 4),
    _r("velocity_trajectory", 136, 4),
    _r("position_trajectory", 140, 4),
    Register("present_input_voltage", 144, 2, False, 50),
    Register("present_temperature", 146, 1, False, 32),
)
BY_NAME: dict[str, Register] = {r.name: r for r in REGISTERS}
BY_ADDRESS: dict[int, Register] = {r.address: r for r in REGISTERS}
ADDR = {r.name: r.address for r in REGISTERS}
"""Register name -> address."""


def encode(reg: Register, value: int) -> bytes:
    """``value`` as the register's little-endian bytes (two's complement when signed)."""
    return int(value).to_bytes(reg.size, "little", signed=reg.signed and value < 0)


def decode(reg: Register, raw: bytes) -> int:
    """The register's value from its bytes."""
    return int.from_bytes(raw, "little", signed=reg.signed)


def to_signed(value: int, size: int) -> int:
    """An unsigned ``size``-byte value (as the SDK's getData returns) as two's complement."""
    bits = 8 * size
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


def hw_error_names(status: int) -> list[str]:
    """Names of the bits set in a Hardware Error Status value."""
    return [name for bit, name in sorted(HW_ERROR_NAMES.items()) if status & (1 << bit)]
