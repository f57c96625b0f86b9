"""Damaged recordings are named, never crash and never replay silently
(payload.trials.integrity, through the reader and the commands that read recordings)."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from mcap.opcode import Opcode

from payload.teleop.hands import Hand, HandFrame
from payload.trials import reading
from payload.trials.integrity import RECORD_HEADER, _open_chunk, clean_records, record_head
from payload.trials.reading import Recording, read_hand_frames, read_recording
from payload.trials.recorder import TrialRecorder, random_step
from payload.trials.records import HANDS_TOPIC, STEP_TOPIC, RecordingError

N_STEPS = 120
DT = 0.02


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A recording of many small chunks (a flush every 0.1 s), hands and metadata."""
    path = tmp_path_factory.mktemp("rec") / "log.mcap"
    rng = np.random.default_rng(7)
    with TrialRecorder(path, flush_period_s=0.1) as rec:
        rec.write_meta({"seed": 3, "ctb": "single", "calibration": {"scale": 1.25}})
        for k in range(N_STEPS):
            step = random_step(rng, k * DT)
            rec.write_hands(
                HandFrame(k * DT, Hand(step.left_joints, True), Hand(step.right_joints, True))
            )
            rec.write(step)
        rec.write_meta({"finished": True})
    return path


def _same(a: Recording, b: Recording) -> bool:
    if a.meta != b.meta or a.complete != b.complete or len(a) != len(b):
        return False
    for f in dataclasses.fields(Recording):
        if f.name in ("path", "meta", "complete"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if x.dtype.kind == "f":
            if not np.array_equal(x, y, equal_nan=True):
                return False
        elif not np.array_equal(x, y):
            return False
    return True


def _hands(path: Path) -> list[tuple[float, bytes, bytes]]:
    _, frames = read_hand_frames(path)
    return [(f.stamp, f.left.joints.tobytes(), f.right.joints.tobytes()) for f in frames]


def test_fuzzed_recordings_are_named_or_read_identically(recording: Path, tmp_path: Path):
    """100 seeded corruptions (random bytes at random offsets, truncations): each is one
    line naming the file, or a read identical to the original (the damage touched only
    what the reader does not use: indexes, the summary), or for a truncation the steps
    before the cut exactly (a killed writer's torn tail)."""
    data = recording.read_bytes()
    original, original_hands = read_recording(recording), _hands(recording)
    rng = np.random.default_rng(2026)
    named = identical = prefixes = 0
    for case in range(100):
        damaged = bytearray(data)
        truncate = case % 5 == 4
        if truncate:
            damaged = damaged[: int(rng.integers(9, len(data) - 1))]
        else:
            at = int(rng.integers(8, len(data) - 8))
            n = int(rng.integers(1, 65))
            new = rng.integers(0, 256, size=min(n, len(data) - at), dtype=np.uint8)
            damaged[at : at + len(new)] = new.tobytes()
            if bytes(damaged) == data:
                continue
        path = tmp_path / f"case{case}.mcap"
        path.write_bytes(bytes(damaged))
        try:
            rec = read_recording(path)
            hands = _hands(path)
        except RecordingError as exc:
            text = str(exc)
            assert "\n" not in text and text.startswith(str(path)), text
            named += 1
            continue
        if truncate:  # a torn tail: whole steps before the cut, never a damaged one
            n = len(rec)
            assert not rec.complete
            assert np.array_equal(rec.q_cmd, original.q_cmd[:n])
            assert np.array_equal(rec.t, original.t[:n])
            assert hands == original_hands[: len(hands)]
            prefixes += 1
        else:
            assert _same(rec, original), f"case {case}: damage read as data"
            assert hands == original_hands
            identical += 1
    # the corruptions must exercise both answers (a test that never names damage, or
    # names everything, would not show the reader tells them apart)
    assert named >= 40 and identical + prefixes >= 5, (named, identical, prefixes)


def test_damaged_chunk_names_channels_steps_and_bytes(recording: Path, tmp_path: Path):
    data = bytearray(recording.read_bytes())
    middle = len(data) // 2
    # find the chunk record around the middle: opcode 0x06 followed by a length that
    # lands on another record
    pos, start = 8, None
    while pos < len(data):
        length = int.from_bytes(data[pos + 1 : pos + 9], "little")
        if data[pos] == 0x06 and pos > middle // 2 and start is None:
            start, end = pos, pos + 9 + length
        pos += 9 + length
    assert start is not None
    data[end - 10] ^= 0xFF  # inside the compressed records
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError) as info:
        read_recording(path)
    text = str(info.value)
    assert f"bytes {start}-{end}" in text and "/trial/step" in text and "steps " in text


def test_metadata_damage_is_not_read_as_other_values(recording: Path, tmp_path: Path):
    """A digit changed inside the metadata's JSON parses as valid JSON: the stored CRC
    catches it."""
    data = recording.read_bytes()
    i = data.index(b'"scale": 1.25') if b'"scale": 1.25' in data else data.index(b"1.25")
    damaged = data[:i] + data[i:].replace(b"1.25", b"1.75", 1)
    path = tmp_path / "meta.mcap"
    path.write_bytes(damaged)
    with pytest.raises(RecordingError, match=r"metadata at bytes .*CRC mismatch"):
        read_recording(path)


def test_commands_name_a_damaged_recording(recording: Path, tmp_path: Path):
    """The commands that read a recording answer damage with one line and exit 2."""
    data = bytearray(recording.read_bytes())
    data[len(data) // 2] ^= 0x55
    trial = tmp_path / "trial"
    trial.mkdir()
    (trial / "log.mcap").write_bytes(bytes(data))
    for args in (
        ["trials", "convert", str(trial)],
        ["export", "lerobot", str(trial / "log.mcap"), "--out", str(tmp_path / "ds")],
        ["trial", "--replay", str(trial / "log.mcap"), "--out", str(tmp_path / "t")],
    ):
        proc = subprocess.run(
            [sys.executable, "-m", "payload", *args], capture_output=True, text=True
        )
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2, (args, proc.stderr)
        assert len(lines) == 1 and "log.mcap" in lines[0], (args, proc.stderr)


# -- the reader's own walk of the records it uses (issue 31) -------------------------------
@pytest.fixture(scope="module")
def scene_recording(tmp_path_factory) -> Path:
    """A recording as a trial writes it: Foxglove scene channels, hands, steps and
    metadata, in many small chunks."""
    from payload.sim.world import build_world
    from payload.trials.foxglove import FoxgloveScene

    world = build_world(None)
    path = tmp_path_factory.mktemp("scene") / "log.mcap"
    rng = np.random.default_rng(11)
    lo, hi = world.model.jnt_range[world.model.dof_jntid[world.dof]].T
    with TrialRecorder(path, flush_period_s=0.2, scene=FoxgloveScene(world)) as rec:
        rec.write_meta({"seed": 5, "ctb": "single"})
        for k in range(N_STEPS):
            step = random_step(rng, k * DT, q_meas=rng.uniform(lo, hi), contact=k > 40)
            rec.write_hands(
                HandFrame(k * DT, Hand(step.left_joints, True), Hand(step.right_joints, True))
            )
            rec.write(step)
        rec.write_meta({"finished": True})
    return path


def _general(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the reader take the general path (mcap's StreamReader over every record)."""
    monkeypatch.setattr(reading, "_used_records", lambda data: None)


def _outcome(path: Path) -> tuple[str, Recording | None, list | None]:
    try:
        return "", read_recording(path), _hands(path)
    except RecordingError as exc:
        return str(exc), None, None


def test_the_used_records_are_the_stream_readers(scene_recording: Path):
    """The reader's walk yields exactly the records of mcap's StreamReader it acts on (the
    same Channel, Metadata and step/hand Message objects, in order), skipping the scene's."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    data = clean_records(scene_recording.read_bytes(), scene_recording).data
    everything = []
    with pytest.raises(EndOfFile):  # how the stream of used records ends (no footer)
        for r in StreamReader(io.BytesIO(data)).records:
            everything.append(r)
    topics: dict[int, str] = {}
    expected = []
    for r in everything:
        if isinstance(r, Channel):
            topics[r.id] = r.topic
            expected.append(r)
        elif isinstance(r, Metadata):
            expected.append(r)
        elif isinstance(r, Message) and topics.get(r.channel_id) in (STEP_TOPIC, HANDS_TOPIC):
            expected.append(r)
    fast = reading._used_records(data)
    assert fast is not None
    assert fast == expected
    scene = sum(isinstance(r, Message) for r in everything) - sum(
        isinstance(r, Message) for r in expected
    )
    assert scene >= N_STEPS // 2  # the file has scene messages, and they were skipped
    assert {r.topic for r in expected if isinstance(r, Channel)} > {STEP_TOPIC, HANDS_TOPIC}


def test_the_readers_walk_reads_what_the_general_path_reads(
    scene_recording: Path, monkeypatch: pytest.MonkeyPatch
):
    fast = read_recording(scene_recording)
    fast_hands = _hands(scene_recording)
    assert len(fast) == N_STEPS and fast.complete and fast.meta["finished"]
    _general(monkeypatch)
    general = read_recording(scene_recording)
    assert _same(fast, general)
    for f in dataclasses.fields(Recording):  # bit for bit, dtypes included
        x = getattr(fast, f.name)
        if isinstance(x, np.ndarray):
            y = getattr(general, f.name)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f.name
    assert fast_hands == _hands(scene_recording)


@pytest.mark.parametrize(
    "tail",
    [
        # a message shorter than its header
        bytes([Opcode.MESSAGE]) + (10).to_bytes(8, "little") + bytes(10),
        bytes([Opcode.MESSAGE]) + (30).to_bytes(8, "little") + bytes(12),  # a torn last record
        # a record type it does not act on
        bytes([Opcode.HEADER]) + (8).to_bytes(8, "little") + bytes(8),
        # a channel not filling its length
        bytes([Opcode.CHANNEL]) + (30).to_bytes(8, "little") + bytes(30),
        bytes([Opcode.MESSAGE, 0]),  # less than a record's opcode and length
    ],
)
def test_anything_unusual_goes_to_the_general_path(scene_recording: Path, tail: bytes):
    data = clean_records(scene_recording.read_bytes(), scene_recording).data
    assert reading._used_records(data) is not None
    assert reading._used_records(data + tail) is None


def _chunk_record(times: bytes, raw: bytes) -> bytes:
    """An uncompressed chunk record of the records ``raw`` (its CRC right); ``times``: the
    message start and end times of the chunk it replaces."""
    body = b"".join(
        (
            times,
            len(raw).to_bytes(8, "little"),
            zlib.crc32(raw).to_bytes(4, "little"),
            (0).to_bytes(4, "little"),  # compression "" (none)
            len(raw).to_bytes(8, "little"),
            raw,
        )
    )
    return bytes([Opcode.CHUNK]) + len(body).to_bytes(8, "little") + body


def test_fuzzed_recordings_read_or_fail_as_on_the_general_path(
    scene_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Seeded corruptions of a recording with a scene, half of them inside a chunk's
    records (anywhere, or in a record's opcode or length) with the chunk rewritten to pass
    its CRC (damage the integrity check cannot see): the same error line, or the same
    recording, through the reader's walk as through the StreamReader."""
    data = scene_recording.read_bytes()
    chunks, pos = [], 8
    while pos + RECORD_HEADER <= len(data):
        op, length = record_head(data, pos)
        if op == Opcode.CHUNK:
            chunks.append((pos, pos + RECORD_HEADER + length))
        pos += RECORD_HEADER + length
    rng = np.random.default_rng(31)
    cases = []
    for case in range(60):
        damaged = bytearray(data)
        if case % 2:
            start, end = chunks[int(rng.integers(len(chunks)))]
            raw = bytearray(_open_chunk(data[start + RECORD_HEADER : end]))
            if case % 4 == 1:  # anywhere
                at = int(rng.integers(len(raw) - 2))
            else:  # a record's opcode or the low bytes of its length
                heads, p = [], 0
                while p + RECORD_HEADER <= len(raw):
                    heads.append(p)
                    p += RECORD_HEADER + record_head(raw, p)[1]
                at = heads[int(rng.integers(len(heads)))] + int(rng.integers(2))
            raw[at : at + 2] = rng.integers(0, 256, size=2, dtype=np.uint8).tobytes()
            times = data[start + RECORD_HEADER : start + RECORD_HEADER + 16]
            damaged[start:end] = _chunk_record(times, bytes(raw))
        else:
            at = int(rng.integers(8, len(data) - 8))
            damaged[at : at + 4] = rng.integers(0, 256, size=4, dtype=np.uint8).tobytes()
        path = tmp_path / f"case{case}.mcap"
        path.write_bytes(bytes(damaged))
        cases.append(path)
    fast = [_outcome(p) for p in cases]
    walked = [_walked(p) for p in cases]
    _general(monkeypatch)
    general = [_outcome(p) for p in cases]
    _, intact, intact_hands = _outcome(scene_recording)
    errors = walked_damage = 0
    for path, took_walk, (e1, r1, h1), (e2, r2, h2) in zip(cases, walked, fast, general):
        assert e1 == e2, path
        if e1:
            errors += 1
        else:
            assert _same(r1, r2) and h1 == h2, path
        if took_walk and (e1 or not _same(r1, intact) or h1 != intact_hands):
            walked_damage += 1
    assert 0 < errors < len(cases), errors
    # some of the damage went through the walk itself, not only the general reader
    assert walked_damage > 0, walked_damage


def _walked(path: Path) -> bool:
    """The reader's own walk reads this file (no fall-back to the general reader)."""
    try:
        data = clean_records(path.read_bytes(), path).data
    except RecordingError:
        return False
    return reading._used_records(data) is not None


def test_a_chunk_claiming_a_huge_size_is_refused_without_allocating_it():
    """A chunk whose uncompressed-size field says 2**62 bytes (a flipped byte in a
    recording) is a malformed chunk (ValueError), not a MemoryError: the decompression is
    streamed, and what it gives is compared with the field afterwards."""
    import struct
    import zlib

    import zstandard

    from payload.trials.integrity import _open_chunk

    raw = b"records " * 100
    packed = zstandard.ZstdCompressor().compress(raw)
    head = struct.pack("<QQQI", 0, 1, 2**62, zlib.crc32(raw))
    body = head + struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(packed)) + packed
    with pytest.raises(ValueError, match="decompressed where it says"):
        _open_chunk(body)
    good = struct.pack("<QQQI", 0, 1, len(raw), zlib.crc32(raw)) + body[28:]
    assert _open_chunk(good) == raw


def _rewritten(src: Path, dst: Path, change: dict[int, dict[str, int]]) -> None:
    """``src`` copied record for record by mcap's own reader and writer (valid chunks and
    CRCs), with the step messages of the sequence numbers in ``change`` re-serialised with
    those fields set: what another writer's well-formed file could hold."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from payload.trials.stepmsg import StepMsg

    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        header = reader.get_header()
        w = Writer(f_out)
        w.start(profile=header.profile, library=header.library)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic,
                    channel.message_encoding,
                    schemas.get(channel.schema_id, 0),
                    channel.metadata,
                )
            data = message.data
            if channel.topic == STEP_TOPIC and message.sequence in change:
                m = StepMsg.FromString(data)
                for name, value in change[message.sequence].items():
                    setattr(m, name, value)
                data = m.SerializeToString()
            w.add_message(
                channels[channel.id], message.log_time, data, message.publish_time,
                message.sequence,
            )  # fmt: skip
        for meta in reader.iter_metadata():
            w.add_metadata(meta.name, meta.metadata)
        w.finish()


@pytest.mark.parametrize(
    ("field", "value"), [("phase", 9), ("phase", -2), ("ctb_module", 4), ("ctb_module", -1)]
)
def test_a_step_whose_enum_is_out_of_range_is_named(
    recording: Path, tmp_path: Path, field: str, value: int
):
    """Protobuf's enums are open: a well-formed file (valid chunks and CRCs) can hold any
    32-bit number in a step's phase or module. The reader names the step and the field
    (before: an IndexError's traceback, and a negative number read silently as a name
    counted from the end)."""
    same = tmp_path / "same.mcap"
    _rewritten(recording, same, {})
    assert _same(read_recording(same), read_recording(recording))  # the copy reads alike
    bad = tmp_path / "bad.mcap"
    _rewritten(recording, bad, {40: {field: value}})
    with pytest.raises(RecordingError) as info:
        read_recording(bad)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{bad}: step 40: "), text
    assert f"{field}: {value} is not a number from 0 to" in text, text


def test_a_recording_cut_before_its_hands_channel_says_so(recording: Path, tmp_path: Path):
    """A file cut before the hands' channel was written (a recorder killed in its first
    second, a copy cut short) is said to be cut short, not an older recording."""
    data = recording.read_bytes()
    channel = data.index(HANDS_TOPIC.encode())  # where the channel record names its topic
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: min(100, channel)])
    with pytest.raises(RecordingError) as info:
        read_hand_frames(cut)
    assert str(info.value) == (
        f"{cut}: cut short ({min(100, channel)} bytes) before its {HANDS_TOPIC} channel was "
        "written: no hands to replay"
    )


def test_another_tools_mcap_is_said_not_to_be_a_recording_of_ours(tmp_path: Path):
    """An MCAP file of another tool (written here with the mcap library itself: one JSON
    channel of its own) was called "an older recording: replay its hands.jsonl"; it is
    said not to be this workbench's recording, naming what is, in one line."""
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with other.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("pose", "jsonschema", b"{}")
        channel = writer.register_channel("/robot/pose", "json", schema)
        writer.add_message(channel, log_time=0, data=b"{}", publish_time=0)
        writer.finish()
    with pytest.raises(RecordingError) as info:
        read_hand_frames(other)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{other}: not a recording of this workbench")
    assert STEP_TOPIC in text and HANDS_TOPIC in text and "older" not in text
