"""What a trial recording holds: the file layout, the step record and its schema.

The writer is :class:`payload.trials.recorder.TrialRecorder`, the reader
:func:`payload.trials.reading.read_recording`; both re-exported by :mod:`payload.trials.recorder`.

File layout (``log.mcap``, schema version 3)
--------------------------------------------
* Profile ``""``, library ``payload-workbench``. Messages go into zstd-compressed chunks;
  the chunk in progress is closed and the file flushed at least once per
  ``flush_period_s`` (default 1 s) of wall-clock time *and* of recorded time, so a process
  killed with SIGKILL loses at most the last second; :func:`read_recording` reads such a
  file (no summary or footer, possibly a torn last chunk) up to the last complete record.
  The summary holds chunk indexes, so indexed readers (Foxglove) seek without a scan.
* Channel ``/trial/step``, encoding ``protobuf``, schema ``payload.trials.Step`` (declared
  in :mod:`payload.trials.codec`): one message per control step, every field below,
  the numbers on the grids of :data:`payload.trials.stepgrid.STEP_GRIDS` (10 nm, 1 ns, ...).
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
* The version is the ``schema_version`` of the ``/trial/step`` channel's metadata
  (:func:`payload.trials.reading.recording_version`). Version 3 stores the step numbers
  on the grids (``grid``/``grid_key``, leaving the ``double`` fields empty); version 2
  stored every number as a lossless ``double`` (a generic protobuf decoder of a version 3
  step sees zeros there and must apply the grids). Both read, the same way. Version 1
  recordings (one JSON message per step, ``jsonschema`` schema :data:`STEP_SCHEMA`,
  ``hands.jsonl`` beside them) still read too; ``payload trials convert`` rewrites them in
  the current version. A version newer than this reader's is refused with a clear
  message.

Step message fields (all SI, workbench frame)
---------------------------------------------
=================  =========  ============================================================
field              shape      meaning
=================  =========  ============================================================
``seq``            int        step counter from 0 (added by the recorder)
``wall_time``      float      wall clock at write [s since the Unix epoch] (added; 1 us grid)
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
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.schema import N_MANIPULATION
from payload.teleop.hands import XR_JOINTS
from payload.vecmath import F64, add_reduce

PHASES: tuple[str, ...] = (
    "calibration",
    "acquisition",
    "translation",
    "turn",
    "arrival",
    "braking",
)
"""Task phases a step can be in (the paper's four plus calibration and braking)."""

CALIBRATION = PHASES[0]
"""The phase before teleoperation (``calibration``): no metric's or episode's steps."""

MODULES: tuple[str, ...] = ("kibo", "hatch", "node2", "outside")
"""Where the CTB centre of mass is: a module, the hatch between them, or outside both."""

MODULE_NAMES = {"kibo": "kibo", "vestibule": "hatch", "node2": "node2"}
"""The recorded name (:data:`MODULES`) of each ISS module (``payload.sim.iss.IssModule``'s
values), in the steps' ``ctb_module`` and the trial metadata's ``modules``."""

N_HAND_JOINTS = len(XR_JOINTS)
"""WebXR XRHand joints per hand."""

STEP_TOPIC = "/trial/step"
HANDS_TOPIC = "/trial/hands"
STEP_SCHEMA_NAME = "payload.trials.StepRecord"
META_NAME = "payload.trial"
SCHEMA_VERSION = 3
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


class DamagedRecordingError(RecordingError):
    """A recording's bytes are damaged (a CRC mismatch, a corrupt record, missing steps,
    not MCAP): what it says cannot be trusted, so nothing is scored from it."""


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


def _coerce(name: str, value: Any, shape: Any = None, kind: Any = None) -> Any:
    if shape is None:
        shape, kind = FIELD_SPECS[name]
    if shape and type(value) is np.ndarray and value.dtype == np.float64 and value.shape == shape:
        return _finite_copy(name, value.copy(), kind)  # the common case, checked first
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
    return _finite_copy(name, arr, kind)


def _finite_copy(name: str, arr: np.ndarray, kind: Any) -> np.ndarray:
    """``arr`` (a float64 array of its own) checked and made read-only."""
    # a finite sum means every value is finite (NaN and inf propagate); only when it is
    # not are the values checked one by one (an overflowing sum of finite values passes)
    if not math.isfinite(arr.sum()):
        bad = np.isinf(arr) if kind == "float_nan" else ~np.isfinite(arr)
        if np.any(bad):
            where = np.argwhere(bad)[0]
            raise RecordingError(f"StepRecord.{name}: non-finite value(s) at {where}")
    arr.setflags(write=False)
    return arr


_FIELDS: tuple[tuple[str, tuple[int, ...], Any], ...] = tuple(
    (name, shape, kind) for name, (shape, kind) in FIELD_SPECS.items()
)
# The array fields, NaN-allowed ones first, each with its place in one shared buffer: the
# common case (float64 arrays of the right shapes, as the trial loop hands them) is copied
# into that buffer in one go and checked with one sum per kind (see StepRecord.__post_init__)
_ARRAYS = sorted(
    ((name, shape, kind) for name, shape, kind in _FIELDS
     if shape and kind in ("float", "float_nan")),
    key=lambda field: field[2] != "float_nan",
)  # fmt: skip
_ARRAY_SLICES: tuple[tuple[str, int, int, tuple[int, ...]], ...] = tuple(
    (name, start, start + math.prod(shape), shape)
    for (name, shape, _), start in zip(
        _ARRAYS, itertools.accumulate((math.prod(f[1]) for f in _ARRAYS), initial=0)
    )
)
_NAN_END = sum(math.prod(shape) for _, shape, kind in _ARRAYS if kind == "float_nan")
_VIEWS: tuple[tuple[str, slice, tuple[int, ...] | None], ...] = tuple(
    (name, slice(start, stop), shape if len(shape) > 1 else None)
    for name, start, stop, shape in _ARRAY_SLICES
)
"""Each array field's part of the shared buffer, and the shape to view it in (None: a
vector, the part's own shape)."""
_OTHER_FIELDS: tuple[tuple[str, tuple[int, ...], Any, type], ...] = tuple(
    (name, shape, kind, str if isinstance(kind, tuple) else bool if kind == "bool" else float)
    for name, shape, kind in _FIELDS
    if (name, shape, kind) not in _ARRAYS
)
"""The scalar fields with the type they keep (a string of the allowed ones, a bool, a float)."""


_FIELD_NAMES = frozenset(FIELD_SPECS)
_QUATERNION_FIELDS = ("astrobee_quat", "ctb_quat")
"""The fields a step checks are not a zero quaternion."""
QUAT_MIN_NORM = 1e-9
"""A step's quaternion with a smaller norm is refused as zero."""
_QUAT_BATCH_MIN = (10 * QUAT_MIN_NORM) ** 2
"""The squared norm every quaternion of a batch (:meth:`StepRecord.many`) must exceed:
ten times the check's norm, so that no rounding of the batch's sum decides it."""
_QUATERNIONS = tuple(
    (start, stop) for name, start, stop, _ in _ARRAY_SLICES if name in _QUATERNION_FIELDS
)
"""The quaternion fields' parts of the buffer (:meth:`StepRecord._check_quaternions`)."""


def _common_arrays(arrays: list[Any]) -> bool:
    """Whether every array field is a float64 numpy array of its shape (the loop's case)."""
    for a, (_, _, _, shape) in zip(arrays, _ARRAY_SLICES):
        if type(a) is not np.ndarray or a.dtype != F64 or a.shape != shape:
            return False
    return True


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
        fields = self.__dict__  # a frozen dataclass's fields, set as object.__setattr__ does
        arrays = [fields[name] for name, _, _, _ in _ARRAY_SLICES]
        if _common_arrays(arrays):
            # one copy of every array field into one read-only buffer, each field a view
            # of its part; a sum per kind that is not finite sends the fields through the
            # per-field checks below, which say what is wrong (or pass an overflowing sum)
            buf = np.concatenate(arrays, axis=None)  # each flattened in C order
            untracked = buf[:_NAN_END]  # NaN allowed (not tracked), infinities not
            if math.isfinite(add_reduce(buf[_NAN_END:])) and (  # ndarray.sum's reduction
                math.isfinite(add_reduce(untracked)) or not np.isinf(untracked).any()
            ):
                buf.setflags(write=False)
                for name, part, shape in _VIEWS:
                    fields[name] = buf[part] if shape is None else buf[part].reshape(shape)
                for name, shape, kind, kept in _OTHER_FIELDS:
                    value = fields[name]
                    if type(value) is not kept or not (  # the loop's own types pass as they are
                        value in kind if kept is str else kept is bool or math.isfinite(value)
                    ):
                        fields[name] = _coerce(name, value, shape, kind)
                self._check_quaternions()
                return
        for name, shape, kind in _FIELDS:
            fields[name] = _coerce(name, fields[name], shape, kind)
        self._check_quaternions()

    def _check_quaternions(self) -> None:
        for name in _QUATERNION_FIELDS:
            q = self.__dict__[name]
            if math.sqrt(q.dot(q)) < QUAT_MIN_NORM:  # np.linalg.norm's own formula
                raise RecordingError(f"StepRecord.{name}: zero quaternion")

    @classmethod
    def many(cls, steps: list[dict[str, Any]]) -> list[StepRecord]:
        """``[StepRecord(**fields) for fields in steps]``, made as a batch: the same steps
        (each array field a read-only view of its own values, equal to the bit) and the
        same errors, for less (a trial's recorder makes about 50 at each flush).

        When every step is the loop's common case (each array field numbers of its shape,
        every value finite where it must be, each scalar of the type it keeps, each
        quaternion's norm above ten times :data:`QUAT_MIN_NORM`, the check's), the arrays
        are copied into one buffer, a row a step, and checked with one sum per kind and
        row; otherwise each step is made on its own, which converts what
        :class:`StepRecord` converts and raises what it raises.
        """
        n = len(steps)
        if n == 0:
            return []
        buf = np.empty((n, _ARRAY_SLICES[-1][2]))
        try:
            for name, start, stop, shape in _ARRAY_SLICES:
                # np.array converts as a step's own conversion does (a float64 copy), and
                # any value not of the field's shape leaves the batch another shape
                values = np.array([fields[name] for fields in steps])
                if values.dtype != F64 or values.shape != (n, *shape):
                    raise TypeError(name)
                buf[:, start:stop] = values.reshape(n, stop - start)
            untracked = buf[:, :_NAN_END]
            whole = bool(np.isfinite(add_reduce(buf[:, _NAN_END:], axis=1)).all()) and (
                bool(np.isfinite(add_reduce(untracked, axis=1)).all())
                or not np.isinf(untracked).any()
            )
            if not whole:
                raise ValueError("not finite")
            for start, stop in _QUATERNIONS:  # clear of the check's threshold on every row
                if not (add_reduce(buf[:, start:stop] ** 2, axis=1) > _QUAT_BATCH_MIN).all():
                    raise ValueError("a quaternion near zero")
            for fields in steps:
                if fields.keys() != _FIELD_NAMES:
                    raise TypeError("fields")
                for name, _, kind, kept in _OTHER_FIELDS:
                    value = fields[name]
                    if type(value) is not kept or not (
                        value in kind if kept is str else kept is bool or math.isfinite(value)
                    ):
                        raise TypeError(name)
        except Exception:  # anything the batch cannot take: each step as it would be made
            return [cls(**fields) for fields in steps]  # converted, or its error raised
        buf.setflags(write=False)
        # each field's rows as views (the step's read-only arrays), a column at a time
        names = [name for name, _, _ in _VIEWS]
        columns = [
            list(buf[:, part] if shape is None else buf[:, part].reshape(n, *shape))
            for _, part, shape in _VIEWS
        ]
        made = []
        for fields, views in zip(steps, zip(*columns)):
            step = object.__new__(cls)  # a frozen dataclass's fields, as __post_init__ sets
            own = step.__dict__
            own.update(fields)
            own.update(zip(names, views))
            made.append(step)
        return made

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
        "q_cmd": rng.normal(size=N_MANIPULATION),
        "deploy_cmd": d.stage.travel,
        "q_meas": rng.normal(size=N_MANIPULATION),
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
