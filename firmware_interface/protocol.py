"""Dynamixel Protocol 2.0 packets: CRC-16, byte stuffing, building and parsing.

Packet layout (ROBOTIS e-Manual, Protocol 2.0)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS ... | CRC_L CRC_H

``LEN`` counts the instruction, the (stuffed) parameters and the CRC. A status packet
has instruction ``0x55`` followed by an error byte and its parameters. The CRC is the
CRC-16 with polynomial 0x8005 (not reflected, initial value 0) over every byte from the
header to the last parameter, as transmitted (after stuffing). Byte stuffing inserts an
``FD`` after any ``FF FF FD`` in the instruction and parameter area so that no header
appears inside a packet.

This module is the emulator's own implementation; the tests check it against
``dynamixel_sdk`` in both directions and against byte strings from the e-Manual.
"""

from __future__ import annotations

from dataclasses import dataclass

from payload.errors import PayloadError

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC

PING = 0x01
READ = 0x02
WRITE = 0x03
REG_WRITE = 0x04
ACTION = 0x05
REBOOT = 0x08
STATUS = 0x55
SYNC_READ = 0x82
SYNC_WRITE = 0x83
FAST_SYNC_READ = 0x8A
BULK_READ = 0x92
BULK_WRITE = 0x93

# status error byte: bit 7 is the hardware alert, the low 7 bits an error number
ERR_RESULT_FAIL = 1
ERR_INSTRUCTION = 2
ERR_CRC = 3
ERR_DATA_RANGE = 4
ERR_DATA_LENGTH = 5
ERR_DATA_LIMIT = 6
ERR_ACCESS = 7
ALERT = 0x80

PACKET_HEAD = len(HEADER) + 4
"""A packet's bytes before its parameters (a status packet's: before its error byte): the
header, the ID, ``LEN`` (2) and the instruction."""
STATUS_TAIL = 3
"""A status packet's bytes besides its instruction and parameters that ``LEN`` counts:
its error byte and CRC (a fast sync read's reply: the first record's error byte and the
last record's CRC stand there)."""
FAST_RECORD_OVERHEAD = 4
"""A fast sync read reply's bytes per servo besides its data: error byte, ID and CRC."""


class ProtocolError(PayloadError):
    """Bytes that are not a valid Protocol 2.0 packet."""


def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return tuple(table)


_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 (polynomial 0x8005, MSB first) of ``data``, continuing from ``crc``."""
    t = _TABLE
    for b in data:
        crc = ((crc << 8) ^ t[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes, before: bytes = b"") -> bytes:
    """Byte-stuff the instruction and parameter area ``body``.

    Args:
        body: Instruction and parameters, unstuffed.
        before: The two bytes sent just before ``body`` (the length field), which can
            complete an ``FF FF FD`` run that starts inside them.
    """
    src = (bytes(before[-2:]).rjust(2, b"\x00")) + bytes(body)
    out = bytearray()
    for i in range(2, len(src)):
        b = src[i]
        out.append(b)
        if b == 0xFD and src[i - 1] == 0xFF and src[i - 2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes, before: bytes = b"") -> bytes:
    """Undo :func:`stuff` (drop the ``FD`` inserted after every ``FF FF FD``)."""
    src = (bytes(before[-2:]).rjust(2, b"\x00")) + bytes(body)
    out = bytearray()
    i = 2
    while i < len(src):
        b = src[i]
        out.append(b)
        if b == 0xFD and src[i - 1] == 0xFF and src[i - 2] == 0xFF and i + 1 < len(src):
            if src[i + 1] == 0xFD:
                i += 1  # the stuffed byte
        i += 1
    return bytes(out)


def build(dxl_id: int, instruction: int, params: bytes = b"", *, stuffing: bool = True) -> bytes:
    """One packet (instruction or status) with stuffing, length and CRC.

    Args:
        dxl_id: Servo ID (``BROADCAST_ID`` for a broadcast; a status packet carries the
            replying servo's ID).
        instruction: Instruction byte (``STATUS`` for a status packet).
        params: Parameters after the instruction (a status packet's start with its error
            byte), unstuffed.
        stuffing: Apply byte stuffing (a fast sync read reply is sent unstuffed, as the
            SDK parses it).
    """
    if not 0 <= dxl_id <= 0xFF:
        raise ProtocolError(f"ID {dxl_id} is outside 0..255")
    body = bytes([instruction]) + bytes(params)
    n0 = len(body) + 2
    if stuffing:
        # like the SDK: stuffing looks back into the unstuffed length field
        body = stuff(body, bytes([n0 & 0xFF, n0 >> 8]))
    n = len(body) + 2
    pkt = HEADER + bytes([dxl_id, n & 0xFF, n >> 8]) + body
    c = crc16(pkt)
    return pkt + bytes([c & 0xFF, c >> 8])


def status(dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A status packet from servo ``dxl_id``."""
    return build(dxl_id, STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A parsed packet.

    Attributes:
        id: ID byte.
        instruction: Instruction byte (``STATUS`` for a status packet).
        params: Parameters after the instruction, unstuffed (a status packet's start with
            the error byte).
    """

    id: int
    instruction: int
    params: bytes

    @property
    def error(self) -> int:
        """Error byte of a status packet."""
        return self.params[0] if self.instruction == STATUS and self.params else 0

    @property
    def data(self) -> bytes:
        """A status packet's parameters after the error byte."""
        return self.params[1:] if self.instruction == STATUS else self.params


class CrcMismatch(ProtocolError):
    """A complete packet whose CRC does not match (the ID is known)."""

    def __init__(self, dxl_id: int, instruction: int, size: int) -> None:
        self.id = dxl_id
        self.instruction = instruction
        self.size = size
        super().__init__(f"CRC mismatch in a packet for ID {dxl_id}")


def split(buffer: bytes | bytearray) -> tuple[Packet | None, int]:
    """Find the first complete packet in ``buffer``.

    Returns:
        (packet or None, number of bytes consumed). With no complete packet yet the
        consumed count only skips bytes before a possible header.

    Raises:
        CrcMismatch: A complete packet failed its CRC (``size`` bytes to drop).
    """
    start = bytes(buffer).find(HEADER[:3])
    while start >= 0 and start + 3 < len(buffer) and buffer[start + 3] == 0xFD:
        start = bytes(buffer).find(HEADER[:3], start + 1)
    if start < 0:
        keep = 2 if buffer[-2:] == b"\xff\xff" else (1 if buffer[-1:] == b"\xff" else 0)
        return None, len(buffer) - keep
    if len(buffer) < start + 7:
        return None, start
    if buffer[start + 3] != 0x00:
        return None, start + 1
    n = buffer[start + 5] | (buffer[start + 6] << 8)
    end = start + 7 + n
    if n < 3 or n > 1024:
        return None, start + 1
    if len(buffer) < end:
        return None, start
    pkt = bytes(buffer[start:end])
    dxl_id, inst = pkt[4], pkt[7]
    if crc16(pkt[:-2]) != (pkt[-2] | (pkt[-1] << 8)):
        raise CrcMismatch(dxl_id, inst, end)
    body = unstuff(pkt[7:-2], pkt[5:7])
    return Packet(dxl_id, body[0], body[1:]), end


def parse(data: bytes) -> Packet:
    """Parse exactly one packet.

    Raises:
        ProtocolError: Incomplete, trailing bytes, or a CRC mismatch.
    """
    pkt, used = split(data)
    if pkt is None:
        raise ProtocolError(f"no complete packet in {data.hex(' ')}")
    if used != len(data):
        raise ProtocolError(f"{len(data) - used} byte(s) after the packet")
    return pkt


def wire_time(n_bytes: int, baud: int) -> float:
    """Time to send ``n_bytes`` on the bus (8N1: 10 bits per byte) [s]."""
    return n_bytes * 10.0 / baud


__all__ = [
    "BROADCAST_ID",
    "FAST_RECORD_OVERHEAD",
    "FAST_SYNC_READ",
    "PACKET_HEAD",
    "PING",
    "READ",
    "REBOOT",
    "STATUS",
    "STATUS_TAIL",
    "SYNC_READ",
    "SYNC_WRITE",
    "WRITE",
    "CrcMismatch",
    "Packet",
    "ProtocolError",
    "build",
    "crc16",
    "parse",
    "split",
    "status",
    "stuff",
    "unstuff",
    "wire_time",
]
