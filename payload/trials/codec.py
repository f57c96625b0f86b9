"""Typed, compact step and hand-frame messages for trial recordings (protobuf).

The messages are declared in :mod:`payload.trials.stepmsg` (re-exported here). The schema
stored in every recording is the ``FileDescriptorSet`` of these messages (MCAP
``protobuf`` encoding), so any MCAP tool (``mcap cat``, Foxglove,
``mcap_protobuf.decoder``) decodes them.

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
from typing import Any, NamedTuple

import numpy as np

from payload.schema import N_MANIPULATION
from payload.trials.codec_c import N_FLAGS, STEP_FLAGS, compiled_steps
from payload.trials.jointcodec import (
    GRID_INT_LIMIT,
    HAND_GRID_M,
    IN_HANDS,
    JOINTS_SHAPE,
    N_JOINT_VALUES,
    JointRows,
    JointsCodec,
    fill_joints,
    quantize_joints,
    same_joints,
)
from payload.trials.records import FIELD_SPECS, MODULES, PHASES
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
from payload.vecmath import all_reduce

_BOOL_FLAGS = tuple(f for f in STEP_FLAGS if FIELD_SPECS.get(f, ((), None))[1] == "bool")
"""The step's flags that are the record's booleans (tracked, contact)."""
_SIZES = {"wall_time": 1, **{name: int(np.prod(shape)) for name, _, shape in STEP_DOUBLES}}
STEP_GRIDS: tuple[tuple[str, float, int], ...] = tuple(
    (name, resolution, _SIZES[name])
    for name, resolution in (
        ("wall_time", 1e-6),
        ("t", 1e-9),
        ("twist_cmd", 1e-9),
        ("q_cmd", 1e-8),
        ("deploy_cmd", 1e-8),
        ("q_meas", 1e-8),
        ("deploy_meas", 1e-8),
        ("astrobee_pos", 1e-8),
        ("astrobee_quat", 1e-10),
        ("astrobee_twist", 1e-9),
        ("ctb_pos", 1e-8),
        ("ctb_quat", 1e-10),
    )
)
"""(field, resolution, size) of the numbers a step stores on a grid, in storage order (sizes
from :data:`STEP_DOUBLES`; ``wall_time`` is a scalar); resolutions in the field's unit
(s, m, rad, m/s, rad/s, quaternion components)."""

_GRID = np.concatenate([np.full(n, g) for _, g, n in STEP_GRIDS])
_PER_UNIT = np.round(1.0 / _GRID)  # grid steps per unit, exact integers: decoded values are
# k / steps, the double nearest the decimal k * grid (0.24 s reads back as 0.24)
_GRID_SPLITS = np.cumsum([n for _, _, n in STEP_GRIDS])[:-1]
_GRID_SLICES: tuple[tuple[str, int, int], ...] = tuple(
    (name, int(start), int(start) + n)
    for (name, _, n), start in zip(STEP_GRIDS, np.concatenate([[0], _GRID_SPLITS]))
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
        """The grid numbers of a batch of steps in turn (:class:`GridRows`; ``fields``:
        :func:`_gathered`): a step with a non-finite number is stored as doubles, and the
        next one is a key."""
        n = len(walls)
        values = np.empty((n, len(_GRID)))
        for name, start, stop in _GRID_SLICES:
            if name == "wall_time":
                values[:, start] = walls
            else:
                values[:, start:stop] = fields[name]
        k = np.rint(values * _PER_UNIT)  # what round() calls on floats
        ok = np.isfinite(k).all(axis=1) & ~(np.abs(k) >= GRID_INT_LIMIT).any(axis=1)
        ki = np.where(ok[:, None], k, 0.0).astype(np.int64)
        decoded = ki / _PER_UNIT
        # each stored row's integers less the previous row's, or themselves in a key row
        # (the first after a flush or a row stored as doubles)
        before = np.empty(n, dtype=bool)
        before[1:] = ok[:-1]
        if n:
            before[0] = self._prev is not None
        key = ok & ~before
        ints = ki.copy()
        ints[1:] -= ki[:-1]
        if n and self._prev is not None:
            ints[0] -= self._prev
        ints[key] = ki[key]
        ints[~ok] = 0
        if n:
            self._prev = ki[-1] if ok[-1] else None
        return GridRows(ok, key, ints, decoded)

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
            data = kernel(self._arrays(items, batch), self.grid)
            return [
                (data[2 * i] if frame is not None else None, data[2 * i + 1])
                for i, (_, _, _, frame) in enumerate(items)
            ]
        return self._serialize(items, batch)

    def _rows(self, items: list[tuple[Any, int, float, Any]]) -> _Batch:
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
        fields = _gathered([it[0] for it in items])
        grids = self._grid_batch(fields, [it[2] for it in items])
        pairs = np.array([_pairs_in_cmd(it[0]) for it in items], dtype=bool).reshape(-1)
        return _Batch(at, hands, (own[0], own[1]), grids, fields, pairs)

    def _columns(
        self, items: list[tuple[Any, int, float, Any]], batch: _Batch
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
        for name, start, stop in _GRID_SLICES:
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

    def _serialize(self, items: list[tuple[Any, int, float, Any]], batch: _Batch) -> list:
        """The batch's messages built as protobuf objects and serialised by the runtime."""
        out = []
        for i, (step, seq, wall_time, frame) in enumerate(items):
            data = None
            if frame is not None:
                h = HandSampleMsg(seq=seq, stamp=float(frame.stamp))
                h.left_tracked = bool(frame.left.tracked)
                h.right_tracked = bool(frame.right.tracked)
                fill_joints(h.left, batch.hands[0], batch.at[i], self.grid)
                fill_joints(h.right, batch.hands[1], batch.at[i], self.grid)
                data = h.SerializeToString()
            m = self._step_fields(step, seq, wall_time, batch.grids, i)
            for side, name in enumerate(("left_joints", "right_joints")):
                sub = getattr(m, name)
                mine, coded = batch.own[side]
                if i in mine:
                    fill_joints(sub, coded, mine[i], self.grid)
                else:
                    sub.in_hands = True
            out.append((data, m.SerializeToString()))
        return out

    def _arrays(self, items: list[tuple[Any, int, float, Any]], batch: _Batch) -> dict:
        """The batch as the compiled serialiser takes it (:mod:`payload.trials.codec_c`)."""
        n = len(items)
        steps = [it[0] for it in items]
        grids = batch.grids
        columns = {
            "phase": [PHASES.index(st.phase) for st in steps],
            "ctb_module": [MODULES.index(st.ctb_module) for st in steps],
            **{f: [bool(getattr(st, f)) for st in steps] for f in _BOOL_FLAGS},
            "pairs_in_cmd": batch.pairs,
            "gridded": grids.ok,
            "grid_key": grids.key,
        }
        flags = np.ascontiguousarray(
            np.array([columns[f] for f in STEP_FLAGS], dtype=np.int64).reshape(N_FLAGS, n).T
        )
        doubles = np.concatenate([batch.fields[name] for name, _, _ in STEP_DOUBLES], axis=1)
        walls = np.array([it[2] for it in items], dtype=np.float64)
        out = {
            "seq": np.array([it[1] for it in items], dtype=np.int64),
            "wall": np.where(grids.ok, 0.0, walls),
            "flags": flags,
            "doubles": doubles,
            "grid": grids.ints,
            "stamp": np.zeros(n),
            "hand": np.full((n, 2), -1, dtype=np.int64),
        }
        for prefix, parts in (("", batch.own), ("h", None)):
            code = np.full((n, 2), IN_HANDS, dtype=np.int64)
            key = np.zeros((n, 2), dtype=np.int64)
            ints = np.zeros((n, 2, N_JOINT_VALUES), dtype=np.int64)
            raw = np.zeros((n, 2, N_JOINT_VALUES))
            for side in (0, 1):
                if parts is not None:
                    mine, coded = parts[side]
                    rows = list(mine)
                    where = [mine[i] for i in rows]
                else:
                    coded = batch.hands[side]
                    rows = list(batch.at)
                    where = [batch.at[i] for i in rows]
                code[rows, side] = coded.kind[where]
                key[rows, side] = coded.key[where]
                ints[rows, side] = coded.ints[where]
                raw[rows, side] = coded.raw[where]
            out.update({f"{prefix}code": code, f"{prefix}key": key, f"{prefix}ints": ints,
                        f"{prefix}raw": raw})  # fmt: skip
        for i in batch.at:
            frame = items[i][3]
            out["hand"][i] = (bool(frame.left.tracked), bool(frame.right.tracked))
            out["stamp"][i] = float(frame.stamp)
        return out

    def _step_fields(self, step: Any, seq: int, wall_time: float, grids: GridRows, i: int) -> Any:
        """A ``Step`` message with everything but the joints (row ``i`` of ``grids``), as
        :meth:`encode_step` fills it."""
        m = StepMsg(seq=seq, wall_time=wall_time)
        m.phase = PHASES.index(step.phase)
        m.ctb_module = MODULES.index(step.ctb_module)
        m.left_tracked = step.left_tracked
        m.right_tracked = step.right_tracked
        m.contact = step.contact
        pairs = _pairs_in_cmd(step)
        m.pairs_in_cmd = pairs
        gridded = bool(grids.ok[i])
        if gridded:
            m.grid_key = bool(grids.key[i])
            m.grid.extend(grids.ints[i].tolist())
            m.wall_time = 0.0
        for name, _, shape in STEP_DOUBLES:
            if pairs and name in PAIR_FIELDS:
                continue
            if gridded and name not in PAIR_FIELDS:
                continue
            value = getattr(step, name)
            if shape == ():
                setattr(m, name, value)
            else:
                getattr(m, name).extend(value.tolist())
        return m

    def _decode_grid(self, m: Any, row: dict[str, Any]) -> None:
        d = np.array(m.grid, dtype=np.int64)
        if m.grid_key:
            k = d
        elif self._prev is None or d.shape != self._prev.shape:
            raise ValueError("a step's numbers refer to a message that is not in the file")
        else:
            k = self._prev + d
        self._prev = k
        _grid_fields(row, k / _PER_UNIT)

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
        grids = self._grid_batch(_gathered([step]), [wall_time])
        m = self._step_fields(step, seq, wall_time, grids, 0)
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
        """
        m = StepMsg.FromString(data)
        row: dict[str, Any] = {
            "seq": int(m.seq),
            "wall_time": float(m.wall_time),
            "phase": PHASES[m.phase],
            "ctb_module": MODULES[m.ctb_module],
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
            _pair_fields(row)
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
    return compiled_steps(fields, len(_GRID), _probe_batches)


def _probe_batches() -> Iterator[tuple[dict[str, np.ndarray], float, list[bytes]]]:
    """Batches of every kind of step, as the compiled serialiser takes them, with the
    bytes the protobuf runtime gives their messages (one codec, keyed now and then)."""
    rng = np.random.default_rng(0)
    codec = StepCodec()
    for b in range(5):
        items = [_probe_item(rng, 40 * b + k) for k in range(40)]
        batch = codec._rows(items)
        want = codec._serialize(items, batch)
        yield codec._arrays(items, batch), codec.grid, [x for h, st in want for x in (h or b"", st)]
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


class _Batch(NamedTuple):
    """What a batch of steps stores besides their own fields (:meth:`StepCodec._rows`)."""

    at: dict[int, int]  # a step with a hand frame: its row among the frames
    hands: tuple[JointRows, JointRows]  # the frames' left and right joints
    # per side (left, right): the steps whose joints are not their frame's (a step -> its
    # row) and those joints' rows
    own: tuple[tuple[dict[int, int], JointRows], tuple[dict[int, int], JointRows]]
    grids: GridRows
    fields: dict[str, np.ndarray]  # :func:`_gathered`
    pairs: np.ndarray  # per step whether its pair fields are its command's (bool)


def _gathered(steps: list[Any]) -> dict[str, np.ndarray]:
    """Each double field of the steps (:data:`STEP_DOUBLES`), as an (n, size) array."""
    n = len(steps)
    return {
        name: np.array([getattr(st, name) for st in steps], dtype=np.float64).reshape(
            n, math.prod(shape)
        )
        for name, _, shape in STEP_DOUBLES
    }


class GridRows(NamedTuple):
    """The grid numbers of a batch of steps (:meth:`StepCodec._grid_batch`), n rows.

    Attributes:
        ok: Per step whether it is stored on the grid (else as doubles: a number that is
            not finite or too large).
        key: Per step whether its integers are the multiples themselves (the first after a
            flush or after a step stored as doubles), not deltas.
        ints: The integers stored, (n, G) in :data:`STEP_GRIDS` order (zero rows where not
            ``ok``).
        values: The numbers as the decoder reads them back (the same integers over the same
            grid steps per unit), (n, G).
    """

    ok: np.ndarray
    key: np.ndarray
    ints: np.ndarray
    values: np.ndarray


def _grid_fields(row: dict[str, Any], values: np.ndarray) -> None:
    """Set a decoded row's gridded fields from their values, in :data:`STEP_GRIDS` order."""
    for name, start, stop in _GRID_SLICES:  # np.split's views, without its overhead
        row[name] = float(values[start]) if stop == start + 1 else values[start:stop]


def _pair_fields(row: dict[str, Any]) -> None:
    """Set a decoded row's pair fields from its ``q_cmd`` (a step stored ``pairs_in_cmd``)."""
    q = row["q_cmd"]
    row["q_left"], row["q_right"] = q[PAIR_L_INDEX], q[PAIR_R_INDEX]
    row["rail_cmd"] = float(q[RAIL_INDEX])


def _pairs_in_cmd(step: Any) -> bool:
    q = step.q_cmd
    return bool(
        _equal(step.q_left, q[PAIR_L_INDEX])
        and _equal(step.q_right, q[PAIR_R_INDEX])
        and step.rail_cmd == q[RAIL_INDEX]
    )


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    """``np.array_equal`` of two arrays (same shape, every element ==), sooner."""
    return a.shape == b.shape and bool(all_reduce(a == b, axis=None))


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
