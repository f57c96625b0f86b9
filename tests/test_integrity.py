"""Damaged recordings are named, never crash and never replay silently
(payload.trials.integrity, through the reader and the commands that read recordings)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from payload.teleop.hands import Hand, HandFrame
from payload.trials.reading import Recording, read_hand_frames, read_recording
from payload.trials.recorder import TrialRecorder, random_step
from payload.trials.records import RecordingError

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
