"""The grid arithmetic of the recorded step messages (:mod:`payload.trials.codec`).

A step's numbers are stored at a stated resolution (:data:`STEP_GRIDS`): each value's
integer multiple of its grid, as the multiple less the previous message's (a delta) or
the multiple itself in a key message (the first after a flush, or after a step stored as
doubles). :func:`grid_rows` works out a batch's integers at once (:class:`GridRows`);
:func:`grid_fields` sets a decoded step's numbers back from them. A step with a
non-finite number, or one too large for the grid's integers, is stored as doubles.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from payload.trials.jointcodec import GRID_INT_LIMIT
from payload.trials.stepmsg import STEP_DOUBLES

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

GRID = np.concatenate([np.full(n, g) for _, g, n in STEP_GRIDS])
"""Each stored number's grid, in :data:`STEP_GRIDS` order."""
PER_UNIT = np.round(1.0 / GRID)  # grid steps per unit, exact integers: decoded values are
# k / steps, the double nearest the decimal k * grid (0.24 s reads back as 0.24)
_GRID_SPLITS = np.cumsum([n for _, _, n in STEP_GRIDS])[:-1]
GRID_SLICES: tuple[tuple[str, int, int], ...] = tuple(
    (name, int(start), int(start) + n)
    for (name, _, n), start in zip(STEP_GRIDS, np.concatenate([[0], _GRID_SPLITS]))
)
"""(field, start, stop) of each gridded field among a step's stored numbers."""


class GridRows(NamedTuple):
    """The grid numbers of a batch of steps (:func:`grid_rows`), n rows.

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


def grid_rows(
    fields: dict[str, np.ndarray], walls: list[float], prev: np.ndarray | None
) -> tuple[GridRows, np.ndarray | None]:
    """The grid numbers of a batch of steps in turn (``fields``: :func:`gathered`): a step
    with a non-finite number is stored as doubles, and the next one is a key.

    Args:
        fields: The batch's double fields.
        walls: Each step's wall clock [s].
        prev: The last stored step's grid multiples before the batch (``None``: the first
            step is a key).

    Returns:
        The batch's :class:`GridRows` and the multiples the next batch's deltas start from
        (``prev`` itself for an empty batch).
    """
    n = len(walls)
    values = np.empty((n, len(GRID)))
    for name, start, stop in GRID_SLICES:
        if name == "wall_time":
            values[:, start] = walls
        else:
            values[:, start:stop] = fields[name]
    k = np.rint(values * PER_UNIT)  # what round() calls on floats
    ok = np.isfinite(k).all(axis=1) & ~(np.abs(k) >= GRID_INT_LIMIT).any(axis=1)
    ki = np.where(ok[:, None], k, 0.0).astype(np.int64)
    decoded = ki / PER_UNIT
    # each stored row's integers less the previous row's, or themselves in a key row
    # (the first after a flush or a row stored as doubles)
    before = np.empty(n, dtype=bool)
    before[1:] = ok[:-1]
    if n:
        before[0] = prev is not None
    key = ok & ~before
    ints = ki.copy()
    ints[1:] -= ki[:-1]
    if n and prev is not None:
        ints[0] -= prev
    ints[key] = ki[key]
    ints[~ok] = 0
    if n:
        prev = ki[-1] if ok[-1] else None
    return GridRows(ok, key, ints, decoded), prev


def gathered(steps: list[Any]) -> dict[str, np.ndarray]:
    """Each double field of the steps (:data:`STEP_DOUBLES`), as an (n, size) array."""
    n = len(steps)
    return {
        name: np.array([getattr(st, name) for st in steps], dtype=np.float64).reshape(
            n, math.prod(shape)
        )
        for name, _, shape in STEP_DOUBLES
    }


def grid_fields(row: dict[str, Any], values: np.ndarray) -> None:
    """Set a decoded row's gridded fields from their values, in :data:`STEP_GRIDS` order."""
    for name, start, stop in GRID_SLICES:  # np.split's views, without its overhead
        row[name] = float(values[start]) if stop == start + 1 else values[start:stop]


__all__ = [
    "GRID",
    "GRID_SLICES",
    "PER_UNIT",
    "STEP_GRIDS",
    "GridRows",
    "gathered",
    "grid_fields",
    "grid_rows",
]
