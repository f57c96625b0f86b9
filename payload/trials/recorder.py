"""Crash-safe, compact trial recording: one MCAP file per trial, one protobuf message per step.

File layout (``log.mcap``, schema version 2)
--------------------------------------------
* Profile ``""``, library ``payload-workbench``. Messages go into zstd-compressed chunks;
  the chunk in progress is closed and the file flushed at least once per
  ``flush_period_s`` (default 1 s) of wall-clock time *and* of recorded time, so a process
  killed with SIGKILL loses at most the last second; :func:`read_recording` reads such a
  file (no summary or footer, possibly a torn last chunk) up to the last complete record.
  The summary holds chunk indexes, so indexed readers (Foxglove) seek without a scan.
* Channel ``/trial/step``, encoding ``protobuf``, schema ``payload.trials.Step`` (declared
  in :mod:`payload.trials.codec`): one message per control step, every field below,
  doubles lossless.
* Channel ``/trial/hands``, schema ``payload.trials.HandSample``: the raw hand frame the
  pipeline saw at that step (stamp, tracked flags, 25 x 3 joints, lossless), written by
  :meth:`TrialRecorder.write_hands`; the step then refers to it instead of repeating the
  joints. ``payload trial --operator replay log.mcap`` replays it bit for bit.
* The standard Foxglove channels of :mod:`payload.trials.foxglove` when the recorder has
  a scene (the trial runner's recordings do).
* Message ``log_time`` is the wall clock at the first step plus the step time, so every
  channel shares one timeline in simulated time [ns since the Unix epoch];
  ``publish_time`` is the step time ``t`` [ns since the start of teleoperation]; the
  wall clock at write is the step's ``wall_time``.
* Metadata records named ``payload.trial`` (see :meth:`TrialRecorder.write_meta`): each
  value is JSON text (trial seed, design hash, operator parameters, calibration, ...).
* Schema version 1 recordings (one JSON message per step, ``jsonschema`` schema
  :data:`STEP_SCHEMA`, ``hands.jsonl`` beside them) still read; ``payload trials convert``
  rewrites them in version 2.

Step message fields (all SI, workbench frame)
---------------------------------------------
=================  =========  ============================================================
field              shape      meaning
=================  =========  ============================================================
``seq``            int        step counter from 0 (added by the recorder)
``wall_time``      float      wall clock at write [s since the Unix epoch] (added)
``t``              float      time since the start of teleoperation [s]
``phase``          str        one of :data:`PHASES`
``left_joints``    (25, 3)    raw WebXR hand-joint positions [m], ``null`` = not tracked
``right_joints``   (25, 3)    same for the right hand
``left_tracked``   bool       left hand tracked this step
``right_tracked``  bool       right hand tracked this step
``q_left``         (8,)       finger channel, pair L = (A, C): A then C, each
                              [mcp_flex, mcp_abd, pip, dip] [rad]
``q_right``        (8,)       finger channel, pair R = (B, D), same order [rad]
``rail_cmd``       float      rail channel command [m]
``twist_cmd``      (6,)       base channel: linear xyz [m/s], angular xyz [rad/s], body frame
``q_cmd``          (17,)      commanded manipulation coordinates, paper order [rad, rail m]
``deploy_cmd``     float      commanded deployment (stage) coordinate [m]
``q_meas``         (17,)      measured manipulation coordinates [rad, rail m]
``deploy_meas``    float      measured deployment coordinate [m]
``astrobee_pos``   (3,)       Astrobee body origin in the world [m]
``astrobee_quat``  (4,)       Astrobee orientation, w x y z, body -> world
``astrobee_twist`` (6,)       world linear velocity [m/s], body angular velocity [rad/s]
``ctb_pos``        (3,)       CTB centre of mass in the world [m]
``ctb_quat``       (4,)       CTB orientation, w x y z, CTB -> world
``contact``        bool       opposing-contact indicator (CTB touches fingertips of both sides)
``ctb_module``     str        one of :data:`MODULES`
=================  =========  ============================================================
"""

from __future__ import annotations

import functools
import io
import json
import logging
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from google.protobuf.message import DecodeError
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from payload.errors import PayloadError
from payload.schema import N_MANIPULATION
from payload.teleop.hands import XR_JOINTS
from payload.trials import codec
from payload.trials.stepcheck import StepError, check_step

log = logging.getLogger(__name__)

PHASES: tuple[str, ...] = (
    "calibration",
    "acquisition",
    "translation",
    "turn",
    "arrival",
    "braking",
)
"""Task phases a step can be in (the paper's four plus calibration and braking)."""

MODULES: tuple[str, ...] = ("kibo", "hatch", "node2", "outside")
"""Where the CTB centre of mass is: a module, the hatch between them, or outside both."""

N_HAND_JOINTS = 25
"""WebXR XRHand joints per hand."""

STEP_TOPIC = "/trial/step"
HANDS_TOPIC = "/trial/hands"
STEP_SCHEMA_NAME = "payload.trials.StepRecord"
META_NAME = "payload.trial"
SCHEMA_VERSION = 2
LIBRARY = "payload-workbench"

# name -> (shape, kind); shape () is a scalar. kind: "float" (finite), "float_nan" (NaN
# allowed, stored as null), "bool", or a tuple of allowed strings.
FIELD_SPECS: dict[str, tuple[tuple[int, ...], Any]] = {
    "t": ((), "float"),
    "phase": ((), PHASES),
    "left_joints": ((N_HAND_JOINTS, 3), "float_nan"),
    "right_joints": ((N_HAND_JOINTS, 3), "float_nan"),
    "left_tracked": ((), "bool"),
    "right_tracked": ((), "bool"),
    "q_left": ((8,), "float"),
    "q_right": ((8,), "float"),
    "rail_cmd": ((), "float"),
    "twist_cmd": ((6,), "float"),
    "q_cmd": ((N_MANIPULATION,), "float"),
    "deploy_cmd": ((), "float"),
    "q_meas": ((N_MANIPULATION,), "float"),
    "deploy_meas": ((), "float"),
    "astrobee_pos": ((3,), "float"),
    "astrobee_quat": ((4,), "float"),
    "astrobee_twist": ((6,), "float"),
    "ctb_pos": ((3,), "float"),
    "ctb_quat": ((4,), "float"),
    "contact": ((), "bool"),
    "ctb_module": ((), MODULES),
}
"""Every step field with its shape and kind; the one table the schema, the validation and
the reader are built from."""


class RecordingError(PayloadError):
    """A step record is malformed, or a recording cannot be written or read."""


def _json_schema_for(shape: tuple[int, ...], kind: Any) -> dict[str, Any]:
    if isinstance(kind, tuple):
        return {"type": "string", "enum": list(kind)}
    if kind == "bool":
        return {"type": "boolean"}
    item: dict[str, Any] = (
        {"type": ["number", "null"]} if kind == "float_nan" else {"type": "number"}
    )
    for n in reversed(shape):
        item = {"type": "array", "items": item, "minItems": n, "maxItems": n}
    return item


STEP_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": STEP_SCHEMA_NAME,
    "description": (
        "One 50 Hz control step of a cargo-transport trial. SI units, workbench frame "
        "(REP-103); quaternions w x y z; null = not tracked. See payload/trials/recorder.py."
    ),
    "type": "object",
    "properties": {
        "seq": {"type": "integer", "minimum": 0},
        "wall_time": {"type": "number"},
        **{name: _json_schema_for(shape, kind) for name, (shape, kind) in FIELD_SPECS.items()},
    },
    "required": ["seq", "wall_time", *FIELD_SPECS],
    "additionalProperties": True,
    "x-version": SCHEMA_VERSION,
}
"""The JSON schema stored in every recording for the ``/trial/step`` channel."""


def _coerce(name: str, value: Any) -> Any:
    shape, kind = FIELD_SPECS[name]
    if isinstance(kind, tuple):
        if not isinstance(value, str) or value not in kind:
            raise RecordingError(f"StepRecord.{name}: {value!r} is not one of {list(kind)}")
        return value
    if kind == "bool":
        if isinstance(value, np.ndarray) and value.shape == ():
            value = value.item()
        if not isinstance(value, (bool, np.bool_)):
            raise RecordingError(f"StepRecord.{name}: expected a bool, got {type(value).__name__}")
        return bool(value)
    if shape == ():
        try:
            out = float(value)
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"StepRecord.{name}: expected a number, got {value!r}") from exc
        if not math.isfinite(out):
            raise RecordingError(f"StepRecord.{name}: not finite ({out})")
        return out
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"StepRecord.{name}: not numeric") from exc
    if arr.shape != shape:
        raise RecordingError(f"StepRecord.{name}: expected shape {shape}, got {arr.shape}")
    bad = np.isinf(arr) if kind == "float_nan" else ~np.isfinite(arr)
    if np.any(bad):
        raise RecordingError(f"StepRecord.{name}: non-finite value(s) at {np.argwhere(bad)[0]}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class StepRecord:
    """Everything recorded at one 50 Hz control step (units and frames: module docstring).

    Arrays are converted to read-only float64 numpy arrays and checked for shape and
    finiteness (only the raw hand joints may be NaN, meaning "not tracked").

    Attributes:
        t: Time since the start of teleoperation [s].
        phase: One of :data:`PHASES`.
        left_joints: Raw left-hand joint positions, shape (25, 3) [m], NaN if untracked.
        right_joints: Raw right-hand joint positions, shape (25, 3) [m].
        left_tracked: Whether the left hand was tracked.
        right_tracked: Whether the right hand was tracked.
        q_left: Finger-channel command for pair L = (A, C), shape (8,) [rad].
        q_right: Finger-channel command for pair R = (B, D), shape (8,) [rad].
        rail_cmd: Rail-channel command [m].
        twist_cmd: Base-channel command, shape (6,): linear [m/s], angular [rad/s], body.
        q_cmd: Commanded manipulation coordinates, shape (17,), paper order.
        deploy_cmd: Commanded deployment coordinate [m].
        q_meas: Measured manipulation coordinates, shape (17,).
        deploy_meas: Measured deployment coordinate [m].
        astrobee_pos: Astrobee position in the world, shape (3,) [m].
        astrobee_quat: Astrobee orientation (w, x, y, z), body -> world, shape (4,).
        astrobee_twist: World linear [m/s] and body angular [rad/s] velocity, shape (6,).
        ctb_pos: CTB centre of mass in the world, shape (3,) [m].
        ctb_quat: CTB orientation (w, x, y, z), shape (4,).
        contact: The opposing-contact indicator.
        ctb_module: One of :data:`MODULES`.
    """

    t: float
    phase: str
    left_joints: np.ndarray
    right_joints: np.ndarray
    left_tracked: bool
    right_tracked: bool
    q_left: np.ndarray
    q_right: np.ndarray
    rail_cmd: float
    twist_cmd: np.ndarray
    q_cmd: np.ndarray
    deploy_cmd: float
    q_meas: np.ndarray
    deploy_meas: float
    astrobee_pos: np.ndarray
    astrobee_quat: np.ndarray
    astrobee_twist: np.ndarray
    ctb_pos: np.ndarray
    ctb_quat: np.ndarray
    contact: bool
    ctb_module: str

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _coerce(f.name, getattr(self, f.name)))
        for name in ("astrobee_quat", "ctb_quat"):
            if np.linalg.norm(getattr(self, name)) < 1e-9:
                raise RecordingError(f"StepRecord.{name}: zero quaternion")

    def to_json_dict(self) -> dict[str, Any]:
        """The step as JSON-ready data (NaN -> ``None``)."""
        out: dict[str, Any] = {}
        for name, (_, kind) in FIELD_SPECS.items():
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                value = value.tolist()
                if kind == "float_nan":
                    value = [[None if v != v else v for v in row] for row in value]
            out[name] = value
        return out


@functools.lru_cache(maxsize=1)
def _default_design() -> Any:
    from payload.design import load_design

    return load_design()


def random_step(rng: np.random.Generator, t: float, **fields: Any) -> StepRecord:
    """An arbitrary but valid step at time ``t`` (benchmarks and format tests).

    Joint commands and poses are random draws; the rail and stage values lie inside the
    default design's travel; ``fields`` override any attribute.
    """
    d = _default_design()
    q = rng.normal(size=4)
    values: dict[str, Any] = {
        "t": t,
        "phase": "translation",
        "left_joints": rng.normal(scale=0.05, size=(25, 3)),
        "right_joints": rng.normal(scale=0.05, size=(25, 3)),
        "left_tracked": True,
        "right_tracked": True,
        "q_left": rng.normal(size=8),
        "q_right": rng.normal(size=8),
        "rail_cmd": float(rng.uniform(0, d.rail.travel)),
        "twist_cmd": rng.normal(size=6),
        "q_cmd": rng.normal(size=17),
        "deploy_cmd": d.stage.travel,
        "q_meas": rng.normal(size=17),
        "deploy_meas": float(rng.uniform(0, d.stage.travel)),
        "astrobee_pos": rng.normal(size=3),
        "astrobee_quat": q / np.linalg.norm(q),
        "astrobee_twist": rng.normal(size=6),
        "ctb_pos": rng.normal(size=3),
        "ctb_quat": np.array([1.0, 0.0, 0.0, 0.0]),
        "contact": True,
        "ctb_module": "kibo",
    }
    values.update(fields)
    return StepRecord(**values)


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
    ) -> None:
        if not (0.0 < flush_period_s <= 1.0):
            raise RecordingError(f"flush_period_s must be in (0, 1] s, got {flush_period_s}")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise RecordingError(f"{self.path}: already exists (pass overwrite=True to replace)")
        self.flush_period_s = float(flush_period_s)
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

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> TrialRecorder:
        """Create the file and write the header, schema and channel (idempotent)."""
        if self._writer is not None:
            return self
        if self._closed:
            raise RecordingError(f"{self.path}: recorder already closed")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # a large buffer (few write calls); the flush deadline bounds what a crash loses
        self._file = open(self.path, "wb", buffering=1 << 20)  # closed in close()
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
        """Write the summary and footer and close the file (idempotent)."""
        if self._writer is not None:
            self._writer.finish()
            self._file.close()
            self._writer = None
            self._file = None
        self._closed = True

    def __enter__(self) -> TrialRecorder:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None and self._writer is not None:
            # the run died: say so in the file, so nobody scores it as a finished trial
            try:
                self.write_meta({"aborted": f"{exc_type.__name__}: {exc}"})
            except RecordingError:
                pass
        self.close()

    # -- writing -----------------------------------------------------------------------
    @property
    def n_steps(self) -> int:
        """Steps written so far."""
        return self._seq

    def flush(self) -> None:
        """Push everything written so far to the operating system (survives SIGKILL)."""
        if self._writer is not None:
            self._writer.flush()  # closes the chunk in progress and flushes the file
            self._codec.key()
            self._flush_wall = time.monotonic()

    def write(self, step: StepRecord) -> None:
        """Append one control step.

        Args:
            step: The step; its ``t`` must be later than the previous step's.

        Raises:
            RecordingError: Not a :class:`StepRecord`, time not increasing, or closed.
        """
        if not isinstance(step, StepRecord):
            raise RecordingError(f"write() takes a StepRecord, got {type(step).__name__}")
        if step.t <= self._last_t:
            raise RecordingError(
                f"step t = {step.t} s is not after the previous step (t = {self._last_t} s)"
            )
        writer = self._require_open()
        wall_ns = self._clock()
        stamp = max(0, round(step.t * 1e9))
        if self._t0_ns is None:
            self._t0_ns = wall_ns - stamp
        log_ns = max(0, self._t0_ns + stamp)
        hands = self._hands if self._hands is not None and self._hands[0] == self._seq else None
        in_hands = (False, False)
        if hands is not None:
            frame = hands[1]
            in_hands = (
                codec.same_joints(frame.left.joints, step.left_joints),
                codec.same_joints(frame.right.joints, step.right_joints),
            )
            writer.add_message(
                channel_id=self._hands_channel,
                log_time=log_ns,
                publish_time=stamp,
                data=self._codec.encode_hands(frame, self._seq),
                sequence=self._seq,
            )
        self._hands = None
        writer.add_message(
            channel_id=self._channel,
            log_time=log_ns,
            publish_time=stamp,
            data=self._codec.encode_step(step, self._seq, wall_ns * 1e-9, in_hands),
            sequence=self._seq,
        )
        if self._scene is not None:
            self._scene.write(writer, step, log_ns)
        self._seq += 1
        self._last_t = step.t
        if self._flush_t == -math.inf:
            self._flush_t = step.t
        now = time.monotonic()
        if (
            now - self._flush_wall >= self.flush_period_s
            or step.t - self._flush_t >= self.flush_period_s
            or self._seq == 1
        ):
            self.flush()
            self._flush_t = step.t

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
        writer.add_metadata(META_NAME, data)
        self.flush()

    def _require_open(self) -> Writer:
        if self._writer is None:
            if self._closed:
                raise RecordingError(f"{self.path}: recorder already closed")
            self.open()
        assert self._writer is not None
        return self._writer


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


# -- reading ---------------------------------------------------------------------------
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
                arr = np.array(
                    [r[name] for r in rows], dtype=object if kind == "float_nan" else np.float64
                )
                if kind == "float_nan":
                    arr = np.where(arr == None, np.nan, arr).astype(np.float64)  # noqa: E711
                cols[name] = arr.reshape((n, *shape))
        seq = np.array([r.get("seq", i) for i, r in enumerate(rows)], dtype=np.int64)
        wall = np.array([r.get("wall_time", math.nan) for r in rows], dtype=np.float64)
        return Recording(
            path=path, meta=dict(meta or {}), complete=complete, seq=seq, wall_time=wall, **cols
        )

    def step(self, i: int) -> StepRecord:
        """Step ``i`` as a :class:`StepRecord`."""
        return StepRecord(**{name: getattr(self, name)[i] for name in FIELD_SPECS})


def _complete_prefix(data: bytes) -> tuple[int, bool]:
    """Length of the longest prefix made of whole MCAP records, and whether it is closed."""
    magic = b"\x89MCAP0\r\n"
    if not data.startswith(magic):
        raise RecordingError("not an MCAP file (bad magic)")
    pos = len(magic)
    n = len(data)
    while pos + 9 <= n:
        opcode = data[pos]
        length = int.from_bytes(data[pos + 1 : pos + 9], "little")
        end = pos + 9 + length
        if end > n:
            break
        pos = end
        if opcode == 0x02 and data[pos : pos + len(magic)] == magic:  # Footer + magic
            return pos + len(magic), True
    return pos, False


def _decode_meta(items: dict[str, str], path: Path) -> dict[str, Any]:
    out = {}
    for key, value in items.items():
        try:
            out[key] = json.loads(value)
        except ValueError:
            raise RecordingError(f"{path}: metadata {key!r}: expected JSON text") from None
    return out


def _read_file(
    path: Path,
) -> tuple[dict[int, Channel], dict[str, Any], list[dict[str, Any]], list[dict[str, Any]], bool]:
    """Channels, merged metadata, step rows, hand samples and completeness of a file."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such recording") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror})") from exc
    try:
        end, complete = _complete_prefix(data)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    reader = StreamReader(io.BytesIO(data[:end]))
    channels: dict[int, Channel] = {}
    meta: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    hands: dict[int, dict[str, Any]] = {}
    samples: list[dict[str, Any]] = []
    step_codec = codec.StepCodec()
    try:
        for record in reader.records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    continue
                if channel.topic == STEP_TOPIC:
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
        raise RecordingError(f"{path}: {where}: corrupt ({exc})") from None
    return channels, meta, rows, samples, complete


def recording_version(path: str | Path) -> int:
    """Schema version of a recording: 1 (JSON steps) or 2 (protobuf steps).

    Raises:
        RecordingError: Unreadable, or no ``/trial/step`` channel.
    """
    path = Path(path)
    channels = _read_file(path)[0]
    for c in channels.values():
        if c.topic == STEP_TOPIC:
            return 1 if c.message_encoding == "json" else 2
    raise RecordingError(f"{path}: no {STEP_TOPIC} channel (not a trial recording)")


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by :class:`TrialRecorder`, complete or cut short.

    A file whose writer was killed has no summary or footer and may end in a torn record;
    every complete record before that is read.

    Args:
        path: The ``.mcap`` file.

    Returns:
        The recording, with ``complete`` telling whether the file was closed properly.

    Raises:
        RecordingError: The file is missing, is not MCAP, or is a closed MCAP file without a
            ``/trial/step`` channel. (A file cut short before its channel record reads as an
            empty recording.)
    """
    path = Path(path)
    channels, meta, rows, _, complete = _read_file(path)
    if complete and not any(c.topic == STEP_TOPIC for c in channels.values()):
        raise RecordingError(f"{path}: no {STEP_TOPIC} channel (not a trial recording)")
    try:
        for i, row in enumerate(rows):  # every step, not just the first
            check_step(row, FIELD_SPECS, i, str(path))
    except StepError as exc:
        raise RecordingError(str(exc)) from None
    return Recording.from_dicts(rows, meta, path, complete)


def read_hand_frames(path: str | Path) -> tuple[dict[str, Any], list[Any]]:
    """The raw hand frames of a recording's ``/trial/hands`` channel, for a replay.

    Returns:
        (trial metadata, :class:`~payload.teleop.hands.HandFrame` list in recorded order).

    Raises:
        RecordingError: Unreadable file, or no hand channel (a recording from before
            schema version 2: replay its ``hands.jsonl`` instead).
    """
    from payload.teleop.hands import Hand, HandFrame

    path = Path(path)
    channels, meta, _, samples, _ = _read_file(path)
    if not any(c.topic == HANDS_TOPIC for c in channels.values()):
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
    return meta, frames


__all__ = [
    "FIELD_SPECS",
    "MODULES",
    "PHASES",
    "STEP_SCHEMA",
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
