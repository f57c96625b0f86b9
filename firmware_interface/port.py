"""The serial port the driver gives ``dynamixel_sdk``."""

from __future__ import annotations

from dynamixel_sdk import PortHandler


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
