"""``payload trials convert DIR``: rewrite schema-1 (JSON step) recordings in the current
schema (:data:`payload.trials.records.SCHEMA_VERSION`).

Every ``log.mcap`` below ``DIR`` whose steps are JSON is rewritten with the current
recorder (protobuf steps, zstd chunks, the Foxglove channels); the hand frames of a
``hands.jsonl`` beside it go into its ``/trial/hands`` channel when they match the steps
one for one. Nothing recorded is lost: the original is kept as ``log.v1.mcap`` (and
``hands.jsonl`` stays), and a folder that already holds a ``log.v1.mcap`` is refused
unless ``force``. Steps, metadata and wall times are carried over, the step numbers at
the recorder's resolution (:data:`payload.trials.stepgrid.STEP_GRIDS`; the original keeps
every bit).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from payload.folders import HANDS, RECORDING, tagged
from payload.trials.reading import CUT_SHORT
from payload.trials.recorder import (
    SCHEMA_VERSION,
    STEP_TOPIC,
    RecordingError,
    TrialRecorder,
    read_recording,
    recording_version,
)

log = logging.getLogger(__name__)

BACKUP_NAME = tagged(RECORDING, "v1")


def convert_file(path: Path, *, force: bool = False) -> str:
    """Convert one recording in place (original kept as ``log.v1.mcap``); says what it did.

    Raises:
        RecordingError: Unreadable file, or a backup exists and ``force`` is not set.
    """
    return _convert_file(path, force=force)[1]


def _convert_file(path: Path, *, force: bool = False) -> tuple[bool, str]:
    """:func:`convert_file`, and whether it converted the file (or left it as it is)."""
    from payload.sim.world import build_world
    from payload.teleop.replay import ReplayError, read_hand_recording
    from payload.trials.foxglove import FoxgloveScene

    with _no_schema1_notice():  # the reader's "convert it" notice, said while converting
        version = recording_version(path)
    if version > SCHEMA_VERSION:
        raise RecordingError(
            f"{path}: schema version {version} is newer than this workbench's "
            f"({SCHEMA_VERSION}); update the workbench to read it"
        )
    if version != 1:  # versions 2 and up read as they are
        return False, f"{path}: already schema version {version}, left as it is"
    backup = path.with_name(BACKUP_NAME)
    if backup.exists() and not force:
        raise RecordingError(f"{backup}: exists; pass --force to convert {path} again")
    if backup.exists() and not _same_bytes(backup, path):  # the backup is another original
        raise RecordingError(
            f"{backup}: holds another recording than {path.name}; move it away to convert "
            f"{path} (an original is never overwritten, --force or not)"
        )
    with _no_schema1_notice():
        rec = read_recording(path)
    frames = None
    hands_path = path.with_name(HANDS)
    if hands_path.is_file():
        try:
            frames = read_hand_recording(hands_path)[1]
        except ReplayError as exc:
            log.warning("%s: hand frames not carried over (%s)", hands_path, exc)
        if frames is not None and len(frames) != len(rec):
            log.warning(
                "%s: %d frames for %d steps, not carried over", hands_path, len(frames), len(rec)
            )
            frames = None
    tmp = path.with_name(path.name + ".converting")
    walls = iter(rec.wall_time)
    with TrialRecorder(tmp, overwrite=True, scene=FoxgloveScene(build_world(None))) as out:
        out._clock = lambda: round(float(next(walls)) * 1e9)
        out.write_meta(rec.meta)
        for i in range(len(rec)):
            if frames is not None:
                out.write_hands(frames[i])
            out.write(rec.step(i))
        if not rec.complete:  # the converted file is closed; its run still was not finished
            out.write_meta({CUT_SHORT: "the schema-1 original was cut short (never closed)"})
            log.warning("%s: the original was cut short; the converted file says so", path)
    os.replace(path, backup)
    os.replace(tmp, path)
    hands = "with" if frames is not None else "without"
    return True, (
        f"{path}: converted {len(rec)} steps to schema version {SCHEMA_VERSION} "
        f"({hands} hand frames); "
        f"the original is {backup.name}"
    )


def _not_the_schema1_notice(record: logging.LogRecord) -> bool:
    """A log filter: every record but the reader's "schema version 1, convert it" notice."""
    return not str(record.msg).startswith("%s: schema version 1")


@contextlib.contextmanager
def _no_schema1_notice() -> Iterator[None]:
    """The reader's "convert it" notice left out while converting (a filter on the
    reader's logger: its level, and any other message, stay as they are)."""
    reader = logging.getLogger(read_recording.__module__)
    reader.addFilter(_not_the_schema1_notice)
    try:
        yield
    finally:
        reader.removeFilter(_not_the_schema1_notice)


def _same_bytes(a: Path, b: Path, block: int = 1 << 20) -> bool:
    """Whether two files hold the same bytes."""
    if a.stat().st_size != b.stat().st_size:
        return False
    with a.open("rb") as fa, b.open("rb") as fb:
        while True:
            x, y = fa.read(block), fb.read(block)
            if x != y:
                return False
            if not x:
                return True


def convert_dir(root: Path, *, force: bool = False) -> dict[str, Any]:
    """Convert every ``log.mcap`` below ``root`` (or ``root`` itself if it is a file).

    Returns:
        ``{"converted": [paths], "skipped": [paths], "messages": [lines]}``.

    Raises:
        RecordingError: ``root`` does not exist or holds no ``log.mcap``.
    """
    root = Path(root)
    if not root.exists():
        raise RecordingError(f"{root}: no such file or folder")
    paths = [root] if root.is_file() else sorted(root.rglob(RECORDING))
    if not paths:
        raise RecordingError(f"{root}: no {RECORDING} below it")
    out: dict[str, Any] = {"converted": [], "skipped": [], "messages": []}
    for p in paths:
        converted, msg = _convert_file(p, force=force)
        out["converted" if converted else "skipped"].append(str(p))
        out["messages"].append(msg)
    return out


__all__ = ["BACKUP_NAME", "STEP_TOPIC", "convert_dir", "convert_file"]
