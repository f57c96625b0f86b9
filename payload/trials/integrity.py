"""Integrity of a recording's bytes: every record of the data section walked, every chunk's
CRC checked, so a damaged file is named (file, channels, steps, bytes) and never read as if
nothing were wrong.

:func:`clean_records` turns an MCAP file's bytes into a stream holding only what the
reader uses (the records of every chunk, decompressed and CRC-checked, and the metadata
records, each checked against the CRC the recorder stores in it), ending at the data
section's end: the summary section, which only repeats the data section, is not read. A
file cut short by a kill (no ``DataEnd``, a torn last record) reads up to its last whole
record, as before; a closed file whose records do not chain to its footer, a record type
the recorder never writes, a chunk whose CRC or compression fails, a metadata record whose
CRC fails, or steps missing between two good chunks raise :class:`DamagedRecordingError`
(a :class:`RecordingError`) naming what is damaged.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from mcap.opcode import Opcode

from payload.trials.records import STEP_TOPIC, DamagedRecordingError, RecordingError

MAGIC = b"\x89MCAP0\r\n"
"""The MCAP magic at both ends of a file."""
META_CRC_KEY = "_crc32"
"""The metadata key holding the CRC-32 of a metadata record's other items."""
RECORD_HEADER = 9
"""Bytes before a record's fields: its opcode (1) and the fields' length (u64)."""

_KNOWN = frozenset(range(0x01, 0x11))
"""Every record type of MCAP version 0."""
_PASSED = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA)
"""Records outside chunks that the reader uses (the recorder keeps schemas and channels
inside its chunks; these are the summary's repeats and the metadata)."""


def metadata_crc(items: dict[str, str]) -> str:
    """CRC-32 (8 hex digits) of a metadata record's items, in a canonical order.

    Args:
        items: The record's key/value strings, without :data:`META_CRC_KEY`.
    """
    text = json.dumps(sorted(items.items()), separators=(",", ":"))
    return f"{zlib.crc32(text.encode('utf-8')):08x}"


@dataclass
class _Chunk:
    start: int
    end: int
    channels: set[int] = field(default_factory=set)
    steps: tuple[int, int] | None = None  # first and last step sequence, when readable
    damage: str | None = None


@dataclass
class CleanRecords:
    """What :func:`clean_records` found.

    Attributes:
        data: ``MAGIC`` followed by the records the reader uses, in file order.
        complete: The file was closed properly (its records chain to the footer).
    """

    data: bytes
    complete: bool


def _u32(data: bytes, pos: int) -> int:
    return struct.unpack_from("<I", data, pos)[0]


def _u64(data: bytes, pos: int) -> int:
    return struct.unpack_from("<Q", data, pos)[0]


def record_head(data: bytes, pos: int) -> tuple[int, int]:
    """The opcode and the fields' length of the record at ``pos`` (its first
    :data:`RECORD_HEADER` bytes; the caller checks that they are there)."""
    return data[pos], _u64(data, pos + 1)


def _open_chunk(body: bytes) -> bytes:
    """The records of a chunk record's body, decompressed and checked against its CRC.

    Raises:
        ValueError: Malformed body, unknown compression, failed decompression or CRC.
    """
    size, crc = _u64(body, 16), _u32(body, 24)
    n = _u32(body, 28)
    compression = body[32 : 32 + n].decode("ascii")
    pos = 32 + n
    length = _u64(body, pos)
    records = body[pos + 8 : pos + 8 + length]
    if len(records) != length or pos + 8 + length != len(body):
        raise ValueError("its lengths do not add up")
    if compression == "zstd":
        import zstandard

        try:  # streamed: a corrupt size field must not make it allocate that much first
            raw = zstandard.ZstdDecompressor().decompressobj().decompress(records)
        except zstandard.ZstdError as exc:
            raise ValueError(f"zstd: {exc}") from None
    elif compression == "":
        raw = records
    else:
        raise ValueError(f"compression {compression!r} is not one the recorder writes")
    if len(raw) != size:
        raise ValueError(f"{len(raw)} bytes decompressed where it says {size}")
    if crc and zlib.crc32(raw) != crc:
        raise ValueError("CRC mismatch")
    return raw


def _scan_chunk(raw: bytes, chunk: _Chunk, step_channels: set[int], names: dict[int, str]):
    """Channel ids, channel names and the step sequence range of a good chunk's records."""
    pos, seqs = 0, []
    while pos + RECORD_HEADER <= len(raw):
        op, length = record_head(raw, pos)
        body = raw[pos + RECORD_HEADER : pos + RECORD_HEADER + length]
        if op == Opcode.MESSAGE and len(body) >= 6:
            cid, seq = struct.unpack_from("<HI", body, 0)
            chunk.channels.add(cid)
            if cid in step_channels:
                seqs.append(seq)
        elif op == Opcode.CHANNEL and len(body) >= 4:
            cid = struct.unpack_from("<H", body, 0)[0]
            n = _u32(body, 4)
            names[cid] = body[8 : 8 + n].decode("utf-8", "replace")
            if names[cid] == STEP_TOPIC:
                step_channels.add(cid)
        pos += RECORD_HEADER + length
    if seqs:
        chunk.steps = (min(seqs), max(seqs))


def _check_metadata(body: bytes) -> None:
    """Check a metadata record's stored CRC (records without one are older files).

    Raises:
        ValueError: Malformed, or the CRC does not match.
    """
    n = _u32(body, 0)
    pos = 4 + n
    size = _u32(body, pos)
    pos += 4
    end = pos + size
    items: dict[str, str] = {}
    while pos < end:
        k = _u32(body, pos)
        key = body[pos + 4 : pos + 4 + k].decode("utf-8")
        pos += 4 + k
        v = _u32(body, pos)
        items[key] = body[pos + 4 : pos + 4 + v].decode("utf-8")
        pos += 4 + v
    if pos != end or end != len(body):
        raise ValueError("its lengths do not add up")
    stored = items.pop(META_CRC_KEY, None)
    if stored is not None and stored != metadata_crc(items):
        raise ValueError("CRC mismatch")


def clean_records(data: bytes, path: str | Path) -> CleanRecords:
    """The records of a recording the reader uses, every chunk and metadata CRC checked.

    Args:
        data: The file's bytes.
        path: The file, for messages.

    Raises:
        RecordingError: Empty (or cut inside the magic): nothing was ever written.
        DamagedRecordingError: Not an MCAP file, or damaged (one line: the file, the
            channels and steps of a damaged chunk, or the byte range where the damage lies).
    """
    if MAGIC.startswith(data):  # empty, or cut inside the magic: a recorder killed
        raise RecordingError(  # before its first write left nothing to read, not damage
            f"{path}: holds no record ({len(data)} bytes): the recording was cut short "
            "before its first write"
        )
    if not data.startswith(MAGIC):
        raise DamagedRecordingError(f"{path}: not an MCAP file (bad magic)")
    closed_file = len(data) >= 2 * len(MAGIC) and data.endswith(MAGIC)
    out = [MAGIC]
    chunks: list[_Chunk] = []
    names: dict[int, str] = {}
    step_channels: set[int] = set()
    pos, n, complete, last = len(MAGIC), len(data), False, None
    while pos + RECORD_HEADER <= n:
        op, length = record_head(data, pos)
        end = pos + RECORD_HEADER + length
        if op not in _KNOWN:
            _damaged(path, f"bytes {pos}-{n}: record type 0x{op:02x} is not MCAP's", chunks)
        if end > n:
            break  # a torn last record (a killed writer), or a damaged length: see below
        body = data[pos + RECORD_HEADER : end]
        if op == Opcode.CHUNK:
            chunk = _Chunk(pos, end)
            try:
                raw = _open_chunk(body)
            except (ValueError, struct.error, UnicodeDecodeError) as exc:
                chunk.damage = str(exc)
            else:
                _scan_chunk(raw, chunk, step_channels, names)
                out.append(raw)
            chunks.append(chunk)
        elif op == Opcode.MESSAGE_INDEX and chunks and len(body) >= 2:
            chunks[-1].channels.add(struct.unpack_from("<H", body, 0)[0])
        elif op in _PASSED:
            if op == Opcode.METADATA:
                try:
                    _check_metadata(body)
                except (ValueError, struct.error, UnicodeDecodeError) as exc:
                    _damaged(path, f"metadata at bytes {pos}-{end}: {exc}", chunks)
            out.append(data[pos:end])
        elif op == Opcode.DATA_END:
            last = end
            break
        pos = end
    if last is not None:  # the data section ended; closed if the footer's magic ends it
        complete = closed_file
    elif closed_file:
        _damaged(path, f"bytes {pos}-{n}: the records do not chain to the file's footer", chunks)
    _check_chunks(path, chunks, names, step_channels)
    return CleanRecords(b"".join(out), complete)


def _check_chunks(
    path: str | Path, chunks: list[_Chunk], names: dict[int, str], step_channels: set[int]
) -> None:
    """Raise on the first damaged chunk, or on steps missing between two good ones."""
    previous = -1
    for i, chunk in enumerate(chunks):
        if chunk.damage is None:
            if chunk.steps is not None:
                if chunk.steps[0] != previous + 1:
                    raise DamagedRecordingError(
                        f"{path}: {STEP_TOPIC}: steps {previous + 1}-{chunk.steps[0] - 1} "
                        f"missing before bytes {chunk.start}-{chunk.end}; the recording is "
                        "damaged"
                    )
                previous = chunk.steps[1]
            continue
        following = next((c.steps for c in chunks[i + 1 :] if c.steps is not None), None)
        steps = f"steps {previous + 1}-" + (f"{following[0] - 1}" if following else "end")
        ids = chunk.channels or _neighbour_channels(chunks, i)  # no message index: the
        topics = sorted(names.get(c, f"channel {c}") for c in ids)  # flush's channels
        where = ", ".join(topics) if topics else "its channels unreadable"
        raise DamagedRecordingError(
            f"{path}: {where}: {steps} (chunk at bytes {chunk.start}-{chunk.end}) damaged: "
            f"{chunk.damage}"
        )


def _neighbour_channels(chunks: list[_Chunk], i: int) -> set[int]:
    """The channels of the good chunks before and after chunk ``i`` (every flush writes a
    chunk of the channels active then)."""
    ids: set[int] = set()
    for side in (reversed(chunks[:i]), chunks[i + 1 :]):
        good = next((c for c in side if c.damage is None and c.channels), None)
        if good is not None:
            ids |= good.channels
    return ids


def _damaged(path: str | Path, what: str, chunks: list[_Chunk]) -> None:
    """Raise for damage outside a chunk, naming the steps read before it."""
    last = next((c.steps[1] for c in reversed(chunks) if c.steps is not None), None)
    after = f" (after step {last})" if last is not None else ""
    raise DamagedRecordingError(f"{path}: {what}{after}; the recording is damaged")
