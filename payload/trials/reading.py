"""Reading trial recordings (:func:`read_recording`), complete or cut short by a crash.

The format is described in :mod:`payload.trials.records`.
"""

from __future__ import annotations

import io
import json
import logging
import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf.message import DecodeError
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from payload.schema import CAP_STOPPED, ENDED_BY_CAP
from payload.trials import codec
from payload.trials.integrity import (
    MAGIC,
    META_CRC_KEY,
    RECORD_HEADER,
    clean_records,
    record_head,
)
from payload.trials.records import (
    FIELD_SPECS,
    HANDS_TOPIC,
    META_NAME,
    SCHEMA_VERSION,
    STEP_TOPIC,
    DamagedRecordingError,
    RecordingError,
    StepRecord,
)
from payload.trials.stepcheck import StepError, check_step

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Recording:
    """A recording as numpy arrays, one row per step (field meanings: :class:`StepRecord`).

    Attributes:
        path: The file read (``None`` for an in-memory recording).
        meta: Merged trial metadata.
        complete: ``True`` if the file was closed properly (has its footer); ``False`` for
            a recording cut short (e.g. a killed process).
        seq: Step counters, shape (N,).
        wall_time: Wall clock at write, shape (N,) [s since the Unix epoch].
        t: Shape (N,) [s]. phase: shape (N,) str. left_joints/right_joints: (N, 25, 3).
        left_tracked/right_tracked/contact: (N,) bool. q_left/q_right: (N, 8).
        rail_cmd/deploy_cmd/deploy_meas: (N,). twist_cmd/astrobee_twist: (N, 6).
        q_cmd/q_meas: (N, 17). astrobee_pos/ctb_pos: (N, 3). astrobee_quat/ctb_quat: (N, 4).
        ctb_module: (N,) str.
    """

    path: Path | None
    meta: dict[str, Any]
    complete: bool
    seq: np.ndarray
    wall_time: np.ndarray
    t: np.ndarray
    phase: np.ndarray
    left_joints: np.ndarray
    right_joints: np.ndarray
    left_tracked: np.ndarray
    right_tracked: np.ndarray
    q_left: np.ndarray
    q_right: np.ndarray
    rail_cmd: np.ndarray
    twist_cmd: np.ndarray
    q_cmd: np.ndarray
    deploy_cmd: np.ndarray
    q_meas: np.ndarray
    deploy_meas: np.ndarray
    astrobee_pos: np.ndarray
    astrobee_quat: np.ndarray
    astrobee_twist: np.ndarray
    ctb_pos: np.ndarray
    ctb_quat: np.ndarray
    contact: np.ndarray
    ctb_module: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def rate_hz(self) -> float:
        """Median step rate [Hz] (NaN with fewer than two steps)."""
        if len(self) < 2:
            return math.nan
        return float(1.0 / np.median(np.diff(self.t)))

    @staticmethod
    def from_steps(
        steps: list[StepRecord],
        meta: dict[str, Any] | None = None,
        path: Path | None = None,
        complete: bool = True,
    ) -> Recording:
        """Build a recording from steps in memory (the same arrays the reader returns)."""
        return Recording.from_dicts([s.to_json_dict() for s in steps], meta, path, complete)

    @staticmethod
    def from_dicts(
        rows: list[dict[str, Any]],
        meta: dict[str, Any] | None = None,
        path: Path | None = None,
        complete: bool = True,
    ) -> Recording:
        """Build a recording from decoded step messages (``seq``/``wall_time`` optional)."""
        n = len(rows)
        cols: dict[str, np.ndarray] = {}
        for name, (shape, kind) in FIELD_SPECS.items():
            if isinstance(kind, tuple):
                cols[name] = np.array([r[name] for r in rows], dtype=object).astype(str)
                if n == 0:
                    cols[name] = np.zeros(0, dtype=str)
            elif kind == "bool":
                cols[name] = np.array([bool(r[name]) for r in rows], dtype=bool)
            else:
                values = [r[name] for r in rows]
                if kind == "float_nan" and not all(isinstance(v, np.ndarray) for v in values):
                    arr = np.array(values, dtype=object)  # JSON rows: null for NaN
                    arr = np.where(arr == None, np.nan, arr).astype(np.float64)  # noqa: E711
                else:  # numbers, or arrays as the typed decoder returns them (NaN kept)
                    arr = np.array(values, dtype=np.float64)
                cols[name] = arr.reshape((n, *shape))
        seq = np.array([r.get("seq", i) for i, r in enumerate(rows)], dtype=np.int64)
        wall = np.array([r.get("wall_time", math.nan) for r in rows], dtype=np.float64)
        return Recording(
            path=path, meta=dict(meta or {}), complete=complete, seq=seq, wall_time=wall, **cols
        )

    def step(self, i: int) -> StepRecord:
        """Step ``i`` as a :class:`StepRecord`."""
        return StepRecord(**{name: getattr(self, name)[i] for name in FIELD_SPECS})


def _decode_meta(items: dict[str, str], path: Path) -> dict[str, Any]:
    out = {}
    for key, value in items.items():
        if key == META_CRC_KEY:
            continue
        try:
            out[key] = json.loads(value)
        except ValueError:
            raise RecordingError(f"{path}: metadata {key!r}: expected JSON text") from None
    return out


def _check_version(channel: Channel, path: Path) -> None:
    """Refuse a step channel of a schema version newer than this reader's."""
    try:
        version = _channel_version(channel)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    if version > SCHEMA_VERSION:
        raise RecordingError(
            f"{path}: schema version {version} is newer than this reader's "
            f"({SCHEMA_VERSION}); update the workbench to read it"
        )


def _file_bytes(path: Path) -> bytes:
    """A recording's bytes (a missing or unreadable file: :class:`RecordingError`)."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such recording") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror})") from exc


def _read_file(
    path: Path,
) -> tuple[dict[int, Channel], dict[str, Any], list[dict[str, Any]], list[dict[str, Any]], bool]:
    """Channels, merged metadata, step rows, hand samples and completeness of a file."""
    data = _file_bytes(path)
    records = clean_records(data, path)
    complete = records.complete
    stream: Iterable[McapRecord] | None = _used_records(records.data)
    if stream is None:  # anything unusual: the general reader, and its errors
        stream = StreamReader(io.BytesIO(records.data)).records
    channels: dict[int, Channel] = {}
    meta: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    hands: dict[int, dict[str, Any]] = {}
    samples: list[dict[str, Any]] = []
    step_codec = codec.StepCodec()
    try:
        for record in stream:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    continue
                if channel.topic == STEP_TOPIC:
                    if not rows:
                        _check_version(channel, path)
                    if channel.message_encoding == "json":  # schema version 1
                        if not rows:
                            log.warning(
                                "%s: schema version 1 (JSON steps), read as it is; "
                                "`payload trials convert DIR` rewrites it compactly",
                                path,
                            )
                        rows.append(json.loads(record.data))
                    else:
                        rows.append(step_codec.decode_step(record.data, hands.get))
                elif channel.topic == HANDS_TOPIC:
                    sample = step_codec.decode_hands(record.data)
                    hands[sample["seq"]] = sample
                    samples.append(sample)
            elif isinstance(record, Metadata) and record.name == META_NAME:
                meta.update(_decode_meta(record.metadata, path))
    except EndOfFile:
        pass  # the complete prefix of a cut-short file ends exactly here
    except (McapError, ValueError, DecodeError) as exc:  # JSON errors are ValueErrors too
        where = (
            f"step {len(rows)}"
            if isinstance(exc, (json.JSONDecodeError, DecodeError))
            else "record"
        )
        raise DamagedRecordingError(f"{path}: {where}: corrupt ({exc})") from None
    return channels, meta, rows, samples, complete


_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log and publish times
_READ = {Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read, Opcode.METADATA: Metadata.read}
_USED_TOPICS = frozenset((STEP_TOPIC, HANDS_TOPIC))


def _used_records(data: bytes) -> list[McapRecord] | None:
    """The records of :func:`clean_records`' stream that :func:`_read_file` acts on: its
    channels and metadata, and the messages of the step and hand channels (the
    Foxglove scene's messages, about 45 % of the records, are skipped without being built).

    The records are the ones :class:`StreamReader` yields for them, parsed by the same
    ``read`` methods from the same stream position; ``None`` (read it with the
    ``StreamReader``, which then raises or stops where it does) for anything else: a
    record type other than these four, a record whose fields do not fill its length
    exactly, a message shorter than its header, a torn last record, a parse error.
    """
    n = len(data)
    if not data.startswith(MAGIC):
        return None
    buffer = io.BytesIO(data)  # shares the bytes (no copy while only read)
    out: list[McapRecord] = []
    used: dict[int, bool] = {}  # channel id -> its messages are used
    unpack_message = _MESSAGE_HEADER.unpack_from
    pos = len(MAGIC)
    try:
        while pos < n:
            if pos + RECORD_HEADER > n:
                return None
            op, length = record_head(data, pos)
            start = pos + RECORD_HEADER
            end = start + length
            if end > n:
                return None
            if op == Opcode.MESSAGE:
                if length < _MESSAGE_HEADER.size:
                    return None
                cid, sequence, log_time, publish_time = unpack_message(data, start)
                if used.get(cid, False):
                    out.append(
                        Message(
                            channel_id=cid,
                            log_time=log_time,
                            data=data[start + _MESSAGE_HEADER.size : end],
                            publish_time=publish_time,
                            sequence=sequence,
                        )
                    )
            elif op in _READ:
                buffer.seek(start)
                stream = ReadDataStream(buffer)
                record = _READ[op](stream)
                if stream.count != length:
                    return None
                if isinstance(record, Channel):
                    used[record.id] = record.topic in _USED_TOPICS
                if not isinstance(record, Schema):  # parsed (to fail where the
                    out.append(record)  # StreamReader fails), never used
            else:
                return None
            pos = end
    except Exception:  # any parse problem: the general reader decides
        return None
    return out


def _channel_version(channel: Channel) -> int:
    """The schema version a ``/trial/step`` channel declares (1: JSON steps; a protobuf
    channel without the key is version 2, the first protobuf one)."""
    if channel.message_encoding == "json":
        return 1
    text = (channel.metadata or {}).get("schema_version", "2")
    try:
        return int(text)
    except ValueError:
        raise RecordingError(f"schema_version {text!r} is not a number") from None


def recording_version(path: str | Path) -> int:
    """Schema version of a recording: 1 (JSON steps), 2 (protobuf steps, lossless
    doubles) or 3 (protobuf steps on the stated grids); see :mod:`payload.trials.records`.

    Raises:
        RecordingError: Unreadable, or no ``/trial/step`` channel.
    """
    path = Path(path)
    channels = _read_file(path)[0]
    for c in channels.values():
        if c.topic == STEP_TOPIC:
            try:
                return _channel_version(c)
            except RecordingError as exc:
                raise RecordingError(f"{path}: {exc}") from None
    raise RecordingError(f"{path}: no {STEP_TOPIC} channel (not a trial recording)")


CUT_SHORT = "cut_short"
"""Metadata key of a recording converted from a cut-short original (``payload trials
convert``): closed now, but the run it records was not finished, and it reads as
``complete = False`` like its original."""


def aborted_note(meta: Mapping[str, Any]) -> str | None:
    """What aborted the run a recording's metadata describes (``None``: not aborted): the
    recorder's ``aborted`` note (an exception left its ``with`` block) or the runner's
    ``aborted_by`` (what stopped the session), whichever is there."""
    note = meta.get("aborted") or meta.get("aborted_by")
    return None if not note else str(note)


def unfinished_reason(meta: Mapping[str, Any], complete: bool) -> str | None:
    """Why a recording is not a finished run's (``None`` if it is), from its metadata and
    whether it reads complete: aborted (an error or Ctrl-C), cut short (its writer killed:
    the file never closed), or converted from such a file (:data:`CUT_SHORT`). One
    definition for scoring, summaries and exports."""
    note = aborted_note(meta)
    if note is not None:
        return f"aborted ({note.rstrip(': ')})"
    if meta.get(CUT_SHORT):
        return "cut short (converted from a recording that was never closed)"
    if not complete:
        return "cut short (never closed: the run was killed or crashed)"
    return None


def cut_reason(meta: Mapping[str, Any], complete: bool) -> str | None:
    """Why a recording's session ends before its operator's task did (``None`` if it runs
    to its end): :func:`unfinished_reason`, or a finished recording of a session the
    ``--max-time`` cap stopped (``ended_by``), or a replay of an unfinished run's hands
    (``replay.source_unfinished``). Such a recording is scored, but its episode ends
    wherever the session stopped: the exports and the replay page say so."""
    why = unfinished_reason(meta, complete)
    if why is not None:
        return why
    if meta.get("ended_by") == ENDED_BY_CAP:
        return CAP_STOPPED
    replay = meta.get("replay")
    source = replay.get("source_unfinished") if isinstance(replay, Mapping) else None
    if source:
        return f"a replay of an unfinished run's hands ({source})"
    return None


def recording_meta(path: str | Path) -> dict[str, Any] | None:
    """A closed recording's metadata read through its summary's index (no step decoded,
    a few milliseconds), or ``None`` when that cannot be done (no such file, no summary:
    the file was never closed)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            meta: dict[str, Any] = {}
            for record in make_reader(f).iter_metadata():
                if record.name == META_NAME:
                    meta.update(_decode_meta(record.metadata, Path(path)))
            return meta
    except (OSError, McapError, RecordingError, ValueError, struct.error):
        return None


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by :class:`TrialRecorder`, complete or cut short.

    A file whose writer was killed has no summary or footer and may end in a torn record;
    every complete record before that is read.

    Args:
        path: The ``.mcap`` file.

    Returns:
        The recording, with ``complete`` telling whether the file was closed properly
        (and is not the conversion of a file that was not: its :data:`CUT_SHORT`
        metadata).

    Raises:
        RecordingError: The file is missing, is not MCAP, or is a closed MCAP file without a
            ``/trial/step`` channel. (A file cut short before its channel record reads as an
            empty recording.)
    """
    path = Path(path)
    channels, meta, rows, _, closed = _read_file(path)
    if closed and not any(c.topic == STEP_TOPIC for c in channels.values()):
        raise RecordingError(f"{path}: no {STEP_TOPIC} channel (not a trial recording)")
    complete = closed and CUT_SHORT not in meta  # a converted cut-short file says so
    typed = any(c.topic == STEP_TOPIC and c.message_encoding != "json" for c in channels.values())
    if typed:  # the typed decoder's rows: right types, so shapes and finiteness, by column
        try:
            rec = Recording.from_dicts(rows, meta, path, complete)
        except (KeyError, TypeError, ValueError):
            rec = None
        if rec is not None and _finite_columns(rec):
            return rec
    try:  # JSON rows, or a problem somewhere: step by step, naming the first bad field
        for i, row in enumerate(rows):  # every step, not just the first
            check_step(row, FIELD_SPECS, i, str(path))
    except StepError as exc:
        raise RecordingError(str(exc)) from None
    return Recording.from_dicts(rows, meta, path, complete)


def _finite_columns(rec: Recording) -> bool:
    """Every number of every step finite (NaN allowed where the field allows it)."""
    for name, (_, kind) in FIELD_SPECS.items():
        if kind == "float":
            if not np.isfinite(getattr(rec, name)).all():
                return False
        elif kind == "float_nan" and np.isinf(getattr(rec, name)).any():
            return False
    return True


def read_messages(path: str | Path) -> list[tuple[Channel, Schema | None, Message]]:
    """Every message of every channel of a recording, in file order, with its channel and
    schema, read as :func:`read_recording` reads a file: a cut-short file up to its last
    complete record, a corrupt one refused.

    Returns:
        ``(channel, schema or None, message)`` per message.

    Raises:
        RecordingError: Unreadable or corrupt file.
    """
    path = Path(path)
    data = _file_bytes(path)
    records = clean_records(data, path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    out: list[tuple[Channel, Schema | None, Message]] = []
    try:
        for record in StreamReader(io.BytesIO(records.data)).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                out.append((channel, schemas.get(channel.schema_id), record))
    except EndOfFile:
        pass  # the complete prefix of a cut-short file ends exactly here
    except McapError as exc:
        raise DamagedRecordingError(f"{path}: record {len(out)}: corrupt ({exc})") from None
    return out


def read_hand_frames(path: str | Path) -> tuple[dict[str, Any], list[Any]]:
    """The raw hand frames of a recording's ``/trial/hands`` channel, for a replay.

    Returns:
        (trial metadata, :class:`~payload.teleop.hands.HandFrame` list in recorded order).

    Raises:
        RecordingError: Unreadable file, or no hand channel (a recording from before
            schema version 2: replay its ``hands.jsonl`` instead).
    """
    meta, frames, _ = read_hand_frames_of_run(path)
    return meta, frames


def read_hand_frames_of_run(path: str | Path) -> tuple[dict[str, Any], list[Any], str | None]:
    """:func:`read_hand_frames`, and why the run it recorded ended before its task did
    (:func:`cut_reason`: aborted, killed, stopped by the ``--max-time`` cap, itself a
    replay of such a run; None: it did not): a replay of it ends where the run stopped."""
    from payload.teleop.hands import Hand, HandFrame

    path = Path(path)
    channels, meta, _, samples, complete = _read_file(path)
    if not any(c.topic == HANDS_TOPIC for c in channels.values()):
        if not complete:  # a recorder killed (or a copy cut) before the channel was written
            raise RecordingError(
                f"{path}: cut short ({path.stat().st_size} bytes) before its {HANDS_TOPIC} "
                "channel was written: no hands to replay"
            )
        if not any(c.topic == STEP_TOPIC for c in channels.values()):  # none of ours
            raise RecordingError(
                f"{path}: not a recording of this workbench (no {STEP_TOPIC} or "
                f"{HANDS_TOPIC} channel): replay a trial's or a live session's log.mcap, "
                "or a hands.jsonl"
            )
        raise RecordingError(
            f"{path}: no {HANDS_TOPIC} channel (an older recording: replay its hands.jsonl)"
        )

    def hand(joints: np.ndarray, tracked: bool) -> Hand:
        if not tracked or not np.all(np.isfinite(joints)):
            return Hand.untracked()
        return Hand(joints, True)

    frames = [
        HandFrame(
            s["stamp"], hand(s["left"], s["left_tracked"]), hand(s["right"], s["right_tracked"])
        )
        for s in samples
    ]
    return meta, frames, cut_reason(meta, complete)
