"""The serial port the driver gives ``dynamixel_sdk``."""

from __future__ import annotations

import termios
import threading
import time

from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_CORRUPT,
    COMM_RX_FAIL,
    COMM_SUCCESS,
    DXL_MAKEWORD,
    GroupSyncRead,
    PortHandler,
    Protocol2PacketHandler,
)

from firmware_interface import protocol as P
from firmware_interface.errors import CommError

DRAIN_LIMIT_WINDOWS = 20
"""A drain gives up (:class:`CommError`) when the line is not quiet within this many
quiet windows: something keeps talking (another master on the bus, a wrong baud rate)."""


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

    A reply that is not there when its timeout ends may still be on its way: the SDK's
    next transaction (the retry, or the next read) would take it as its own answer (the
    status packet names the servo, not the register it answers). After a failed reply (a
    timeout, a corrupt packet, a parameter length other than the one asked for: see
    :class:`CheckedPacketHandler`) the port is ``unsettled``, and the next transaction
    first drains the line until it has been quiet for :attr:`quiet_window_ms`: the reply
    allowance of the timeout itself (twice the latency timer plus 2 ms), the time the SDK
    already gives the adapter and the host to pass a reply on, so a reply up to one more
    allowance late is drained, not taken. Whole status packets drained are counted per
    servo in ``late`` (ID -> count): replies that came after their timeout (with the status
    packets of servos not asked that a later request skipped, see
    :class:`CheckedPacketHandler`), but not those of the servos of a plain sync read that
    failed (``excused``): they answer that read, on time.
    """

    def __init__(self, port_name: str, latency_timer_ms: float) -> None:
        self._user: int | None = None  # the thread whose transaction holds the port
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms
        self.unsettled = False  # a reply failed: what is left of it may still arrive
        self.late: dict[int, int] = {}  # servo ID -> status packets drained after a timeout
        # the servos of a plain sync read that failed: their statuses drained next are that
        # read's answers, sent on time, that the SDK stopped waiting for (not counted late)
        self.excused: frozenset[int] = frozenset()

    @property
    def reply_allowance_ms(self) -> float:
        """What the reply timeout allows beyond the packet's bytes [ms]: twice the
        adapter's latency timer plus 2 ms (the SDK's rule)."""
        return self.latency_timer_ms * 2.0 + 2.0

    @property
    def quiet_window_ms(self) -> float:
        """How long the line must be quiet after a failed reply before the next
        transaction [ms]: one more reply allowance (see the class docstring)."""
        return self.reply_allowance_ms

    @property
    def is_using(self) -> bool:  # type: ignore[override]
        self._end_cut_short()
        return self._user is not None

    def _end_cut_short(self) -> None:
        if self._user is not None and self._user == threading.get_ident():
            self._user = None  # this thread's last transaction was cut short: it is over
            self.unsettled = True  # and its reply may still come
            try:
                if self.ser is not None:
                    self.ser.reset_input_buffer()  # the rest of its reply, if any
            except (OSError, termios.error):
                pass

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
        """Called by the SDK before every packet it sends: after a failed reply, drain the
        line until quiet (see the class docstring), then drop what is buffered."""
        if self.unsettled and self.ser is not None:  # (inside its own transaction)
            self._drain()
        try:
            super().clearPort()
        except (OSError, termios.error) as exc:
            raise self._failed(exc) from exc

    def settle(self) -> None:
        """Drain the line now if a reply failed (what is still on its way is counted in
        ``late``); nothing when the last reply was whole. Outside a transaction only."""
        self._end_cut_short()
        if self.unsettled and self.ser is not None:
            self._drain()

    def _drain(self) -> None:
        window = self.quiet_window_ms / 1e3
        drained = bytearray()
        now = time.monotonic()
        quiet_since, deadline = now, now + DRAIN_LIMIT_WINDOWS * window
        while now - quiet_since < window:
            got = self.readPort(4096)  # what came within the port's read timeout
            now = time.monotonic()
            if got:
                drained += got
                quiet_since = now
                if now > deadline:
                    raise CommError(
                        f"{self.port_name}: the line was not quiet for "
                        f"{self.quiet_window_ms:.0f} ms within {DRAIN_LIMIT_WINDOWS} windows "
                        "after a failed reply: another master on the bus, or a wrong baud rate?"
                    )
            elif not self.ser.timeout:  # a non-blocking port: do not spin
                time.sleep(0.0005)
        self.unsettled = False
        for dxl_id in _status_ids(drained):
            if dxl_id not in self.excused:
                self.late[dxl_id] = self.late.get(dxl_id, 0) + 1
        self.excused = frozenset()

    def isPacketTimeout(self) -> bool:
        if super().isPacketTimeout():
            self.unsettled = True  # the reply may still be on its way
            return True
        return False

    def setPacketTimeout(self, packet_length: int) -> None:
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.reply_allowance_ms


def _status_ids(data: bytes | bytearray) -> list[int]:
    """IDs of the whole status packets (CRC good) in ``data``, in order. A header that
    starts no whole packet (a bogus one, a packet cut off, a bad CRC) is skipped and the
    scan goes on after it: a whole packet behind it is still found."""
    ids = []
    buf = bytearray(data)
    while buf:
        try:
            pkt, used = P.split(buf)
        except P.CrcMismatch:
            pkt, used = None, 0
        if pkt is not None:
            del buf[:used]
            if pkt.instruction == P.STATUS:
                ids.append(pkt.id)
            continue
        start = buf.find(P.HEADER[:3])
        if start < 0:
            break
        del buf[: start + 1]  # past this header: what it started is not a whole packet
    return ids


def _params(rx: list[int]) -> int:
    """A status packet's parameter count after its error byte, from its LEN field
    (instruction, error, parameters, CRC 2): the SDK's ``removeStuffing`` sets LEN to
    the unstuffed length but leaves the list as long as the stuffed packet."""
    return DXL_MAKEWORD(rx[5], rx[6]) - 1 - P.STATUS_TAIL  # 1: the instruction


class CheckedPacketHandler(Protocol2PacketHandler):
    """The SDK's Protocol 2.0 packet handler, with the length of every status checked.

    The SDK takes any status packet from the servo it asked as the answer: a late reply
    to an earlier request (a ping's three bytes as a one-byte read, a two-byte Model Number
    as a four-byte position) was read as the answer to this one. Here a status whose
    parameter count differs from what the request asks for (PING 3, READ its length,
    WRITE and REBOOT none; a fast sync read its data and ``FAST_RECORD_OVERHEAD`` per
    servo) is a corrupt reply (``COMM_RX_CORRUPT``): the driver retries it, the port
    drains the line first. The count is the one the LEN field gives (see
    :func:`_params`), a byte-stuffed reply's too.

    A status from a servo not asked is counted late, but not one from a servo of the plain
    sync read under way (``group``, the IDs its packet names): it answers that read,
    on time, while the SDK still waits for a servo before it that went silent.

    Its port is the driver's :class:`SdkPort` (``unsettled``, ``late``, ``excused``).
    """

    def __init__(self) -> None:
        super().__init__()
        self._last: list[int] = []
        self._asked: int | None = None  # the servo whose status is awaited
        self.group: frozenset[int] = frozenset()  # the servos of the sync read under way

    def rxPacket(self, port: PortHandler, fast_option: bool) -> tuple[list[int], int]:
        rx, result = super().rxPacket(port, fast_option)
        self._last = rx
        if result != COMM_SUCCESS:
            port.unsettled = True
            port.excused = self.group
        elif self._asked is not None and rx[4] != self._asked and rx[4] not in self.group:
            # one master on the bus: a status from a servo not asked answers an earlier
            # request (the SDK skips it and waits on)
            port.late[rx[4]] = port.late.get(rx[4], 0) + 1
        return rx, result

    def txPacket(self, port: PortHandler, txpacket: list[int]) -> int:
        # a plain sync read: PARAMS are the start address (2), the length (2), the IDs
        is_sync = txpacket[7] == P.SYNC_READ
        self.group = frozenset(txpacket[12:-2]) if is_sync else frozenset()
        return super().txPacket(port, txpacket)

    @staticmethod
    def _refuse(port: PortHandler) -> int:
        port.unsettled = True  # the answer asked for may still come: drain it
        return COMM_RX_CORRUPT

    def txRxPacket(self, port: PortHandler, txpacket: list[int]) -> tuple[list[int], int, int]:
        self._asked = txpacket[4]
        try:
            rx, result, error = super().txRxPacket(port, txpacket)
        finally:
            self._asked = None
        if result != COMM_SUCCESS or rx is None or txpacket[4] == BROADCAST_ID:
            return rx, result, error
        inst = txpacket[7]
        if inst == P.PING:
            want = 3  # model number (2), firmware version
        elif inst == P.READ:
            want = txpacket[10] | (txpacket[11] << 8)
        else:
            want = 0
        if _params(rx) != want:
            return rx, self._refuse(port), 0
        return rx, result, error

    def readRx(self, port: PortHandler, dxl_id: int, length: int) -> tuple[list[int], int, int]:
        self._asked = dxl_id
        try:
            data, result, error = super().readRx(port, dxl_id, length)
        finally:
            self._asked = None
        if result == COMM_SUCCESS and _params(self._last) != length:
            return [], self._refuse(port), 0
        return data, result, error

    def fastSyncReadRx(
        self, port: PortHandler, dxl_id: int, length: int
    ) -> tuple[list[int], int, int]:
        data, result, error = super().fastSyncReadRx(port, dxl_id, length)
        # the records of ``length`` bytes in all (AlertSyncRead parses them by their
        # lengths): the first servo's error byte and the last one's CRC stand where a
        # servo's own status has its error and CRC, the rest are the parameters
        if result == COMM_SUCCESS and _params(self._last) != length - P.STATUS_TAIL:
            return [], self._refuse(port), 0
        return data, result, error


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
        record = n + P.FAST_RECORD_OVERHEAD
        raw, result, _ = self.ph.fastSyncReadRx(
            self.port, BROADCAST_ID, record * len(self.data_dict)
        )
        if result != COMM_SUCCESS:
            return result
        raw = bytes(raw)
        for k in range(len(self.data_dict)):
            part = raw[k * record : (k + 1) * record]
            if len(part) < n + 2 or part[1] not in self.data_dict:
                return COMM_RX_CORRUPT
            self.data_dict[part[1]] = bytearray(part[2 : 2 + n])
            self.errors[part[1]] = part[0]
        self.last_result = True
        return COMM_SUCCESS
