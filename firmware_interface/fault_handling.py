"""Health, faults and recovery of the payload's servos: a part of :class:`DynamixelDriver`.

:class:`FaultHandling` holds the driver's health reads, the reaction to a hardware error
(the safe stop) and the recovery (REBOOT, restore, re-home); the driver inherits it.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead

from firmware_interface.control_table import (
    ADDR,
    BY_NAME,
    VOLTAGE_UNIT_V,
    hw_error_names,
    to_signed,
)
from firmware_interface.deployment import (
    RAIL,
    STAGE,
    STOWED_TOL_RAD,
    shaft_per_rad,
    unstowed,
)
from firmware_interface.errors import CommError, HardwareFault, HomingError, WrongModelError
from firmware_interface.health import Recovery, ServoHealth

if TYPE_CHECKING:
    from firmware_interface.servo_map import ServoMap, ServoSpec

log = logging.getLogger("firmware_interface.driver")


class FaultHandling:
    """Health reads, the safe stop and recovery (mixed into :class:`DynamixelDriver`)."""

    map: ServoMap
    design: Any
    ids: list[int]
    port: Any
    packet: Any
    on_fault: str
    fault: HardwareFault | None
    faults: list[HardwareFault]
    health: dict[int, ServoHealth]
    _stopped: bool
    _torque_on: bool  # every servo's torque should be on (brought up, not stopped torque off)
    _reset: set[int]  # servos found restarted (torque off, no error): recover() reboots them
    homed: set[int]
    _present: Any
    _known: set[int]  # servos whose present position has been read (_present holds it)
    other_model: dict[int, int]  # servos answering as another model (ID -> its number)
    _longest_gap: float

    def _check_alerted(self, ids: list[int]) -> None:
        """Hardware Error Status of the servos whose status carried the alert bit."""
        faulted = []
        for i in ids:
            err = self._read_reg(i, ADDR["hardware_error_status"], 1)
            if err:
                faulted.append(ServoHealth(i, self.map.joint_of(i), err, 0.0, 0.0, 0))
        if faulted:
            self._on_hardware_error(faulted)

    # -- health, faults, recovery ------------------------------------------------------------
    def _group_read(self, address: int, size: int) -> GroupSyncRead:
        g = GroupSyncRead(self.port, self.packet, address, size)
        for i in self.ids:
            g.addParam(i)
        self._sync_read(g, f"address {address}")
        return g

    def read_health(self, dxl_id: int) -> ServoHealth:
        """One servo's health, read register by register (works with servos missing)."""
        return ServoHealth(
            dxl_id,
            self.map.joint_of(dxl_id),
            self._read_reg(dxl_id, ADDR["hardware_error_status"], 1),
            float(self._read_reg(dxl_id, ADDR["present_temperature"], 1)),
            self._read_reg(dxl_id, ADDR["present_input_voltage"], 2) * VOLTAGE_UNIT_V,
            self._read_reg(dxl_id, ADDR["bus_watchdog"], 1),
            self._read_reg(dxl_id, ADDR["model_number"], 2),
        )

    def check_health(self) -> dict[int, ServoHealth]:
        """Read Hardware Error Status, Bus Watchdog, input voltage and temperature.

        A hardware error stops the payload safely and is logged (see :meth:`safe_stop`).
        """
        torque, error, dog, volts, temp = (
            BY_NAME[n]
            for n in ("torque_enable", "hardware_error_status", "bus_watchdog",
                      "present_input_voltage", "present_temperature")
        )  # fmt: skip
        # Torque Enable .. Hardware Error Status in one read, voltage and temperature in one
        err = self._group_read(torque.address, error.address + error.size - torque.address)
        wd = self._group_read(dog.address, dog.size)
        env = self._group_read(volts.address, temp.address + temp.size - volts.address)
        out = {}
        for spec in self.map.servos:
            i = spec.id
            out[i] = ServoHealth(
                i,
                spec.joint,
                int(err.getData(i, error.address, error.size)),
                float(env.getData(i, temp.address, temp.size)),
                env.getData(i, volts.address, volts.size) * VOLTAGE_UNIT_V,
                int(wd.getData(i, dog.address, dog.size)),
                torque=bool(err.getData(i, torque.address, torque.size)),
            )
        self.health = out
        if any(h.watchdog == 0xFF for h in out.values()) and not self._stopped:
            # the longest silence since the last check could have tripped it, not the last
            self._rearm_watchdog(self._longest_gap)
        self._longest_gap = 0.0
        faulted = [h for h in out.values() if h.hardware_error]
        if self._torque_on:  # a servo found torque off restarted: its count (and homing) lost
            reset = [h for h in out.values() if h.reset]
            self._reset.update(h.id for h in reset)
            self.homed.difference_update(h.id for h in reset)
            faulted += reset
        if faulted and (self.fault is None or not self._stopped):
            self._on_hardware_error(faulted)
        return out

    def _on_hardware_error(self, faulted: list[ServoHealth]) -> None:
        h = faulted[0]
        also = [HardwareFault(x.id, x.joint, x.bits) for x in faulted[1:]]
        fault = HardwareFault(h.id, h.joint, h.bits, also=also)
        self.fault = fault
        self.faults.append(fault)
        log.error("servo fault, the payload stopped (%s): %s", self.on_fault, fault)
        self.safe_stop()

    def safe_stop(self) -> None:
        """Stop the payload: hold every servo where it is, or turn the torque off. A servo
        of another model than the map's that the driver never enabled is left alone, as
        :meth:`~firmware_interface.driver.DynamixelDriver.close` leaves it (its
        ``_owed_torque_off`` says why)."""
        self._stopped = True
        owed = self._owed_torque_off()
        # hold only a servo whose position has been read: a goal of the zeros the driver
        # starts with would move one left holding by another program; such a servo, and
        # every one when the fault's answer is torque off, gets the torque-off
        hold = [i for i in owed if i in self._known] if self.on_fault == "hold" else []
        off = [i for i in owed if i not in hold]
        self._torque_off(off)
        if self.on_fault == "torque_off":
            self._torque_on = False
            return
        self._sync_write_goals([int(p) for p in self._present], hold)

    def _homing_refused(self, relost: list[ServoSpec]) -> None:
        """Refuse to home ``relost`` (the rail, the stage) mid-session with the payload out
        of its stowed posture: homing drives them to their stowed stops, the stage up into
        the bays, whatever the fingers and the rail do. The stage goes up only as the
        deployment comes down, the fingers and the rail stowed (a rail whose count was
        kept is checked too; one that lost it is homed first, to its stowed stop). A new
        bring-up folds the fingers first
        (:func:`~firmware_interface.deployment.fold_before_homing`).

        Raises:
            HomingError: A finger, or the rail, more than ``STOWED_TOL_RAD`` (at its
                shaft) from stowed.
        """
        ticks = self.present_ticks()
        rail = self.map.servos[RAIL]
        kept_rail = all(sp.id != rail.id for sp in relost)
        specs = self.map.servos[: STAGE if kept_rail else RAIL]
        joint, off = unstowed(self.design, specs, ticks[: len(specs)])
        if off > STOWED_TOL_RAD:
            names = " and ".join(sp.joint for sp in relost)
            where = f"{off:.2f} rad"
            if joint == rail.joint:  # its shaft's radians as the rail's millimetres
                where = f"{off * shaft_per_rad([rail])[0] * 1e3:.1f} mm"
            out = "the rail" if joint == rail.joint else "the fingers"
            raise HomingError(
                f"{names} lost {'their' if len(relost) > 1 else 'its'} count with {joint} "
                f"{where} from stowed: homing would drive the stage into the bays with "
                f"{out} out, so the payload stays stopped; bring it up again (the "
                "fingers are folded before homing)"
            )

    def recover(self, timeout: float = 5.0) -> Recovery:
        """Reboot the faulted servo(s), restore their settings, return them to service.

        Returns:
            The servos rebooted and the time from the REBOOT to back in service.

        Raises:
            HardwareFault: The error is still there after the reboot (the cause persists).
            WrongModelError: Another model than the map's answers on a rebooted servo's ID
                (nothing of its table is read or written: not the registers the driver
                knows).
            CommError: A servo did not come back within ``timeout``.
        """
        self._check_open()
        self.check_health()
        ids = [h.id for h in self.health.values() if h.hardware_error or h.id in self._reset]
        t0 = time.monotonic()
        for i in ids:
            self.packet.reboot(self.port, i)
        for i in ids:
            while True:
                model, result, _ = self.packet.ping(self.port, i)
                if result == COMM_SUCCESS:
                    break
                if time.monotonic() - t0 > timeout:
                    raise CommError(f"{self._name(i)}: did not answer within {timeout} s of REBOOT")
            if model != self.map.model_number:  # swapped while it was down: not ours to set up
                self.other_model[i] = model
                raise WrongModelError(i, self.map.joint_of(i), model, self.map.model_number)
            err = self._read_reg(i, ADDR["hardware_error_status"], 1)
            if err:
                raise HardwareFault(i, self.map.joint_of(i), hw_error_names(err))
            self._configure(self.map.by_id(i))
        relost = [sp for sp in self._linear if sp.id in ids]
        if relost:  # a reboot lost the multi-turn count: home again, the fingers stowed
            self.homed.difference_update(sp.id for sp in relost)  # unknown until then
            self._homing_refused(relost)
            for spec in relost:  # the rail before the stage
                self.home([spec])
        self._arm_watchdog(self.ids)
        if self.on_fault == "torque_off":
            for spec in self.map.servos:
                if spec.id not in ids:
                    present = to_signed(self._read_reg(spec.id, ADDR["present_position"], 4), 4)
                    self._write(spec.id, "goal_position", present)
                    self._write(spec.id, "torque_enable", 1)
        self._stopped = False
        self._torque_on = True
        self._reset.clear()
        self.fault = None
        seconds = time.monotonic() - t0
        log.info("recovered %s in %.3f s", ", ".join(self._name(i) for i in ids), seconds)
        return Recovery(tuple(ids), seconds)
