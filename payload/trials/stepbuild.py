"""Building the recorded step and hand-sample messages of a batch of steps
(:meth:`payload.trials.codec.StepCodec.encode_batch`): as protobuf objects the runtime
serialises (:func:`serialize`), or as the arrays the compiled serialiser takes
(:func:`kernel_arrays`, :mod:`payload.trials.codec_c`), from the batch's numbers
(:class:`StepBatch`: the grid arithmetic of :mod:`payload.trials.stepgrid` and the
joints' rows of :mod:`payload.trials.jointcodec`).

A step whose pair fields are its command's entries (:func:`pairs_in_cmd`) stores them
there only; :func:`pair_fields` sets them back when it is read.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from payload.trials.codec_c import N_FLAGS, STEP_FLAGS
from payload.trials.jointcodec import IN_HANDS, N_JOINT_VALUES, JointRows, fill_joints
from payload.trials.records import FIELD_SPECS, MODULES, PHASES
from payload.trials.stepgrid import GridRows
from payload.trials.stepmsg import (
    PAIR_FIELDS,
    PAIR_L_INDEX,
    PAIR_R_INDEX,
    RAIL_INDEX,
    STEP_DOUBLES,
    HandSampleMsg,
    StepMsg,
)
from payload.vecmath import all_reduce

_BOOL_FLAGS = tuple(f for f in STEP_FLAGS if FIELD_SPECS.get(f, ((), None))[1] == "bool")
"""The step's flags that are the record's booleans (tracked, contact)."""


class StepBatch(NamedTuple):
    """What a batch of steps stores besides their own fields
    (:meth:`payload.trials.codec.StepCodec._rows`)."""

    at: dict[int, int]  # a step with a hand frame: its row among the frames
    hands: tuple[JointRows, JointRows]  # the frames' left and right joints
    # per side (left, right): the steps whose joints are not their frame's (a step -> its
    # row) and those joints' rows
    own: tuple[tuple[dict[int, int], JointRows], tuple[dict[int, int], JointRows]]
    grids: GridRows
    fields: dict[str, np.ndarray]  # :func:`~payload.trials.stepgrid.gathered`
    pairs: np.ndarray  # per step whether its pair fields are its command's (bool)


def serialize(items: list[tuple[Any, int, float, Any]], batch: StepBatch, grid: float) -> list:
    """The batch's messages built as protobuf objects and serialised by the runtime
    (``grid``: the joints' grid [m]), per step ``(hand sample bytes or None, step bytes)``."""
    out = []
    for i, (step, seq, wall_time, frame) in enumerate(items):
        data = None
        if frame is not None:
            h = HandSampleMsg(seq=seq, stamp=float(frame.stamp))
            h.left_tracked = bool(frame.left.tracked)
            h.right_tracked = bool(frame.right.tracked)
            fill_joints(h.left, batch.hands[0], batch.at[i], grid)
            fill_joints(h.right, batch.hands[1], batch.at[i], grid)
            data = h.SerializeToString()
        m = step_fields(step, seq, wall_time, batch.grids, i)
        for side, name in enumerate(("left_joints", "right_joints")):
            sub = getattr(m, name)
            mine, coded = batch.own[side]
            if i in mine:
                fill_joints(sub, coded, mine[i], grid)
            else:
                sub.in_hands = True
        out.append((data, m.SerializeToString()))
    return out


def kernel_arrays(items: list[tuple[Any, int, float, Any]], batch: StepBatch) -> dict:
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


def step_fields(step: Any, seq: int, wall_time: float, grids: GridRows, i: int) -> Any:
    """A ``Step`` message with everything but the joints (row ``i`` of ``grids``), as
    :meth:`~payload.trials.codec.StepCodec.encode_step` fills it."""
    m = StepMsg(seq=seq, wall_time=wall_time)
    m.phase = PHASES.index(step.phase)
    m.ctb_module = MODULES.index(step.ctb_module)
    m.left_tracked = step.left_tracked
    m.right_tracked = step.right_tracked
    m.contact = step.contact
    pairs = pairs_in_cmd(step)
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


def pair_fields(row: dict[str, Any]) -> None:
    """Set a decoded row's pair fields from its ``q_cmd`` (a step stored ``pairs_in_cmd``)."""
    q = row["q_cmd"]
    row["q_left"], row["q_right"] = q[PAIR_L_INDEX], q[PAIR_R_INDEX]
    row["rail_cmd"] = float(q[RAIL_INDEX])


def pairs_in_cmd(step: Any) -> bool:
    """Whether a step's pair fields are its command's entries (then stored only there)."""
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
    "StepBatch",
    "kernel_arrays",
    "pair_fields",
    "pairs_in_cmd",
    "serialize",
    "step_fields",
]
