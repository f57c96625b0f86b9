"""Health readings and recovery reports of the servos."""

from __future__ import annotations

from dataclasses import dataclass

from firmware_interface.control_table import hw_error_names


@dataclass(frozen=True)
class ServoHealth:
    """Health reading of one servo (Hardware Error Status, temperature, input voltage)."""

    id: int
    joint: str
    hardware_error: int
    temperature_c: float
    voltage_v: float
    watchdog: int
    model_number: int = 0

    @property
    def bits(self) -> list[str]:
        """Names of the hardware error bits set."""
        return hw_error_names(self.hardware_error)


@dataclass(frozen=True)
class Recovery:
    """What :meth:`DynamixelDriver.recover` did.

    Attributes:
        ids: Servos rebooted and returned to service.
        seconds: Time from the REBOOT to back in service [s].
    """

    ids: tuple[int, ...]
    seconds: float
