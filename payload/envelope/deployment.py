"""The deployment sweep: the stage from stowed to deployed past the vehicle body."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from payload.envelope.fit_results import (
    BodyHit,
    PairContact,
    SweepResult,
    UnfoldResult,
)
from payload.envelope.geometry import PayloadGeometry, aabb, aabb_gap, box_geometry
from payload.envelope.self_collision import colliding_pairs, self_contacts
from payload.envelope.vehicle import Vehicle

UNFOLD_STEP_RAD = math.radians(1.0)
"""The most a revolute joint moves between two checked postures of the unfolding [rad]."""
UNFOLD_STEP_M = 0.5e-3
"""The most the rail moves between two checked postures of the unfolding [m]."""


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


def unfolding_samples(
    geom: PayloadGeometry, stowed: Mapping[str, float], home: Mapping[str, float]
) -> int:
    """How many postures :func:`unfolding_check` takes from ``stowed`` to ``home``: no
    revolute joint moves more than :data:`UNFOLD_STEP_RAD` and no prismatic one more than
    :data:`UNFOLD_STEP_M` between two."""
    joints = geom.tree.joint_map
    steps = [
        abs(home[j] - stowed[j])
        / (UNFOLD_STEP_M if joints[j].kind == "prismatic" else UNFOLD_STEP_RAD)
        for j in home
        if j != "stage"
    ]
    return max(1, math.ceil(max(steps, default=0.0)))


def unfolding_postures(
    stowed: Mapping[str, float], home: Mapping[str, float], n: int
) -> list[dict[str, float]]:
    """The fingers and the rail from ``stowed`` to ``home`` in a straight line in joint
    space, the stage at ``home``'s (down): ``n`` evenly spaced postures, the stowed end
    left out (the stage's sweep ends there) and home in. The deployment's second half, as
    the envelope check takes it and the design review plays it."""
    out = []
    for s in np.linspace(0.0, 1.0, n + 1)[1:]:
        values = {j: (1 - s) * stowed[j] + s * home[j] for j in home}
        values["stage"] = home["stage"]
        out.append(values)
    return out


def unfolding_check(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    stowed: Mapping[str, float],
    home: Mapping[str, float],
    contacts: Sequence[PairContact],
) -> UnfoldResult:
    """The deployment's second half: with the stage down, the fingers and the rail from
    ``stowed`` to ``home`` (:func:`unfolding_postures`), each posture's links against each
    other and the base (the pairs colliding stowed, in ``contacts``, left out: they are
    the stowed check's) and against the vehicle body. Sampled, not certified as the
    stage's sweep is: a contact thinner than a step's motion can go unseen."""
    postures = unfolding_postures(stowed, home, unfolding_samples(geom, stowed, home))
    stowed_pairs = {frozenset((c.a, c.b)) for c in contacts if c.colliding}
    pairs = [(a, b) for a, b in geom.pairs if frozenset((a, b)) not in stowed_pairs]
    body = _obstacles(geom, vehicle)
    moving = [n for n in geom.links if n != geom.root]
    collided: dict[frozenset[str], PairContact] = {}  # each at its deepest
    deepest: dict[str, BodyHit] = {}
    for q in postures:
        poses = geom.poses(q)
        boxes = {n: aabb(geom.hull_vertices(n, poses[n])) for n in geom.links}
        for c in colliding_pairs(geom, poses, boxes, pairs):
            key = frozenset((c.a, c.b))
            if key not in collided or c.distance < collided[key].distance:
                collided[key] = c
        for link in moving:  # each link: two reaching into the body at once are both said
            near = [o for o in body if aabb_gap(boxes[link], o[2]) <= 0.0]
            if not near:
                continue
            d, (_, thing) = geom.min_distance(poses, pairs=(), others=near, moving=[link])
            if d <= 0 and (link not in deepest or d < deepest[link].distance):
                deepest[link] = BodyHit(link, thing, float(d))
    collisions = sorted(collided.values(), key=lambda c: c.distance)
    hits = sorted(deepest.values(), key=lambda h: h.distance)
    return UnfoldResult(collisions, hits, len(postures))


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
    "UNFOLD_STEP_M",
    "UNFOLD_STEP_RAD",
    "deployment_sweep",
    "unfolding_check",
    "unfolding_postures",
    "unfolding_samples",
]
