"""Protocol 2.0 packet code against the ROBOTIS e-Manual examples and dynamixel_sdk."""

from __future__ import annotations

import pytest
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from firmware_interface import protocol as P
from firmware_interface.bus import Bus

# (what, id, instruction, params, bytes on the wire) from the e-Manual's Protocol 2.0 page
EMANUAL = [
    ("ping", 1, P.PING, b"", "FF FF FD 00 01 03 00 01 19 4E"),
    ("ping status", 1, P.STATUS, bytes([0, 0x06, 0x04, 0x26]),
     "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D"),
    ("broadcast ping", 0xFE, P.PING, b"", "FF FF FD 00 FE 03 00 01 31 42"),
    ("read", 1, P.READ, bytes([0x84, 0, 4, 0]), "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"),
    ("read status", 1, P.STATUS, bytes([0, 0xA6, 0, 0, 0]),
     "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0"),
    ("write", 1, P.WRITE, bytes([0x74, 0, 0, 2, 0, 0]),
     "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"),
    ("write status", 1, P.STATUS, bytes([0]), "FF FF FD 00 01 04 00 55 00 A1 0C"),
    ("reboot", 1, P.REBOOT, b"", "FF FF FD 00 01 03 00 08 2F 4E"),
    ("sync read", 0xFE, P.SYNC_READ, bytes([0x84, 0, 4, 0, 1, 2]),
     "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"),
    ("sync write", 0xFE, P.SYNC_WRITE,
     bytes([0x74, 0, 4, 0, 1, 0x96, 0, 0, 0, 2, 0xAA, 0, 0, 0]),
     "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"),
]  # fmt: skip


@pytest.mark.parametrize("case", EMANUAL, ids=[c[0] for c in EMANUAL])
def test_emanual_examples_build_and_parse(case):
    _, dxl_id, inst, params, wire = case
    raw = bytes.fromhex(wire)
    assert P.build(dxl_id, inst, params) == raw
    pkt = P.parse(raw)
    assert (pkt.id, pkt.instruction, pkt.params) == (dxl_id, inst, params)


def test_crc_is_the_sdk_crc_on_random_data():
    import random

    sdk = PacketHandler(2.0)
    rng = random.Random(1)
    for n in (0, 1, 7, 64, 300):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert P.crc16(data) == sdk.updateCRC(0, list(data), len(data))


class _Wire:
    """A port object for the SDK's packet handler: records writes, serves reads."""

    def __init__(self, incoming: bytes = b"") -> None:
        self.written = b""
        self.incoming = bytearray(incoming)
        self.is_using = False
        self.baudrate = 4_000_000

    def clearPort(self) -> None:
        pass

    def writePort(self, packet) -> int:
        self.written += bytes(packet)
        return len(packet)

    def readPort(self, length: int) -> bytes:
        out = bytes(self.incoming[:length])
        del self.incoming[:length]
        return out

    def setPacketTimeout(self, n) -> None:
        pass

    def setPacketTimeoutMillis(self, ms) -> None:
        pass

    def isPacketTimeout(self) -> bool:
        return True

    def getBaudRate(self) -> int:
        return self.baudrate


payload_bytes = st.binary(min_size=0, max_size=40)
with_headers = st.lists(
    st.sampled_from([b"\xff", b"\xfd", b"\xff\xff\xfd", b"\x00", b"\x55"]), max_size=12
).map(b"".join)


def _has_header(b: bytes) -> bool:
    return b"\xff\xff\xfd" in b


@settings(max_examples=200, deadline=None)
@given(data=st.one_of(payload_bytes, with_headers), address=st.integers(0, 146))
def test_sdk_writes_and_we_parse(data, address):
    """The SDK builds a WRITE; our parser recovers it, and our builder emits its bytes."""
    sdk = PacketHandler(2.0)
    wire = _Wire()
    sdk.writeTxOnly(wire, 7, address, len(data), list(data))
    params = address.to_bytes(2, "little") + data
    if _has_header(params):
        # dynamixel_sdk 4.1 computes the stuffed packet but txPacket discards it when the
        # length changes (addStuffing rebinds its argument): such packets go out unstuffed
        assert wire.written[5] | (wire.written[6] << 8) == len(params) + 3
        return
    pkt = P.parse(wire.written)
    assert pkt.id == 7 and pkt.instruction == P.WRITE and pkt.params == params
    assert P.build(7, P.WRITE, params) == wire.written


@settings(max_examples=300, deadline=None)
@given(data=st.one_of(payload_bytes, with_headers))
def test_stuffing_matches_the_sdk_both_ways(data):
    """Our stuffing equals the SDK's addStuffing; the SDK's removeStuffing undoes ours."""
    sdk = PacketHandler(2.0)
    body = bytes([P.WRITE]) + data
    n = len(body) + 2
    unstuffed = list(P.HEADER + bytes([1, n & 0xFF, n >> 8]) + body + b"\0\0")
    sdk_stuffed = bytes(sdk.addStuffing(unstuffed))
    ours = P.build(1, P.WRITE, data)
    assert ours[:-2] == sdk_stuffed[:-2]  # the SDK fills in the CRC afterwards
    assert P.unstuff(P.stuff(body, bytes([n & 0xFF, n >> 8])), bytes([n & 0xFF, n >> 8])) == body
    if body.count(b"\xff\xff\xfd") <= 1 and ours.count(b"\xfd\xfd") <= 1:
        # (the SDK's removeStuffing edits in place and misreads a second FD FD after a run)
        back = sdk.removeStuffing(list(ours))
        m = back[5] | (back[6] << 8)
        assert bytes(back[7 : 7 + m - 2]) == body


@settings(max_examples=200, deadline=None)
@given(data=st.one_of(payload_bytes.filter(len), with_headers.filter(len)))
def test_we_build_status_and_the_sdk_parses(data):
    """Our status packet (stuffed) is read by the SDK's readRx with the same data."""
    sdk = PacketHandler(2.0)
    raw = P.status(9, 0x80, data)
    # (the SDK's removeStuffing edits in place and misreads a second FD FD after a run)
    assume(raw.count(b"\xfd\xfd") <= 1)
    wire = _Wire(raw)
    got, result, error = sdk.readRx(wire, 9, len(data))
    assert result == COMM_SUCCESS
    assert bytes(got) == data and error == 0x80


def test_sdk_sync_write_is_applied_by_the_bus():
    bus = Bus({1: 100, 2: 200, 3: 300})
    for s in bus.servos.values():
        assert s.write(11, b"\x05") == 0  # current-based position: multi-turn goals
        s.write(64, b"\x01")
    sdk = PacketHandler(2.0)
    wire = _Wire()
    g = GroupSyncWrite(wire, sdk, 116, 4)
    for i, v in ((1, 1234), (2, -5), (3, 1_048_575)):
        g.addParam(i, list(v.to_bytes(4, "little", signed=True)))
    assert g.txPacket() == COMM_SUCCESS
    assert bus.feed(wire.written, 1.0) == []  # a broadcast write has no reply
    assert [bus.servos[i].get("goal_position") for i in (1, 2, 3)] == [1234, -5, 1_048_575]


@pytest.mark.parametrize("fast", [True, False])
def test_bus_sync_read_replies_are_parsed_by_the_sdk(fast):
    bus = Bus({1: 2048, 4: -70000, 9: 0x3FDFFFF})
    for i in (4, 9):  # multi-turn counts (turns counted since power-up, which starts within one)
        bus.servos[i].pos = bus.servos[i].physical
        bus.servos[i].origin = 0.0
        bus.servos[i].advance(1e-3)
    sdk = PacketHandler(2.0)
    wire = _Wire()
    g = GroupSyncRead(wire, sdk, 132, 4)
    for i in (1, 4, 9):
        g.addParam(i)
    assert (g.fastSyncReadTxPacket() if fast else g.txPacket()) == COMM_SUCCESS
    replies = bus.feed(wire.written, 0.0)
    assert len(replies) == (1 if fast else 3)
    wire.incoming += b"".join(raw for _, raw in replies)
    assert (g.fastSyncReadRxPacket() if fast else g.rxPacket()) == COMM_SUCCESS
    got = [g.getData(i, 132, 4) for i in (1, 4, 9)]
    assert got == [2048, (-70000) & 0xFFFFFFFF, 0x3FDFFFF]


def test_a_corrupted_packet_fails_its_crc_and_the_servo_says_so():
    raw = bytearray(P.build(1, P.READ, bytes([0x84, 0, 4, 0])))
    raw[9] ^= 0x10
    with pytest.raises(P.CrcMismatch):
        P.parse(bytes(raw))
    bus = Bus({1: 0})
    ((_, reply),) = bus.feed(bytes(raw), 0.0)
    assert P.parse(reply).error == P.ERR_CRC
    assert bus.stats.crc_errors == 1


def test_wire_time_of_a_reply_delays_it_at_the_baud_rate():
    bus = Bus({1: 0}, baud=1_000_000)
    bus.servos[1].write(9, b"\x00")  # return delay 0
    req = P.build(1, P.READ, bytes([0x84, 0, 4, 0]))
    ((due, reply),) = bus.feed(req, 10.0)
    expected = 10.0 + (len(req) + len(reply)) * 10 / 1_000_000
    assert due == pytest.approx(expected, abs=1e-9)
    bus.servos[1].write(9, b"\x0a")  # 20 us return delay
    ((due2, _),) = bus.feed(req, 20.0)
    assert due2 - 20.0 == pytest.approx(expected - 10.0 + 20e-6, abs=1e-9)
