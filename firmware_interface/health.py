"""Health readings and recovery reports of the servos."""

from __future__ import annotations

from dataclasses import dataclass

from firmware_interface.control_table import hw_error_names


@dataclass(frozen=True)
class ServoHealth:
    """Health reading of one servo (Hardware Error Status, temperature, input voltage,
    Bus Watchdog, Torque Enable)."""

    id: int
    joint: str
    hardware_error: int
    temperature_c: float
    voltage_v: float
    watchdog: int
    model_number: int = 0
    torque: bool = True

    @property
    def reset(self) -> bool:
        """Torque off with no hardware error: the servo restarted (power lost, a REBOOT)."""
        return not self.torque and not self.hardware_error

    @property
    def bits(self) -> list[str]:
        """Names of the hardware error bits set (``reset`` for a servo that restarted)."""
        return hw_error_names(self.hardware_error) or (["reset"] if self.reset else [])


@dataclass(frozen=True)
class Recovery:
    """What :meth:`DynamixelDriver.recover` did.

    Attributes:
        ids: Servos rebooted and returned to service.
        seconds: Time from the REBOOT to back in service [s].
    """

    ids: tuple[int, ...]
    seconds: float
