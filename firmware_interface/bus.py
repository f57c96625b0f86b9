"""The emulated Protocol 2.0 bus: servos, instruction handling, wire timing, faults.

:class:`Bus` is transport-free: :meth:`Bus.feed` takes the bytes the host sent and the
time they arrived and returns the replies with the time each one's last byte leaves the
bus (the instruction's own bits at the baud rate, then per reply the Return Delay Time
and its bits, plus any injected latency). The emulator process writes them to the pty at
those times.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

from firmware_interface import protocol as P
from firmware_interface.control_table import ADDR, BAUD_RATES, BY_NAME, encode
from firmware_interface.faults import Fault
from firmware_interface.servo_dynamics import Plant
from firmware_interface.servo_model import ServoModel

ADVANCE_S = 0.0005  # servo state is integrated at least this finely [s]
_MODEL_NUMBER = BY_NAME["model_number"]
_MODEL_SPAN = slice(_MODEL_NUMBER.address, _MODEL_NUMBER.address + _MODEL_NUMBER.size)
"""Where a servo's control table holds its Model Number (a PING reply's first bytes)."""


@dataclass
class BusStats:
    """Counters of what the bus saw and did."""

    packets: dict[str, int] = field(default_factory=dict)
    crc_errors: int = 0
    dropped: int = 0
    corrupted: int = 0
    replies: int = 0


_NAMES = {P.PING: "ping", P.READ: "read", P.WRITE: "write", P.REBOOT: "reboot",
          P.SYNC_READ: "sync_read", P.SYNC_WRITE: "sync_write",
          P.FAST_SYNC_READ: "fast_sync_read"}  # fmt: skip


class Bus:
    """Servos on one bus.

    Args:
        positions: Servo ID -> initial present position [ticks].
        baud: Bus baud rate [bit/s] (the servos' Baud Rate register is set to match).
        seed: Seed of the fault dice.
        now: Start time [s].
        stops: Servo ID -> hard stops ``(low, high)`` [ticks] (the rail's and the stage's).
        plants: Servo ID -> its output shaft (default: an unloaded servo).
    """

    def __init__(
        self,
        positions: dict[int, int],
        baud: int = 4_000_000,
        seed: int = 0,
        now: float = 0.0,
        stops: dict[int, tuple[float, float]] | None = None,
        plants: dict[int, Plant] | None = None,
    ) -> None:
        code = {v: k for k, v in BAUD_RATES.items()}.get(baud)
        if code is None:
            raise ValueError(f"baud {baud} is not a Dynamixel baud rate")
        self.baud = baud
        self.servos: dict[int, ServoModel] = {}
        for dxl_id, pos in positions.items():
            s = ServoModel(dxl_id, pos, now, (stops or {}).get(dxl_id), (plants or {}).get(dxl_id))
            s.table[ADDR["baud_rate"]] = code
            self.servos[dxl_id] = s
        self.missing: set[int] = set()
        self.corrupt = 0.0
        self.drop = 0.0
        self.latency = 0.0
        self.rng = random.Random(seed)
        self.stats = BusStats()
        self.buffer = bytearray()
        self.free_at = now  # when the bus is idle again [s]
        self._advanced = now

    # -- faults ------------------------------------------------------------------------------
    def apply(self, fault: Fault) -> None:
        """Inject a fault (see :mod:`firmware_interface.faults`)."""
        if fault.kind == "missing":
            self.missing.add(int(fault.id))
        elif fault.kind == "corrupt":
            self.corrupt = fault.value
        elif fault.kind == "drop":
            self.drop = fault.value
        elif fault.kind == "latency":
            self.latency = fault.value
        elif fault.kind == "error":
            self.servos[int(fault.id)].set_error(str(fault.bit))
        elif fault.kind == "block":
            self.servos[int(fault.id)].blocked = True
        elif fault.kind == "model":  # a read-only EEPROM register: kept over reboots
            self.servos[int(fault.id)].table[_MODEL_SPAN] = encode(_MODEL_NUMBER, int(fault.value))

    def power_cycle(self) -> None:
        """Every servo off and on again (EEPROM kept, multi-turn counts lost)."""
        for s in self.servos.values():
            s.power_cycle()

    def clear_faults(self) -> None:
        """Remove the bus faults (missing IDs, corruption, drops, latency, blocks)."""
        self.missing.clear()
        self.corrupt = self.drop = self.latency = 0.0
        for s in self.servos.values():
            s.blocked = False

    def present(self, dxl_id: int) -> ServoModel | None:
        if dxl_id in self.missing:
            return None
        return self.servos.get(dxl_id)

    # -- time --------------------------------------------------------------------------------
    def advance(self, now: float, *, force: bool = False) -> None:
        """Integrate every servo to ``now`` (at most every ``ADVANCE_S`` unless forced)."""
        if not force and now - self._advanced < ADVANCE_S:
            return
        self._advanced = now
        for s in self.servos.values():
            s.advance(now)

    def _wire(self, n: int) -> float:
        return P.wire_time(n, self.baud)

    # -- packets -----------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        """Bytes from the host; returns ``(due time, reply bytes)`` in order."""
        self.buffer.extend(data)
        out: list[tuple[float, bytes]] = []
        while True:
            try:
                pkt, used = P.split(self.buffer)
            except P.CrcMismatch as exc:
                self.stats.crc_errors += 1
                del self.buffer[: exc.size]
                end = max(self.free_at, now) + self._wire(exc.size)
                self.free_at = end
                s = self.present(exc.id)
                if s is not None and exc.id != P.BROADCAST_ID:
                    out += self._schedule(end, [(s, P.status(s.id, P.ERR_CRC | s.alert()))])
                continue
            if pkt is None:
                del self.buffer[:used]
                return out
            del self.buffer[:used]
            end = max(self.free_at, now) + self._wire(used)
            self.free_at = end
            self.advance(end)
            name = _NAMES.get(pkt.instruction, f"0x{pkt.instruction:02x}")
            self.stats.packets[name] = self.stats.packets.get(name, 0) + 1
            out += self._schedule(end, self._handle(pkt, end))

    def _schedule(
        self, end: float, replies: list[tuple[ServoModel, bytes]]
    ) -> list[tuple[float, bytes]]:
        out = []
        t = end
        for servo, raw in replies:
            t += servo.return_delay + self._wire(len(raw))
            if self.drop and self.rng.random() < self.drop:
                self.stats.dropped += 1
                continue
            if self.corrupt and self.rng.random() < self.corrupt:
                b = bytearray(raw)
                b[self.rng.randrange(7, len(b))] ^= 1 << self.rng.randrange(8)
                raw = bytes(b)
                self.stats.corrupted += 1
            self.stats.replies += 1
            out.append((t + self.latency, raw))
        self.free_at = max(self.free_at, t)
        return out

    def _targets(self, pkt: P.Packet) -> list[ServoModel]:
        if pkt.id == P.BROADCAST_ID:
            return [s for i, s in self.servos.items() if i not in self.missing]
        s = self.present(pkt.id)
        return [s] if s is not None else []

    def _handle(self, pkt: P.Packet, now: float) -> list[tuple[ServoModel, bytes]]:
        inst, prm = pkt.instruction, pkt.params
        if inst == P.SYNC_WRITE:
            self._sync_write(prm, now)
            return []
        if inst in (P.SYNC_READ, P.FAST_SYNC_READ):
            return self._sync_read(prm, now, fast=inst == P.FAST_SYNC_READ)
        targets = self._targets(pkt)
        for s in targets:
            s.heard(now)
        replies = []
        for s in targets:
            raw = self._unicast(s, inst, prm)
            if raw is not None and (pkt.id != P.BROADCAST_ID or inst == P.PING):
                replies.append((s, raw))
        return replies

    def _unicast(self, s: ServoModel, inst: int, prm: bytes) -> bytes | None:
        if inst == P.PING:  # Model Number and Firmware Version, from the control table
            model = bytes(s.table[_MODEL_SPAN])
            return P.status(s.id, s.alert(), model + bytes([s.table[ADDR["firmware_version"]]]))
        if inst == P.READ:
            if len(prm) != 4:
                return P.status(s.id, P.ERR_DATA_LENGTH | s.alert())
            addr, n = int.from_bytes(prm[:2], "little"), int.from_bytes(prm[2:], "little")
            err, data = s.read(addr, n)
            return P.status(s.id, err, data)
        if inst == P.WRITE:
            if len(prm) < 3:
                return P.status(s.id, P.ERR_DATA_LENGTH | s.alert())
            err = s.write(int.from_bytes(prm[:2], "little"), prm[2:])
            return P.status(s.id, err)
        if inst == P.REBOOT:
            s.reboot()
            return P.status(s.id, 0)
        return P.status(s.id, P.ERR_INSTRUCTION | s.alert())

    def _sync_write(self, prm: bytes, now: float) -> None:
        if len(prm) < 4:
            return
        addr, n = int.from_bytes(prm[:2], "little"), int.from_bytes(prm[2:4], "little")
        body = prm[4:]
        for k in range(0, len(body) - n, n + 1):
            s = self.present(body[k])
            if s is not None:
                s.heard(now)
                s.write(addr, body[k + 1 : k + 1 + n])

    def _sync_read(self, prm: bytes, now: float, fast: bool) -> list[tuple[ServoModel, bytes]]:
        if len(prm) < 5:
            return []
        addr, n = int.from_bytes(prm[:2], "little"), int.from_bytes(prm[2:4], "little")
        ids = list(prm[4:])
        for i in ids:
            s = self.present(i)
            if s is not None:
                s.heard(now)
        if not fast:
            out = []
            for i in ids:
                s = self.present(i)
                if s is not None:
                    err, data = s.read(addr, n)
                    out.append((s, P.status(s.id, err, data)))
            return out
        return self._fast_reply(ids, addr, n)

    def _fast_reply(self, ids: list[int], addr: int, n: int) -> list[tuple[ServoModel, bytes]]:
        """One status packet (ID FE) to which each servo appends ERR, ID, data and a CRC.

        Each servo's CRC is the running CRC of the packet so far, so the last one is the
        packet's CRC. A missing servo breaks the chain: the packet stops before it.
        """
        length = (n + P.FAST_RECORD_OVERHEAD) * len(ids) + 1  # 1: the instruction
        pkt = bytearray(P.HEADER + bytes([P.BROADCAST_ID, length & 0xFF, length >> 8, P.STATUS]))
        first: ServoModel | None = None
        c = P.crc16(pkt)
        for i in ids:
            s = self.present(i)
            if s is None:
                break
            first = first or s
            err, data = s.read(addr, n)
            part = bytes([err, i]) + data
            c = P.crc16(part, c)
            crc = bytes([c & 0xFF, c >> 8])
            c = P.crc16(crc, c)  # the next servo continues the CRC over these bytes too
            pkt += part + crc
        if first is None:
            return []
        return [(first, bytes(pkt))]
