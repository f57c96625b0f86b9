"""Typed, compact step and hand-frame messages for trial recordings (protobuf).

The messages are declared in :mod:`payload.trials.stepmsg` (re-exported here). The schema
stored in every recording is the ``FileDescriptorSet`` of these messages (MCAP
``protobuf`` encoding), so any MCAP tool (``mcap cat``, Foxglove,
``mcap_protobuf.decoder``) decodes them. The grid arithmetic of the step numbers is
:mod:`payload.trials.stepgrid`, the building of a batch's messages (protobuf objects, or
the compiled serialiser's arrays) :mod:`payload.trials.stepbuild`.

``payload.trials.Step`` (channel ``/trial/step``): one message per 50 Hz control step.
Phases and modules are enums. The numbers are stored at a stated resolution
(:data:`STEP_GRIDS`: 10 nm, 1e-10 of a unit quaternion, 1 nm/s, 10 nrad, 1 ns; far below
anything the metrics resolve or the sensors could tell apart): ``grid`` holds, in the
order of :data:`STEP_GRIDS`, each value's integer multiple of its grid minus the previous
message's (zigzag varints), or the multiple itself in a ``grid_key`` message (the first
message after every flush, so each MCAP chunk decodes on its own). A step with a
non-finite number, and the files of earlier versions, store ``double`` fields (packed,
lossless) instead; the reader reads both. The raw hand joints are a
``payload.trials.Joints`` message, or a reference to the ``/trial/hands`` message with the
same sequence number when it holds the same joints.

When ``pairs_in_cmd`` is set, ``q_left``, ``q_right`` and ``rail_cmd`` are not stored:
they are the pair L (A, C) and pair R (B, D) entries and the last entry of ``q_cmd``
(:data:`PAIR_L_INDEX`, :data:`PAIR_R_INDEX`), as the trial runner records them.

``payload.trials.Joints``: 25 x 3 hand-joint positions [m], lossless, in one of three forms:

* ``grid`` > 0: every value is ``k * grid`` for an integer ``k``; ``delta`` holds ``k``
  minus the previous message's ``k`` (the same hand on the same channel), or ``k`` itself
  when ``key`` is set (the first message after every flush is a key message, so each MCAP
  chunk decodes on its own). The trial runner's synthetic headset reports joints on the
  :data:`HAND_GRID_M` grid, so its frames cost about 2 bytes per coordinate.
* ``raw``: 75 doubles (values off any grid, e.g. a replayed double-precision recording).
* ``untracked``: all NaN (no joints).

``payload.trials.HandSample`` (channel ``/trial/hands``): the raw hand frame the pipeline
saw (stamp, tracked flags, joints), so a recording replays bit for bit.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from google.protobuf.message import DecodeError

from payload.schema import N_MANIPULATION
from payload.trials.codec_c import compiled_steps
from payload.trials.jointcodec import (
    HAND_GRID_M,
    JOINTS_SHAPE,
    JointsCodec,
    quantize_joints,
    same_joints,
)
from payload.trials.records import MODULES, PHASES
from payload.trials.stepbuild import (
    StepBatch,
    kernel_arrays,
    pair_fields,
    pairs_in_cmd,
    serialize,
    step_fields,
)
from payload.trials.stepgrid import (
    GRID,
    GRID_SLICES,
    PER_UNIT,
    STEP_GRIDS,
    GridRows,
    gathered,
    grid_fields,
    grid_rows,
)
from payload.trials.stepmsg import (
    FILE_DESCRIPTOR,
    HANDS_MESSAGE,
    PAIR_FIELDS,
    PAIR_L_INDEX,
    PAIR_R_INDEX,
    RAIL_INDEX,
    STEP_DOUBLES,
    STEP_MESSAGE,
    HandSampleMsg,
    JointsMsg,
    StepMsg,
    schema_data,
)


class StepCodec:
    """Encode steps and hand samples to protobuf bytes and back (stateful for the deltas)."""

    def __init__(self, grid: float = HAND_GRID_M) -> None:
        self.joints = {
            name: JointsCodec(grid)
            for name in ("left_joints", "right_joints", "hands_left", "hands_right")
        }
        self.grid = grid
        self._prev: np.ndarray | None = None  # the last step's grid multiples

    def key(self) -> None:
        """The next messages start fresh (call after every flush)."""
        for c in self.joints.values():
            c.key()
        self._prev = None

    def _grid_batch(self, fields: dict[str, np.ndarray], walls: list[float]) -> GridRows:
        """The grid numbers of a batch of steps in turn (:func:`grid_rows`), carrying the
        last step's multiples on to the next batch."""
        rows, self._prev = grid_rows(fields, walls, self._prev)
        return rows

    def encode_batch(
        self,
        items: list[tuple[Any, int, float, Any]],
        columns: list[dict[str, np.ndarray]] | None = None,
    ) -> list[tuple[Any, bytes]]:
        """Several steps (and their hand samples) at once, in order: the bytes that
        :meth:`encode_hands` and :meth:`encode_step` give one at a time, with the grid and
        joint arithmetic done once for the batch (the recorder's flush).

        Args:
            items: Per step ``(step, seq, wall_time, frame)``: ``frame`` the hand frame
                recorded with it (``None``: none); the step's joints refer to the frame's
                where they are the same (:func:`same_joints`).
            columns: If given, gets what the reader will read back from the batch's bytes
                (without decoding them): the columns of a
                :class:`~payload.trials.reading.Recording` (``seq``, ``wall_time`` and every
                step field, one row per step), as :meth:`decode_step`'s rows give them.

        Returns:
            Per step ``(hand sample bytes or None, step bytes)``.
        """
        batch = self._rows(items)
        if columns is not None:
            columns.append(self._columns(items, batch))
        # the runtime refuses a negative sequence number (ValueError): it serialises those
        kernel = _steps_kernel() if items and min(it[1] for it in items) >= 0 else None
        if kernel is not None:
            data = kernel(kernel_arrays(items, batch), self.grid)
            return [
                (data[2 * i] if frame is not None else None, data[2 * i + 1])
                for i, (_, _, _, frame) in enumerate(items)
            ]
        return serialize(items, batch, self.grid)

    def _rows(self, items: list[tuple[Any, int, float, Any]]) -> StepBatch:
        """The numbers a batch stores (the grid and joint arithmetic, done for the batch);
        each step's joints refer to its frame's where they are the same."""
        frames = [(i, f) for i, (_, _, _, f) in enumerate(items) if f is not None]
        hands = tuple(
            self.joints[f"hands_{side}"].encode_many([getattr(f, side).joints for _, f in frames])
            for side in ("left", "right")
        )
        refs = [
            (False, False)
            if frame is None
            else (
                same_joints(frame.left.joints, step.left_joints),
                same_joints(frame.right.joints, step.right_joints),
            )
            for step, _, _, frame in items
        ]
        own = []
        for name, side in (("left_joints", 0), ("right_joints", 1)):
            rows = [i for i, ref in enumerate(refs) if not ref[side]]
            coded = self.joints[name].encode_many([getattr(items[i][0], name) for i in rows])
            own.append(({i: r for r, i in enumerate(rows)}, coded))
        at = {i: r for r, (i, _) in enumerate(frames)}
        fields = gathered([it[0] for it in items])
        grids = self._grid_batch(fields, [it[2] for it in items])
        pairs = np.array([pairs_in_cmd(it[0]) for it in items], dtype=bool).reshape(-1)
        return StepBatch(at, hands, (own[0], own[1]), grids, fields, pairs)

    def _columns(
        self, items: list[tuple[Any, int, float, Any]], batch: StepBatch
    ) -> dict[str, np.ndarray]:
        """What the reader reads back from a batch, column by column: each step's own
        values, its numbers on the grid as the grid's integers give them back, its pair
        fields from its ``q_cmd`` when stored there, its joints as their rows decode."""
        n = len(items)
        steps = [it[0] for it in items]
        cols: dict[str, np.ndarray] = {
            "seq": np.array([it[1] for it in items], dtype=np.int64),
            "wall_time": np.array([it[2] for it in items], dtype=np.float64),
        }
        for name, _, shape in STEP_DOUBLES:
            cols[name] = batch.fields[name].reshape((n, *shape)).copy()
        grids = batch.grids
        ok = grids.ok
        for name, start, stop in GRID_SLICES:
            cols[name][ok] = grids.values[ok, start:stop].reshape(cols[name][ok].shape)
        pairs = batch.pairs
        q = cols["q_cmd"][pairs]
        cols["q_left"][pairs] = q[:, PAIR_L_INDEX]
        cols["q_right"][pairs] = q[:, PAIR_R_INDEX]
        cols["rail_cmd"][pairs] = q[:, RAIL_INDEX]
        for name in ("phase", "ctb_module"):
            cols[name] = np.array([getattr(st, name) for st in steps], dtype=object).astype(str)
        for name in ("left_tracked", "right_tracked", "contact"):
            cols[name] = np.array([bool(getattr(st, name)) for st in steps], dtype=bool)
        for side, name in enumerate(("left_joints", "right_joints")):
            joints = np.empty((n, *JOINTS_SHAPE))
            mine, coded = batch.own[side]
            rows = list(mine)
            joints[rows] = coded.decoded[[mine[i] for i in rows]]
            rest = [i for i in range(n) if i not in mine]
            joints[rest] = batch.hands[side].decoded[[batch.at[i] for i in rest]]
            cols[name] = joints
        return cols

    def _decode_grid(self, m: Any, row: dict[str, Any]) -> None:
        d = np.array(m.grid, dtype=np.int64)
        if m.grid_key:
            k = d
        elif self._prev is None or d.shape != self._prev.shape:
            raise ValueError("a step's numbers refer to a message that is not in the file")
        else:
            k = self._prev + d
        self._prev = k
        grid_fields(row, k / PER_UNIT)

    def encode_step(
        self, step: Any, seq: int, wall_time: float, in_hands: tuple[bool, bool] = (False, False)
    ) -> bytes:
        """A :class:`~payload.trials.recorder.StepRecord` as ``payload.trials.Step`` bytes.

        Args:
            step: The step.
            seq: Its sequence number.
            wall_time: Wall clock at write [s since the Unix epoch].
            in_hands: For each hand, whether the ``/trial/hands`` message of this sequence
                number holds the same joints (they are then not repeated).
        """
        grids = self._grid_batch(gathered([step]), [wall_time])
        m = step_fields(step, seq, wall_time, grids, 0)
        for name, ref in zip(("left_joints", "right_joints"), in_hands):
            sub = getattr(m, name)
            if ref:
                sub.in_hands = True
            else:
                self.joints[name].encode(getattr(step, name), sub)
        return m.SerializeToString()

    def encode_hands(self, frame: Any, seq: int) -> bytes:
        """A :class:`~payload.teleop.hands.HandFrame` as ``payload.trials.HandSample`` bytes."""
        m = HandSampleMsg(seq=seq, stamp=float(frame.stamp))
        m.left_tracked = bool(frame.left.tracked)
        m.right_tracked = bool(frame.right.tracked)
        self.joints["hands_left"].encode(frame.left.joints, m.left)
        self.joints["hands_right"].encode(frame.right.joints, m.right)
        return m.SerializeToString()

    def decode_hands(self, data: bytes) -> dict[str, Any]:
        """``{"seq", "stamp", "left_tracked", "right_tracked", "left", "right"}``."""
        m = HandSampleMsg.FromString(data)
        return {
            "seq": int(m.seq),
            "stamp": float(m.stamp),
            "left_tracked": bool(m.left_tracked),
            "right_tracked": bool(m.right_tracked),
            "left": self.joints["hands_left"].decode(m.left),
            "right": self.joints["hands_right"].decode(m.right),
        }

    def decode_step(
        self, data: bytes, hands: Callable[[int], dict[str, Any] | None] | None = None
    ) -> dict[str, Any]:
        """A step message as the dict :meth:`Recording.from_dicts` takes.

        Args:
            data: The message bytes.
            hands: Looks up the decoded hand sample of a sequence number (for joints
                stored there).

        Raises:
            ValueError: The message refers to a hand sample that is not in the file.
            DecodeError: Its phase or module is a number outside its enum (protobuf's
                enums are open: another writer's file can hold any 32-bit number, and a
                negative one would otherwise index the names from their end).
        """
        m = StepMsg.FromString(data)
        row: dict[str, Any] = {
            "seq": int(m.seq),
            "wall_time": float(m.wall_time),
            "phase": _enum_name(PHASES, m.phase, "phase"),
            "ctb_module": _enum_name(MODULES, m.ctb_module, "ctb_module"),
            "left_tracked": bool(m.left_tracked),
            "right_tracked": bool(m.right_tracked),
            "contact": bool(m.contact),
        }
        for name, _, shape in STEP_DOUBLES:
            value = getattr(m, name)
            if shape == ():
                row[name] = float(value)
            else:
                row[name] = np.array(value, dtype=np.float64) if len(value) else _EMPTY
        if len(m.grid):
            self._decode_grid(m, row)
        else:
            self._prev = None
        if m.pairs_in_cmd:
            pair_fields(row)
        for name, side in (("left_joints", "left"), ("right_joints", "right")):
            sub = getattr(m, name)
            if sub.in_hands:
                sample = hands(int(m.seq)) if hands is not None else None
                if sample is None:
                    raise ValueError(f"step {m.seq}: its hand sample is not in the file")
                row[name] = sample[side]
            else:
                row[name] = self.joints[name].decode(sub)
        return row


def _enum_name(names: tuple[str, ...], number: int, field: str) -> str:
    """``names[number]``, or a :class:`DecodeError` naming the field and the number."""
    if 0 <= number < len(names):
        return names[number]
    raise DecodeError(f"{field}: {number} is not a number from 0 to {len(names) - 1}")


_EMPTY = np.zeros(0)
_EMPTY.setflags(write=False)


@functools.cache
def _steps_kernel() -> Any:
    """The process's compiled serialiser of a batch's messages (checked on
    :func:`_probe_batches`), or None: the protobuf runtime serialises them."""
    fields = [
        (number, math.prod(shape) if shape else 0, name in PAIR_FIELDS)
        for name, number, shape in STEP_DOUBLES
    ]
    return compiled_steps(fields, len(GRID), _probe_batches)


def _probe_batches() -> Iterator[tuple[dict[str, np.ndarray], float, list[bytes]]]:
    """Batches of every kind of step, as the compiled serialiser takes them, with the
    bytes the protobuf runtime gives their messages (one codec, keyed now and then)."""
    rng = np.random.default_rng(0)
    codec = StepCodec()
    for b in range(5):
        items = [_probe_item(rng, 40 * b + k) for k in range(40)]
        batch = codec._rows(items)
        want = serialize(items, batch, codec.grid)
        yield kernel_arrays(items, batch), codec.grid, [x for h, st in want for x in (h or b"", st)]
        if b % 2:
            codec.key()


def _probe_item(rng: np.random.Generator, k: int) -> tuple[Any, int, float, Any]:
    """A step of a probe batch (``k``: which kinds it is of), with a hand frame or not."""
    from types import SimpleNamespace

    def hand() -> np.ndarray:
        return np.rint(rng.normal(scale=0.1, size=JOINTS_SHAPE) / HAND_GRID_M) * HAND_GRID_M

    def vector(size: int) -> np.ndarray:
        v = rng.normal(size=size) * (rng.random(size) < 0.8)  # some zeros
        v[rng.random(size) < 0.1] = -0.0
        return v

    tracked = (k % 11 != 5, k % 13 != 6)
    joints = [hand() if tracked[0] else np.full(JOINTS_SHAPE, np.nan), hand()]
    if k % 7 == 3:
        joints[0] = rng.normal(size=JOINTS_SHAPE)  # off the grid: raw
    if k % 7 == 5:
        joints[1] = rng.normal(size=JOINTS_SHAPE)
    if not tracked[1]:
        joints[1] = np.full(JOINTS_SHAPE, np.nan)
    q = vector(N_MANIPULATION)
    pairs = k % 3 != 0
    step = SimpleNamespace(
        t=0.02 * k,
        phase=PHASES[k % len(PHASES)],
        ctb_module=MODULES[k % len(MODULES)],
        left_joints=hand() if k % 6 == 1 else joints[0],  # not the frame's
        right_joints=hand() if k % 5 == 2 else joints[1],
        left_tracked=tracked[0],
        right_tracked=tracked[1],
        q_left=q[PAIR_L_INDEX] if pairs else vector(8),
        q_right=q[PAIR_R_INDEX] if pairs else vector(8),
        rail_cmd=float(q[RAIL_INDEX]) if pairs else float(vector(1)[0]),
        twist_cmd=vector(6),
        q_cmd=q,
        deploy_cmd=float(vector(1)[0]),
        q_meas=vector(N_MANIPULATION),
        deploy_meas=float(vector(1)[0]),
        astrobee_pos=vector(3) * 10.0,
        astrobee_quat=vector(4),
        astrobee_twist=vector(6),
        ctb_pos=vector(3),
        ctb_quat=vector(4),
        contact=k % 2 == 1,
    )
    if k % 17 == 9:  # not finite: stored as doubles, the next step a key
        step.ctb_pos = np.array([np.nan, 0.0, 0.0])
    if k % 19 == 4:  # too large for the grid's integers
        step.astrobee_pos = np.array([1e300, 0.0, -1.0])
    frame = None
    if k % 9 != 4:
        frame = SimpleNamespace(
            stamp=0.02 * k - 1.0 * (k % 4 == 1),
            left=SimpleNamespace(joints=joints[0], tracked=tracked[0]),
            right=SimpleNamespace(joints=joints[1], tracked=tracked[1]),
        )
    return step, k, (1.7e9 + 0.02 * k) * (k % 8 != 0), frame


__all__ = [
    "FILE_DESCRIPTOR",
    "HANDS_MESSAGE",
    "HAND_GRID_M",
    "PAIR_L_INDEX",
    "PAIR_R_INDEX",
    "STEP_DOUBLES",
    "STEP_GRIDS",
    "STEP_MESSAGE",
    "HandSampleMsg",
    "JointsCodec",
    "JointsMsg",
    "StepCodec",
    "StepMsg",
    "quantize_joints",
    "same_joints",
    "schema_data",
]
