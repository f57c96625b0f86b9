"""The serial port the driver gives ``dynamixel_sdk``."""

from __future__ import annotations

from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_CORRUPT,
    COMM_RX_FAIL,
    COMM_SUCCESS,
    GroupSyncRead,
    PortHandler,
    Protocol2PacketHandler,
)


class SdkPort(PortHandler):
    """The SDK's PortHandler with the packet timeout's latency allowance configurable.

    The SDK assumes a USB adapter latency timer of 16 ms (``LATENCY_TIMER``) and waits
    twice that plus the packet's bytes for a reply; a bus behind another latency (an
    adapter set to 1 ms, a busy host) sets its own.
    """

    def __init__(self, port_name: str, latency_timer_ms: float) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

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

    def rxPacket(self) -> int:
        """Plain sync read: one status packet per servo, its error byte kept."""
        self.last_result = False
        result = COMM_RX_FAIL
        for dxl_id in self.data_dict:
            data, result, error = self.ph.readRx(self.port, dxl_id, self.data_length)
            if result != COMM_SUCCESS:
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
