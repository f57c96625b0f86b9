"""Recorded hand sessions: a documented JSON Lines format, its writer and its reader.

Format (UTF-8, one JSON object per line):

- line 1, the header::

    {"format": "payload-hands", "version": 1, "frame": "workbench" | "webxr",
     "joints": [25 XRHand joint names], "meta": {...}}

- every further line, one frame::

    {"t": 12.34, "left": {"tracked": true, "joints": [[x, y, z], ... 25]},
     "right": {"tracked": false, "joints": null}}

Positions in metres; ``joints`` is ``null`` for an untracked hand. Floats are written
with ``repr`` precision, so a replay reproduces the recorded frames bit for bit. Times
are kept as recorded (even going backwards): judging them is the pipeline's safety
supervisor's job, not the reader's.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

from payload.errors import PayloadError
from payload.teleop.hands import XR_JOINTS, Hand, HandFrame

FORMAT = "payload-hands"
VERSION = 1


class ReplayError(PayloadError):
    """A hand recording is malformed; the message names the file and line."""


def _hand_json(hand: Hand) -> dict[str, Any]:
    if not hand.tracked or not np.all(np.isfinite(hand.joints)):
        return {"tracked": bool(hand.tracked), "joints": None}
    return {"tracked": True, "joints": [[float(v) for v in row] for row in hand.joints]}


class HandRecordingWriter:
    """Append hand frames to a JSON Lines recording (flushed every frame).

    An existing file is refused unless ``overwrite``.
    """

    def __init__(
        self,
        path: str | Path,
        frame: str = "workbench",
        meta: dict | None = None,
        *,
        overwrite: bool = False,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fh: IO[str] | None = self.path.open("w" if overwrite else "x", encoding="utf-8")
        except FileExistsError:
            raise ReplayError(f"{self.path}: already exists (not replaced)") from None
        header = {
            "format": FORMAT,
            "version": VERSION,
            "frame": frame,
            "joints": list(XR_JOINTS),
            "meta": meta or {},
        }
        self._frame = frame
        self._fh.write(json.dumps(header) + "\n")

    def write(self, frame: HandFrame) -> None:
        if self._fh is None:
            raise ReplayError(f"{self.path}: writer is closed")
        if frame.frame != self._frame:
            raise ReplayError(f"{self.path}: frame convention {frame.frame} != {self._frame}")
        line = {"t": float(frame.stamp), "left": _hand_json(frame.left)}
        line["right"] = _hand_json(frame.right)
        self._fh.write(json.dumps(line) + "\n")
        self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> HandRecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _parse_hand(obj: Any, where: str) -> Hand:
    if not isinstance(obj, dict) or "tracked" not in obj or "joints" not in obj:
        raise ReplayError(f"{where}: a hand needs 'tracked' and 'joints'")
    if not isinstance(obj["tracked"], bool):
        raise ReplayError(f"{where}: 'tracked' must be true or false, got {obj['tracked']!r}")
    if obj["joints"] is None or not obj["tracked"]:
        return Hand.untracked()
    rows = obj["joints"]
    if (
        not isinstance(rows, list)
        or len(rows) != 25
        or not all(isinstance(r, list) and len(r) == 3 for r in rows)
    ):
        raise ReplayError(f"{where}: 'joints' must be 25 rows of [x, y, z] or null")
    if not all(type(v) in (int, float) for r in rows for v in r):
        raise ReplayError(f"{where}: 'joints' must hold numbers only")
    return Hand(np.asarray(rows, dtype=np.float64), True)


def read_hand_recording(path: str | Path) -> tuple[dict[str, Any], list[HandFrame]]:
    """Read a whole recording.

    Returns:
        (header, frames).

    Raises:
        ReplayError: Missing file, wrong header, or a malformed line (named by number).
    """
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ReplayError(f"{p}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise ReplayError(
            f"{p}: not a {FORMAT} recording (not UTF-8 text: byte {exc.start})"
        ) from None
    if not lines:
        raise ReplayError(f"{p}: empty file")
    try:
        header = json.loads(lines[0])
    except json.JSONDecodeError as exc:
        raise ReplayError(
            f"{p}: not a {FORMAT} recording (a JSON-lines file whose first line is its "
            f"header; line 1 is not one JSON object: {exc.msg}); a trial's log.mcap "
            "replays too"
        ) from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ReplayError(f"{p}:1: not a {FORMAT} recording")
    if header.get("version") != VERSION:
        raise ReplayError(f"{p}:1: unsupported version {header.get('version')}")
    if list(header.get("joints", [])) != list(XR_JOINTS):
        raise ReplayError(f"{p}:1: joint list differs from the 25 XRHand joints")
    frame_kind = header.get("frame", "workbench")
    if frame_kind not in ("workbench", "webxr"):
        raise ReplayError(f"{p}:1: 'frame': expected 'workbench' or 'webxr', got {frame_kind!r}")
    if not isinstance(header.get("meta", {}), dict):
        raise ReplayError(f"{p}:1: 'meta': expected an object")
    frames: list[HandFrame] = []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        where = f"{p}:{n}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ReplayError(f"{where}: not JSON ({exc.msg})") from exc
        if not isinstance(obj, dict) or not isinstance(obj.get("t"), (int, float)):
            raise ReplayError(f"{where}: 't': expected a number (seconds)")
        t = float(obj["t"])
        if not np.isfinite(t):
            raise ReplayError(f"{where}: time {t} is not finite")
        hands = [_parse_hand(obj.get(side), f"{where}: {side!r}") for side in ("left", "right")]
        frames.append(HandFrame(t, hands[0], hands[1], frame_kind))
    return header, frames


def iter_hand_recording(path: str | Path) -> Iterator[HandFrame]:
    """Frames of a recording in order (validated as a whole first)."""
    _, frames = read_hand_recording(path)
    yield from frames
