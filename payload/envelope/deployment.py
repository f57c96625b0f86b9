"""The deployment sweep: the stage from stowed to deployed past the vehicle body."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from payload.envelope.fit_results import (
    PairContact,
    SweepResult,
)
from payload.envelope.geometry import PayloadGeometry, box_geometry
from payload.envelope.self_collision import self_contacts
from payload.envelope.vehicle import Vehicle


def _obstacles(geom: PayloadGeometry, vehicle: Vehicle) -> list[tuple[str, Any, tuple]]:
    names = (
        "above the bays",
        "aft of the bays",
        "forward of the bays",
        "right of the bays",
        "left of the bays",
    )
    out = []
    for (lo, hi), name in zip(vehicle.body_boxes(), names):
        out.append((f"vehicle body ({name})", box_geometry(lo, hi), (lo, hi)))
    return out


def deployment_sweep(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    q: Mapping[str, float],
    contacts: Sequence[PairContact] | None = None,
    min_step: float = 1e-5,
    extra: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
) -> SweepResult:
    """Lower the stage from 0 to its full travel with the fingers held in ``q``.

    The stage carries every link but the base rigidly, so their mutual distances do
    not change on the way: the sweep checks them against the vehicle body (five
    convex boxes around the open bays), the base and any ``extra`` obstacle, and
    takes the carried parts' self-collision from ``contacts``. The distance to the
    fixed things is 1-Lipschitz in the stage travel, so an interval whose end
    distances add up to more than its length is contact-free; other intervals are
    halved down to ``min_step``.

    Args:
        geom: Collision geometry.
        vehicle: The vehicle.
        q: Joint values; ``q["stage"]`` is ignored.
        contacts: Self-contacts of ``q`` (computed when not given).
        min_step: Smallest interval halved [m].
        extra: More fixed boxes ``(name, lower corner, upper corner)`` [m].

    Returns:
        The :class:`SweepResult`.
    """
    stage = geom.tree.joint_map["stage"]
    moving = [n for n in geom.links if n != geom.root]
    pairs = [(n, geom.root) for n in moving if frozenset((n, geom.root)) not in geom.adjacent]
    obstacles = _obstacles(geom, vehicle)
    obstacles += [
        (name, box_geometry(lo, hi), (np.asarray(lo), np.asarray(hi))) for name, lo, hi in extra
    ]
    q = dict(q)

    def dist(s: float) -> tuple[float, tuple[str, str]]:
        q["stage"] = s
        return geom.min_distance(geom.poses(q), pairs=pairs, others=obstacles, moving=moving)

    grid = np.linspace(stage.lower, stage.upper, 9)
    values = {float(s): dist(float(s)) for s in grid}
    certified = _certify(values, dist, grid, min_step)
    first, hits = _first_contact(values, dist, min_step)
    s_min = min(values, key=lambda s: values[s][0])
    d_min, between = values[s_min]
    vehicle_clear = not hits and certified
    if contacts is None:
        contacts = self_contacts(geom, geom.poses(q))
    carried = any(c.colliding and geom.root not in (c.a, c.b) for c in contacts)
    return SweepResult(
        bool(vehicle_clear and not carried),
        bool(vehicle_clear),
        float(d_min),
        float(s_min),
        between,
        len(values),
        bool(certified),
        float(first),
    )


Distance = Callable[[float], tuple[float, tuple[str, str]]]
"""Stage travel [m] -> (smallest distance to the fixed things [m], the two closest)."""


def _certify(
    values: dict[float, tuple[float, tuple[str, str]]],
    dist: Distance,
    grid: np.ndarray,
    min_step: float,
) -> bool:
    """Halve every interval not proved contact-free (adding to ``values``); whether all were.

    An interval whose end distances add up to more than its length is contact-free
    (the distance is 1-Lipschitz in the travel); one with an end in contact needs no
    proof.
    """
    stack = [(float(a), float(b)) for a, b in itertools.pairwise(grid)]
    certified = True
    while stack:
        a, b = stack.pop()
        da, db = values[a][0], values[b][0]
        if da <= 0 or db <= 0 or da + db > b - a:
            continue
        if b - a < min_step:
            certified = False
            continue
        m = 0.5 * (a + b)
        values[m] = dist(m)
        stack += [(a, m), (m, b)]
    return certified


def _first_contact(
    values: dict[float, tuple[float, tuple[str, str]]], dist: Distance, min_step: float
) -> tuple[float, list[float]]:
    """(Travel of the first contact, bisected to ``min_step``, NaN when none; the samples
    in contact), adding the bisection's samples to ``values``."""
    order = sorted(values)
    hits = [s for s in order if values[s][0] <= 0]
    if not hits:
        return float("nan"), hits
    # bisect the interval that ends at the first sample in contact
    hi_s = hits[0]
    lo_s = max((s for s in order if s < hi_s), default=None)
    while lo_s is not None and hi_s - lo_s > min_step:
        m = 0.5 * (lo_s + hi_s)
        values[m] = dist(m)
        if values[m][0] <= 0:
            hi_s = m
        else:
            lo_s = m
    return hi_s, hits


__all__ = [
    "deployment_sweep",
]
