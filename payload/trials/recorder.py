"""Crash-safe, compact trial recording: one MCAP file per trial, one protobuf message per step.

The writer, :class:`TrialRecorder`. The file layout and the step fields are described in
:mod:`payload.trials.records`; the reader is :mod:`payload.trials.reading`. This module
re-exports both, so ``from payload.trials.recorder import read_recording`` keeps working.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import numpy as np
from mcap.writer import CompressionType, IndexType, Writer

from payload.teleop.hands import XR_JOINTS
from payload.trials import codec
from payload.trials.integrity import META_CRC_KEY, metadata_crc
from payload.trials.reading import (
    Recording,
    read_hand_frames,
    read_recording,
    recording_version,
)
from payload.trials.records import (
    FIELD_SPECS,
    HANDS_TOPIC,
    LIBRARY,
    META_NAME,
    MODULES,
    N_HAND_JOINTS,
    PHASES,
    SCHEMA_VERSION,
    STEP_SCHEMA,
    STEP_SCHEMA_NAME,
    STEP_TOPIC,
    RecordingError,
    StepRecord,
    random_step,
)

log = logging.getLogger(__name__)


class TrialRecorder:
    """Write a trial's steps into an MCAP file, crash-safe (see the module docstring).

    Use as a context manager::

        with TrialRecorder(out_dir / "log.mcap") as rec:
            rec.write_meta({"seed": 3, "design_hash": "..."})
            for step in loop:
                rec.write(step)

    Args:
        path: The ``.mcap`` file to create (parent folders are created).
        flush_period_s: Longest time [s] between flushes, counted both in wall-clock time
            and in recorded time ``t``. Must be in (0, 1].
        overwrite: Replace an existing file instead of refusing.
        scene: Optional Foxglove scene writer (:class:`~payload.trials.foxglove.FoxgloveScene`)
            adding the standard Foxglove channels (transforms, scene, joint states).
        keep: Also keep what was written as the reader will read it back, for
            :meth:`recording` (a trial scores its recording without reading the file).

    Raises:
        RecordingError: ``flush_period_s`` out of range, or the file exists.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_period_s: float = 1.0,
        overwrite: bool = False,
        scene: Any = None,
        keep: bool = False,
    ) -> None:
        if not (0.0 < flush_period_s <= 1.0):
            raise RecordingError(f"flush_period_s must be in (0, 1] s, got {flush_period_s}")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise RecordingError(f"{self.path}: already exists (pass overwrite=True to replace)")
        self.flush_period_s = float(flush_period_s)
        self._overwrite = bool(overwrite)
        self._file: Any = None
        self._writer: Writer | None = None
        self._channel = 0
        self._seq = 0
        self._last_t = -math.inf
        self._flush_wall = 0.0
        self._flush_t = -math.inf
        self._closed = False
        self._hands_channel = 0
        self._hands: tuple[int, Any] | None = None
        self._codec = codec.StepCodec()
        self._scene = scene
        self._t0_ns: int | None = None
        self._clock = time.time_ns
        self._pending: list[_Pending] = []  # steps written, not yet encoded
        self._kept: list[Recording] | None = [] if keep else None  # per flush, as read back
        self._meta: dict[str, Any] = {}  # the metadata as read back
        self._failed = False  # a deferred step could not be made (write_later)
        self._written_t = -math.inf  # the time of the last step in the file

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> TrialRecorder:
        """Create the file and write the header, schema and channel (idempotent)."""
        if self._writer is not None:
            return self
        if self._closed:
            raise RecordingError(f"{self.path}: recorder already closed")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # a large buffer (few write calls); the flush deadline bounds what a crash loses.
        # Created only if it is still not there (another recorder, another process, may
        # have made it since this one was set up): never truncated unless ``overwrite``
        try:
            self._file = open(  # closed in close()
                self.path, "wb" if self._overwrite else "xb", buffering=1 << 20
            )
        except FileExistsError:
            raise RecordingError(f"{self.path}: already exists (not replaced)") from None
        # zstd chunks, one per flush (at most a second): a kill loses at most the open one
        self._writer = Writer(
            self._file,
            chunk_size=1 << 30,
            compression=CompressionType.ZSTD,
            index_types=IndexType.CHUNK | IndexType.METADATA | IndexType.ATTACHMENT,
        )
        self._writer.start(profile="", library=LIBRARY)
        data = codec.schema_data()
        step_schema = self._writer.register_schema(
            name=codec.STEP_MESSAGE, encoding="protobuf", data=data
        )
        hands_schema = self._writer.register_schema(
            name=codec.HANDS_MESSAGE, encoding="protobuf", data=data
        )
        self._channel = self._writer.register_channel(
            topic=STEP_TOPIC,
            message_encoding="protobuf",
            schema_id=step_schema,
            metadata={"schema_version": str(SCHEMA_VERSION), "rate_hz": "50"},
        )
        self._hands_channel = self._writer.register_channel(
            topic=HANDS_TOPIC,
            message_encoding="protobuf",
            schema_id=hands_schema,
            metadata={"frame": "workbench", "joints": ",".join(XR_JOINTS)},
        )
        if self._scene is not None:
            self._scene.start(self._writer)
        self.flush()
        return self

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent).

        A step that cannot be made at this last flush (:meth:`write_later`) is raised after
        the file is finished, with the steps before it and an ``aborted`` metadata record
        naming the error: nobody scores it as a finished trial."""
        self._closed = True  # the writer below is still open until finished
        if self._writer is None:
            return
        try:
            self._drain()
        except BaseException as exc:
            self.write_meta({"aborted": f"{type(exc).__name__}: {exc}"})
            raise
        finally:
            self._writer.finish()
            self._file.close()
            self._writer = None
            self._file = None

    def __enter__(self) -> TrialRecorder:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is not None and self._writer is not None:
                # the run died: say so in the file, so nobody scores it as a finished trial
                try:
                    self.write_meta({"aborted": f"{exc_type.__name__}: {exc}"})
                    if isinstance(exc, KeyboardInterrupt):  # Ctrl-C, SIGTERM: said by the CLI
                        exc.add_note(f"recording kept, marked aborted (not scored): {self.path}")
                except Exception as failed:  # the run's own error is the one to raise
                    log.warning("%s: marking the recording aborted failed: %s", self.path, failed)
        finally:
            self.close()

    # -- writing -----------------------------------------------------------------------
    @property
    def n_steps(self) -> int:
        """Steps written so far (those to be made at the next flush included)."""
        return self._seq

    @property
    def last_written_t(self) -> float:
        """The time [s] of the last step in the file (``-inf`` before any): the steps
        written since the last flush are not in it yet."""
        return self._written_t

    def mark_aborted(self, exc: BaseException) -> tuple[str, float]:
        """Mark the recording aborted by ``exc``, after the steps made so far reach the
        file (a step that cannot be made is left out: those before it are in the file).

        The metadata gains ``aborted_by``, ``aborted_at_s`` and ``aborted_traceback`` (the
        exception's traceback as Python prints it).

        Returns:
            What aborted it (``"<type>: <message>"``) and the time [s] of the last step in
            the file (0 when none).
        """
        import traceback

        what = f"{type(exc).__name__}: {exc}"
        try:
            self.flush()
        except RecordingError:
            pass
        at = max(0.0, self.last_written_t)
        # where it came from, for the bug report (a command prints only the line above)
        where = "".join(traceback.format_exception(exc))
        self.write_meta({"aborted_by": what, "aborted_at_s": at, "aborted_traceback": where})
        return what, at

    def flush(self) -> None:
        """Push everything written so far to the operating system (survives SIGKILL)."""
        if self._writer is not None:
            try:
                self._drain()
            finally:  # what was drained reaches the file, a step that failed or not
                self._writer.flush()  # closes the chunk in progress and flushes the file
                self._codec.key()
                self._flush_wall = time.monotonic()

    def _drain(self) -> None:
        """Encode the steps written since the last flush, as one batch, and add their
        messages (hand sample, step, Foxglove scene) in the order they were written."""
        if not self._pending or self._writer is None:
            return
        writer, pending = self._writer, self._pending
        self._pending = []
        failed = _built(pending)  # the deferred steps made, up to one that fails
        if failed is None:
            self._add(writer, pending)
            return
        # the steps before it are written; it and the steps after it are not
        self._failed = True
        self._seq = pending[failed[0]].seq
        try:
            self._add(writer, pending[: failed[0]])
        finally:
            discard = getattr(self._scene, "discard", None)
            if discard is not None:
                discard()  # the safety records of the steps not written
        raise failed[1]

    def _add(self, writer: Writer, pending: list[_Pending]) -> None:
        """Encode these pending steps as one batch and add their messages."""
        if not pending:
            return
        columns: list[dict[str, np.ndarray]] | None = [] if self._kept is not None else None
        encoded = self._codec.encode_batch([p[:4] for p in pending], columns)
        if self._kept is not None and columns:
            self._kept.append(Recording(path=None, meta={}, complete=True, **columns[0]))
        for (step, seq, _, _, log_ns, stamp, _), (hands, data) in zip(pending, encoded):
            if hands is not None:
                writer.add_message(
                    channel_id=self._hands_channel,
                    log_time=log_ns,
                    publish_time=stamp,
                    data=hands,
                    sequence=seq,
                )
            writer.add_message(
                channel_id=self._channel,
                log_time=log_ns,
                publish_time=stamp,
                data=data,
                sequence=seq,
            )
            if self._scene is not None:
                self._scene.write(writer, step, log_ns)
        self._written_t = pending[-1].t

    def write(self, step: StepRecord) -> None:
        """Append one control step.

        Args:
            step: The step; its ``t`` must be later than the previous step's.

        Raises:
            RecordingError: Not a :class:`StepRecord`, time not increasing, or closed.
        """
        if not isinstance(step, StepRecord):
            raise RecordingError(f"write() takes a StepRecord, got {type(step).__name__}")
        self._append(step.t, step)

    def write_later(self, t: float, build: Callable[..., StepRecord], *args: Any) -> None:
        """Append the control step at time ``t`` that ``build(*args)`` makes, made at the
        next flush with the other steps of the batch (the trial runner's observer).

        The same step as ``write(build(*args))``, in the same place in the file, with the
        same wall-clock time (taken now): only the making waits. Made one after the other
        at a flush, about 50 steps cost half what they cost made one at a time between the
        loop's other work (docs/speed-log.md, item 19). ``args`` must stay as they are until
        then: the loop's snapshots (frozen or fresh arrays), not buffers reused.

        Raises:
            RecordingError: ``t`` not after the previous step's, or closed; at a flush, a
                step that ``build`` could not make (its error, naming the step's time),
                after the steps before it were written; the steps after it are dropped and
                the recorder takes no more steps (:meth:`write_meta` and :meth:`close`
                still work).
        """
        self._append(float(t), (build, args))

    def _append(self, t: float, step: Any) -> None:
        """Append a step at time ``t`` (a :class:`StepRecord`, or ``(build, args)`` to make
        it at the flush) to the batch, and flush when due."""
        if self._failed:
            raise RecordingError(f"{self.path}: a step could not be recorded; no more steps")
        if t <= self._last_t:
            raise RecordingError(
                f"step t = {t} s is not after the previous step (t = {self._last_t} s)"
            )
        self._require_open()
        wall_ns = self._clock()
        stamp = max(0, round(t * 1e9))
        if self._t0_ns is None:
            self._t0_ns = wall_ns - stamp
        log_ns = max(0, self._t0_ns + stamp)
        hands = self._hands if self._hands is not None and self._hands[0] == self._seq else None
        self._hands = None
        # encoded and added at the next flush, in this order, as a batch (same messages)
        held = None if hands is None else hands[1]
        self._pending.append(_Pending(step, self._seq, wall_ns * 1e-9, held, log_ns, stamp, t))
        self._seq += 1
        self._last_t = t
        if self._flush_t == -math.inf:
            self._flush_t = t
        now = time.monotonic()
        if (
            now - self._flush_wall >= self.flush_period_s
            or t - self._flush_t >= self.flush_period_s
            or self._seq == 1
        ):
            self.flush()
            self._flush_t = t

    def write_hands(self, frame: Any) -> None:
        """Record the raw hand frame of the next step (call before :meth:`write`).

        The frame goes to the ``/trial/hands`` channel with the next step's sequence
        number; a replay of the recording feeds these frames to the pipeline bit for bit.

        Args:
            frame: A :class:`~payload.teleop.hands.HandFrame` in the workbench convention.
        """
        if getattr(frame, "frame", "workbench") != "workbench":
            raise RecordingError("write_hands: frames must be in the workbench convention")
        self._hands = (self._seq, frame)

    def write_meta(self, meta: dict[str, Any]) -> None:
        """Store trial metadata (seed, design hash, operator parameters, calibration, ...).

        May be called more than once; the reader merges the dicts in order. Values must be
        JSON-serialisable (numpy arrays and scalars are converted).

        Raises:
            RecordingError: A key is not a string or a value cannot be serialised.
        """
        writer = self._require_open()
        data: dict[str, str] = {}
        for key, value in meta.items():
            if not isinstance(key, str):
                raise RecordingError(f"write_meta: key {key!r} is not a string")
            try:
                data[key] = json.dumps(value, default=_json_default, allow_nan=False)
            except (TypeError, ValueError) as exc:
                raise RecordingError(f"write_meta: value of {key!r} is not JSON: {exc}") from exc
        try:
            self._drain()  # the steps before it stay before it in the file
        finally:  # a step that could not be made is raised after the metadata is in
            self._meta.update({key: json.loads(text) for key, text in data.items()})
            data[META_CRC_KEY] = metadata_crc(data)
            writer.add_metadata(META_NAME, data)
            self.flush()

    def recording(self) -> Recording:
        """What :func:`read_recording` reads back from the closed file, from what was
        written (the same arrays, bit for bit, and the same metadata), without reading it.

        Raises:
            RecordingError: The recorder was made without ``keep``, is not closed, or
                wrote no step (the reader refuses such a file: no step channel).
        """
        if self._kept is None:
            raise RecordingError("recording(): the recorder was not asked to keep its steps")
        if not self._closed:
            raise RecordingError("recording(): close the recorder first")
        parts = self._kept
        if not parts:
            raise RecordingError(f"{self.path}: no step was written")
        columns = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in dataclasses.fields(Recording)
            if f.name not in ("path", "meta", "complete")
        }
        return Recording(path=self.path, meta=dict(self._meta), complete=True, **columns)

    def _require_open(self) -> Writer:
        if self._writer is None:
            if self._closed:
                raise RecordingError(f"{self.path}: recorder already closed")
            self.open()
        assert self._writer is not None
        return self._writer


def _at(t: float, what: str, cause: BaseException | None = None) -> RecordingError:
    """The error of the deferred step at time ``t`` that could not be made (its cause
    chained)."""
    error = RecordingError(f"step at t = {t} s: {what}")
    error.__cause__ = cause
    return error


class _Pending(NamedTuple):
    """A step written and not yet encoded (:meth:`TrialRecorder.write`, ``write_later``);
    its first four fields are what the codec's batch takes."""

    step: Any  # a StepRecord, or (build, args) to make one at the flush
    seq: int
    wall_s: float  # the wall clock when written [s]
    hands: Any  # the raw hand frame recorded with it, or None
    log_ns: int  # MCAP log time [ns]
    stamp: int  # MCAP publish time: the step's time [ns]
    t: float  # the step's time [s]


def _built(pending: list[_Pending]) -> tuple[int, RecordingError] | None:
    """Make the deferred steps of a batch (:meth:`TrialRecorder.write_later`) in place, in
    order; at the first that fails, its index and a :class:`RecordingError` naming the
    step's time and what went wrong (``build``'s own error chained as its cause).

    A ``build`` with a ``many`` attribute (``many(calls) -> steps``, each call's
    ``build(*args)`` in order: :func:`payload.trials.stepobserver.step_records`) makes a
    run of its steps at once; if it raises, or makes other than those steps, they are
    made one at a time, which finds the one that fails."""
    runs: dict[int, tuple[Any, list[int]]] = {}  # by the build's identity
    for i, item in enumerate(pending):
        step = item.step
        if type(step) is tuple and getattr(step[0], "many", None) is not None:
            runs.setdefault(id(step[0]), (step[0], []))[1].append(i)
    for build, where in runs.values():
        try:
            made = list(build.many([pending[i].step[1] for i in where]))
        except Exception:  # made one at a time below, which says which step and why
            continue
        if len(made) == len(where) and all(
            isinstance(m, StepRecord) and m.t == pending[i].t for m, i in zip(made, where)
        ):
            for m, i in zip(made, where):
                pending[i] = pending[i]._replace(step=m)
    for i, item in enumerate(pending):
        step, t = item.step, item.t
        if type(step) is not tuple:
            continue
        build, args = step
        try:
            made = build(*args)
        except RecordingError as exc:
            return i, _at(t, str(exc), exc)
        except Exception as exc:  # raised once the steps before it are written
            return i, _at(t, f"{type(exc).__name__}: {exc}", exc)
        if not isinstance(made, StepRecord):
            return i, _at(t, f"made a {type(made).__name__}, not a StepRecord")
        if made.t != t:
            return i, _at(t, f"made the step at t = {made.t} s")
        pending[i] = item._replace(step=made)
    return None


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


__all__ = [
    "FIELD_SPECS",
    "HANDS_TOPIC",
    "LIBRARY",
    "META_NAME",
    "MODULES",
    "N_HAND_JOINTS",
    "PHASES",
    "SCHEMA_VERSION",
    "STEP_SCHEMA",
    "STEP_SCHEMA_NAME",
    "STEP_TOPIC",
    "Recording",
    "RecordingError",
    "StepRecord",
    "TrialRecorder",
    "random_step",
    "read_hand_frames",
    "read_recording",
    "recording_version",
]
