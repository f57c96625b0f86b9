"""The serial port the driver gives ``dynamixel_sdk``."""

from __future__ import annotations

import termios
import threading

from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_CORRUPT,
    COMM_RX_FAIL,
    COMM_SUCCESS,
    GroupSyncRead,
    PortHandler,
    Protocol2PacketHandler,
)

from firmware_interface.errors import CommError


class SdkPort(PortHandler):
    """The SDK's PortHandler with the packet timeout's latency allowance configurable.

    The SDK assumes a USB adapter latency timer of 16 ms (``LATENCY_TIMER``) and waits
    twice that plus the packet's bytes for a reply; a bus behind another latency (an
    adapter set to 1 ms, a busy host) sets its own.

    The SDK marks the port in use (``is_using``) for the length of a transaction and
    refuses a new one while it is set. An exception that cuts a transaction short (Ctrl-C
    while a reply is awaited, a device that vanished) leaves the mark set, and every later
    transaction, the torque-off of :meth:`DynamixelDriver.close` included, failed as
    "Port is in use!". The mark here remembers the thread that set it: the SDK's calls
    are not re-entrant, so a thread that starts a transaction while its own mark is set
    is past a transaction that was cut short; the mark is cleared and the half-read reply
    dropped. Another thread's transaction still holds the port.

    A serial device that fails (unplugged, the emulator's pty gone) raises
    :class:`CommError` naming the device, not the serial library's own exception.
    """

    def __init__(self, port_name: str, latency_timer_ms: float) -> None:
        self._user: int | None = None  # the thread whose transaction holds the port
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    @property
    def is_using(self) -> bool:  # type: ignore[override]
        if self._user is not None and self._user == threading.get_ident():
            self._user = None  # this thread's last transaction was cut short: it is over
            try:
                if self.ser is not None:
                    self.ser.reset_input_buffer()  # the rest of its reply, if any
            except (OSError, termios.error):
                pass
        return self._user is not None

    @is_using.setter
    def is_using(self, value: bool) -> None:
        self._user = threading.get_ident() if value else None

    def _failed(self, exc: BaseException) -> CommError:
        return CommError(f"{self.port_name}: the serial device failed ({exc}): unplugged, "
                         "powered off, or the emulator ended?")  # fmt: skip

    def readPort(self, length: int) -> bytes:
        try:
            return super().readPort(length)
        except (OSError, termios.error) as exc:
            raise self._failed(exc) from exc

    def writePort(self, packet: list[int]) -> int:
        try:
            return super().writePort(packet)
        except (OSError, termios.error) as exc:
            raise self._failed(exc) from exc

    def clearPort(self) -> None:
        try:
            super().clearPort()
        except (OSError, termios.error) as exc:
            raise self._failed(exc) from exc

    def setPacketTimeout(self, packet_length: int) -> None:
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (
            self.tx_time_per_byte * packet_length + self.latency_timer_ms * 2.0 + 2.0
        )


class AlertSyncRead(GroupSyncRead):
    """GroupSyncRead that keeps each servo's status error byte (bit 7: the alert).

    The SDK's group drops the error byte of each servo's status; the driver needs its
    alert bit (a latched hardware error) in the same cycle. ``errors`` maps ID -> the
    error byte of the last successful read.
    """

    def __init__(self, port: PortHandler, ph: Protocol2PacketHandler, start: int, n: int) -> None:
        super().__init__(port, ph, start, n)
        self.errors: dict[int, int] = {}
        self.silent_id: int | None = None
        """The servo whose status the last plain sync read did not get (it stops there)."""

    def rxPacket(self) -> int:
        """Plain sync read: one status packet per servo, its error byte kept."""
        self.last_result = False
        self.silent_id = None
        result = COMM_RX_FAIL
        for dxl_id in self.data_dict:
            data, result, error = self.ph.readRx(self.port, dxl_id, self.data_length)
            if result != COMM_SUCCESS:
                self.silent_id = dxl_id
                return result
            self.data_dict[dxl_id], self.errors[dxl_id] = data, int(error)
        self.last_result = result == COMM_SUCCESS
        return result

    def fastSyncReadRxPacket(self) -> int:
        """Fast sync read: per servo ``ERR, ID, data, CRC`` in one packet; errors kept."""
        self.last_result = False
        n = self.data_length
        raw, result, _ = self.ph.fastSyncReadRx(
            self.port, BROADCAST_ID, (n + 4) * len(self.data_dict)
        )
        if result != COMM_SUCCESS:
            return result
        raw = bytes(raw)
        for k in range(len(self.data_dict)):
            part = raw[k * (n + 4) : (k + 1) * (n + 4)]
            if len(part) < n + 2 or part[1] not in self.data_dict:
                return COMM_RX_CORRUPT
            self.data_dict[part[1]] = bytearray(part[2 : 2 + n])
            self.errors[part[1]] = part[0]
        self.last_result = True
        return COMM_SUCCESS
