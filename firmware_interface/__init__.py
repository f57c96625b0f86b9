"""The payload's Dynamixel hardware: driver, servo map, and the Protocol 2.0 bus emulator.

The public names load on first use, so the emulator process (``python -m
firmware_interface.emulator``) does not import the driver, the SDK or the design.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "DynamixelDriver": "firmware_interface.driver",
    "CommandGuard": "firmware_interface.guard",
    "Recovery": "firmware_interface.health",
    "ServoHealth": "firmware_interface.health",
    "ServoMap": "firmware_interface.servo_map",
    "ServoSpec": "firmware_interface.servo_map",
    "ServoMapError": "firmware_interface.servo_map",
    "load_servo_map": "firmware_interface.servo_map",
    "EmulatorProcess": "firmware_interface.emulator",
    "HardwareInTheLoop": "firmware_interface.run",
    "CommError": "firmware_interface.errors",
    "DynamixelError": "firmware_interface.errors",
    "HardwareFault": "firmware_interface.errors",
    "MissingServoError": "firmware_interface.errors",
    "FaultSpecError": "firmware_interface.faults",
    "parse_fault": "firmware_interface.faults",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'firmware_interface' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
