"""Leaving the servos safe: the torque-off a shutdown owes, and the close that confirms
it; a part of :class:`~firmware_interface.driver.DynamixelDriver`.

:class:`Shutdown` holds which servos a shutdown writes to (:meth:`Shutdown._owed_torque_off`),
the one torque-off sync write (:meth:`Shutdown._torque_off`, also the safe stop's in
:mod:`firmware_interface.fault_handling`) and :meth:`Shutdown.close`; the driver inherits it.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from dynamixel_sdk import COMM_SUCCESS, GroupSyncWrite

from firmware_interface.control_table import ADDR
from firmware_interface.errors import CommError

if TYPE_CHECKING:
    from firmware_interface.servo_map import ServoMap

log = logging.getLogger("firmware_interface.driver")

TORQUE_OFF_TRIES = 3
"""close(): reads of Torque Enable per servo (and re-sends of the torque-off to a servo
still on) before it warns that the servo's torque off is not confirmed."""
TORQUE_OFF_CONFIRM_S = 1.0
"""close(): no read of Torque Enable starts later than this after the first [s] (a silent
servo costs a reply timeout and a quiet window, about 70 ms at the default latency, so a
close on a silent bus returns within about 1.1 s); the servos not read by then are left
unconfirmed."""


class Shutdown:
    """The shutdown of :class:`~firmware_interface.driver.DynamixelDriver` (its state is
    the driver's: declared here for the type checker)."""

    map: ServoMap
    ids: list[int]
    port: Any
    packet: Any
    heard: set[int]
    other_model: dict[int, int]
    _enabled: set[int]
    _closed: bool
    torque_unconfirmed: list[int]

    def _torque_off(self, ids: list[int]) -> int:
        """One sync write of Torque Enable = 0 to ``ids`` (no reply: a sync write has
        none); the SDK's result, ``COMM_SUCCESS`` when there is no servo to write to."""
        if not ids:
            return COMM_SUCCESS
        g = GroupSyncWrite(self.port, self.packet, ADDR["torque_enable"], 1)
        for i in ids:
            g.addParam(i, [0])
        return int(g.txPacket())

    def close(self) -> None:
        """Leave the servos safe and close the port: torque off on every servo owed it
        (one sync write; every mapped servo but one of another model the driver never
        enabled, see :meth:`_owed_torque_off`), confirmed by reading Torque Enable back
        from each of them that answered a scan (see :meth:`_confirm_torque_off`); the
        servos left unconfirmed are named in a warning and kept in ``torque_unconfirmed``
        (every one of them heard when the sync write itself failed). A driver no servo
        ever answered only sends the sync write.

        Idempotent; never raises for a bus that stopped answering.
        """
        if self._closed:
            return
        owed = self._owed_torque_off()
        try:
            result = self._torque_off(owed)
            if result != COMM_SUCCESS:
                raise CommError(self._why(result))
            unconfirmed = self._confirm_torque_off(owed) if self.heard else {}
            self.torque_unconfirmed = sorted(unconfirmed)
            if unconfirmed:
                by_why: dict[str, list[int]] = {}
                for i, why in unconfirmed.items():
                    by_why.setdefault(why, []).append(i)
                log.warning("close: could not confirm the torque off of %s",
                            "; ".join(f"{', '.join(map(self._name, ids))} ({why})"
                                      for why, ids in by_why.items()))  # fmt: skip
        except Exception as exc:  # the port may be gone: closing must still succeed
            self.torque_unconfirmed = sorted(self.heard.intersection(owed))
            log.warning("close: could not turn the torque off: %s", exc)
        finally:
            self._closed = True
            try:
                self.port.closePort()
            except Exception:
                pass

    def _owed_torque_off(self) -> list[int]:
        """The mapped servos a shutdown (:meth:`close`, :meth:`safe_stop`) writes to and
        reads back: all but those whose last answer to a scan gave another model number
        than the map's and that the driver never sent a torque enable.

        Leaving such a servo alone is the safe choice: the driver never turned its torque
        on (the bring-up refuses it before configuring any servo), so no torque of ours is
        left to turn off, while another family's control table may keep another register
        at the X series' Torque Enable address (64), where a 0 could change a setting or
        move it; a servo whose model is not known (it never answered) still gets the
        torque-off, the safe default for one that may be the map's model with its torque
        on, and so does one of another model that the driver did enable (whatever answers
        on its ID now, the servo it enabled may still be there)."""
        return [i for i in self.ids if i not in self.other_model or i in self._enabled]

    def _confirm_torque_off(self, ids: list[int]) -> dict[int, str]:
        """Read Torque Enable of each servo of ``ids`` heard, up to
        :data:`TORQUE_OFF_TRIES` passes within :data:`TORQUE_OFF_CONFIRM_S`; returns the
        servos not confirmed off, with why. After a pass the torque-off goes again to the
        servos not confirmed, as one sync write (no reply awaited: a servo whose reply was
        lost costs no timeout). When no servo answered the first pass (a bus gone silent)
        the passes stop there."""
        addr = ADDR["torque_enable"]
        pending = {i: "" for i in ids if i in self.heard}
        deadline = time.monotonic() + TORQUE_OFF_CONFIRM_S
        for attempt in range(TORQUE_OFF_TRIES):
            answered = False
            for i in list(pending):
                if time.monotonic() > deadline:
                    pending[i] = pending[i] or (
                        f"not read within the {TORQUE_OFF_CONFIRM_S:g} s of the confirmation"
                    )
                    continue
                value, result, _ = self.packet.read1ByteTxRx(self.port, i, addr)
                answered |= result == COMM_SUCCESS
                if result == COMM_SUCCESS and value == 0:
                    del pending[i]
                elif result == COMM_SUCCESS:
                    pending[i] = "still on"
                else:
                    pending[i] = self._why(result, i)
            if not pending or (attempt == 0 and not answered):
                break
            self._torque_off(list(pending))  # read back on the next pass
            if time.monotonic() > deadline:
                break
        return pending


__all__ = ["TORQUE_OFF_CONFIRM_S", "TORQUE_OFF_TRIES", "Shutdown"]
