"""Lossless coding of hand-joint positions for trial recordings (the ``Joints`` message of
:mod:`payload.trials.codec`).

``payload.trials.Joints``: 25 x 3 hand-joint positions [m], lossless, in one of three forms:

* ``grid`` > 0: every value is ``k * grid`` for an integer ``k``; ``delta`` holds ``k``
  minus the previous message's ``k`` (the same hand on the same channel), or ``k`` itself
  when ``key`` is set (the first message after every flush is a key message).
* ``raw``: 75 doubles (values off any grid).
* ``untracked``: all NaN (no joints).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from payload.teleop.hands import round_to_grid
from payload.trials.records import N_HAND_JOINTS

HAND_GRID_M = 1e-5
"""Resolution of the synthetic headset's joint positions [m] (10 um; WebXR reports float32)."""

GRID_INT_LIMIT = 2.0**62
"""Grid multiples at or beyond this are not stored on a grid (an int64 holds those below
it and their deltas): such joints are stored raw, such steps as doubles."""


def quantize_joints(joints: np.ndarray, grid: float = HAND_GRID_M) -> np.ndarray:
    """Joint positions rounded to ``grid`` [m] (what the synthetic headset reports:
    :func:`payload.teleop.hands.round_to_grid`).

    NaN stays NaN; the result is exactly representable by the ``grid`` form of ``Joints``.
    """
    return round_to_grid(joints, grid)


class JointsCodec:
    """Lossless encoder/decoder of one hand's joints on one channel (keeps the delta state).

    Args:
        grid: The grid [m] tried first (values off it are stored raw).
    """

    def __init__(self, grid: float = HAND_GRID_M) -> None:
        self.grid = grid
        self._prev: np.ndarray | None = None

    def key(self) -> None:
        """Make the next message a key message (no reference to earlier ones)."""
        self._prev = None

    def encode(self, joints: np.ndarray, out: Any) -> None:
        """Fill the ``Joints`` message ``out`` with ``joints`` (25, 3)."""
        flat = np.asarray(joints, dtype=np.float64).reshape(-1)
        if np.isnan(flat).all():
            out.untracked = True
            return
        with np.errstate(invalid="ignore"):
            k = np.rint(flat / self.grid)  # what round() calls on floats
        # on the grid: integers an int64 holds, and exactly the values (np.array_equal)
        if (
            np.isfinite(k).all()
            and (np.abs(k) < GRID_INT_LIMIT).all()
            and (k * self.grid == flat).all()
        ):
            ki = k.astype(np.int64)
            out.grid = self.grid
            if self._prev is None:
                out.key = True
                out.delta.extend(ki.tolist())
            else:
                out.delta.extend((ki - self._prev).tolist())
            self._prev = ki
            return
        out.raw.extend(flat.tolist())
        self._prev = None

    def encode_many(self, joints: list[np.ndarray]) -> JointRows:
        """What :meth:`encode` would store for each of several joint arrays in turn (the
        arithmetic done once for the batch: the same elementwise operations, so the same
        integers), for :func:`fill_joints`, and what :meth:`decode` reads back from them.

        Args:
            joints: Joint arrays (25, 3), in the order they are written.
        """
        n = len(joints)
        if not n:
            empty = np.zeros((0, N_JOINT_VALUES), dtype=np.int64)
            return JointRows(empty[:, 0].copy(), empty[:, 0] > 0, empty, empty * 0.0,
                             np.zeros((0, *JOINTS_SHAPE)))  # fmt: skip
        flat = np.array(joints, dtype=np.float64).reshape(n, -1)
        untracked = np.isnan(flat).all(axis=1)
        with np.errstate(invalid="ignore"):
            k = np.rint(flat / self.grid)
            gridded = (
                np.isfinite(k).all(axis=1)
                & (np.abs(k) < GRID_INT_LIMIT).all(axis=1)
                & (k * self.grid == flat).all(axis=1)
            )
        ki = np.where(gridded[:, None], k, 0.0).astype(np.int64)
        kind = np.where(untracked, UNTRACKED, np.where(gridded, ON_GRID, RAW))
        key = np.zeros(n, dtype=bool)
        ints = ki.copy()
        prev = self._prev
        for i in np.flatnonzero(~untracked).tolist():  # untracked rows leave the chain be
            if gridded[i]:
                if prev is None:
                    key[i] = True
                else:
                    ints[i] -= prev
                prev = ki[i]
            else:
                prev = None
        self._prev = prev
        decoded = np.where(gridded[:, None], ki * self.grid, flat)
        decoded[untracked] = np.nan
        return JointRows(kind, key, ints, flat, decoded.reshape(n, *JOINTS_SHAPE))

    def decode(self, msg: Any) -> np.ndarray:
        """Joints (25, 3) [m] from a ``Joints`` message (NaN when untracked)."""
        if msg.untracked:
            return np.full(JOINTS_SHAPE, np.nan)
        if msg.grid > 0:
            d = np.array(msg.delta, dtype=np.int64)
            if msg.key or self._prev is None:
                if not msg.key:
                    raise ValueError("hand joints reference a message that is not in the file")
                k = d
            else:
                k = self._prev + d
            self._prev = k
            return (k * msg.grid).reshape(JOINTS_SHAPE)
        self._prev = None
        return np.array(msg.raw, dtype=np.float64).reshape(JOINTS_SHAPE)


UNTRACKED, ON_GRID, RAW = 0, 1, 2
"""The forms of a ``Joints`` message (:attr:`JointRows.kind`)."""

IN_HANDS = 3
"""A step's joints stored as a reference to its hand sample's (a fourth form, of a step's
joints only)."""

JOINTS_SHAPE = (N_HAND_JOINTS, 3)
"""One hand's joint positions: a row per WebXR joint."""

N_JOINT_VALUES = N_HAND_JOINTS * 3
"""Numbers in one hand's joints."""


class JointRows(NamedTuple):
    """What :meth:`JointsCodec.encode_many` stores for a batch of joint arrays (n rows).

    Attributes:
        kind: Per row its form: :data:`UNTRACKED`, :data:`ON_GRID` or :data:`RAW`.
        key: Per row whether it is a key message (grid rows only).
        ints: The grid rows' integers (the multiples, or their deltas), (n,
            :data:`N_JOINT_VALUES`).
        raw: The values themselves (what a raw row stores), (n, :data:`N_JOINT_VALUES`).
        decoded: What the decoder reads back, (n, 25, 3): NaN where untracked, ``k *
            grid`` on the grid (the decoder's product of the same integers), the values
            themselves raw.
    """

    kind: np.ndarray
    key: np.ndarray
    ints: np.ndarray
    raw: np.ndarray
    decoded: np.ndarray


def fill_joints(out: Any, rows: JointRows, i: int, grid: float) -> None:
    """Fill a ``Joints`` message from row ``i`` of :meth:`JointsCodec.encode_many`'s rows,
    as :meth:`JointsCodec.encode` fills it."""
    kind = rows.kind[i]
    if kind == UNTRACKED:
        out.untracked = True
    elif kind == ON_GRID:
        out.grid = grid
        if rows.key[i]:
            out.key = True
        out.delta.extend(rows.ints[i].tolist())
    else:
        out.raw.extend(rows.raw[i].tolist())


def same_joints(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit-for-bit equality of two joint arrays (NaN equal to NaN)."""
    if a is b or (a.shape == b.shape and a.tobytes() == b.tobytes()):
        return True  # identical bytes: equal (the common case, decided without a pass)
    return bool(np.array_equal(a, b, equal_nan=True))


__all__ = [
    "GRID_INT_LIMIT",
    "HAND_GRID_M",
    "IN_HANDS",
    "JOINTS_SHAPE",
    "N_JOINT_VALUES",
    "ON_GRID",
    "RAW",
    "UNTRACKED",
    "JointRows",
    "JointsCodec",
    "fill_joints",
    "quantize_joints",
    "same_joints",
]
