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
from payload.envelope.geometry import (
    PayloadGeometry,
    aabb_gap,
    box_geometry,
    signed_distance,
)
from payload.envelope.self_collision import colliding_pairs, self_contacts
from payload.envelope.vehicle import Vehicle

UNFOLD_STEP_RAD = math.radians(1.0)
"""The most a revolute joint moves between two checked postures of the unfolding [rad]."""
UNFOLD_STEP_M = 0.5e-3
"""The most the rail moves between two checked postures of the unfolding [m]."""
PROOF_MIN_MOTION_M = 1e-5
"""The halving of a deployment proof's unproved stretches stops where nothing moves more
than this between their ends [m]: the stage's sweep (its ``min_step``) and the
unfolding's."""


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
    min_step: float = PROOF_MIN_MOTION_M,
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
    return [_posture_at(stowed, home, s) for s in np.linspace(0.0, 1.0, n + 1)[1:]]


def _posture_at(stowed: Mapping[str, float], home: Mapping[str, float], s: float) -> dict:
    """The posture a share ``s`` of the way along the unfolding's line, the stage down."""
    values = {j: (1 - s) * stowed[j] + s * home[j] for j in home}
    values["stage"] = home["stage"]
    return values


def unfolding_rates(
    geom: PayloadGeometry, start: Mapping[str, float], end: Mapping[str, float]
) -> dict[str, float]:
    """How fast each link's points move, at most, along the straight joint-space line from
    ``start`` to ``end`` (the stage at ``end``'s), per unit of the line's parameter [m]:
    for every revolute joint above the link, its change times the farthest the link's
    convex pieces reach from the joint's axis (the chain's offsets below it, any
    prismatic travel on the way, then the link's own pieces from its origin); for every
    prismatic one, its change. A bound for every posture on the line, so a distance
    between two links changes no faster than the sum of their rates, and one to a thing
    fixed to the vehicle no faster than the link's."""
    above = {j.child: j for j in geom.tree.joints}
    start = {**start, "stage": end.get("stage", 0.0)}
    rates = {}
    for link in geom.links:
        reach = geom.reach(link)
        rate, name = 0.0, link
        while name in above:
            j = above[name]
            a, b = float(start.get(j.name, 0.0)), float(end.get(j.name, 0.0))
            axis = float(np.linalg.norm(j.axis))
            if j.kind == "revolute":
                rate += abs(b - a) * axis * reach  # the axis passes through the origin
            elif j.kind == "prismatic":
                rate += abs(b - a) * axis
                reach += max(abs(a), abs(b)) * axis
            reach += float(np.linalg.norm(j.xyz))
            name = j.parent
        rates[link] = rate
    return rates


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
    the stowed check's) and against the vehicle body. Then the line between the postures
    is proved contact-free as the stage's sweep is: a stretch whose end distances, each
    over the two things' bound of :func:`unfolding_rates`, add up to more than its length
    cannot hold a contact; other stretches are halved (down to
    :data:`PROOF_MIN_MOTION_M` of motion), and a contact a halving finds is reported as
    the postures' are."""
    n = unfolding_samples(geom, stowed, home)
    postures = unfolding_postures(stowed, home, n)
    stowed_pairs = {frozenset((c.a, c.b)) for c in contacts if c.colliding}
    pairs = [(a, b) for a, b in geom.pairs if frozenset((a, b)) not in stowed_pairs]
    body = _obstacles(geom, vehicle)
    moving = [n for n in geom.links if n != geom.root]
    collided: dict[frozenset[str], PairContact] = {}  # each at its deepest
    deepest: dict[str, BodyHit] = {}
    for q in postures:
        _examine(geom, q, pairs, body, moving, collided, deepest)
    grid = np.linspace(0.0, 1.0, n + 1)
    while True:  # a stretch with an end in contact is proved for no pair: again without it
        proof = _UnfoldProof(geom, body, stowed, home, pairs, moving, collided, deepest)
        certified = proof.run(grid)
        if not proof.touching:
            break
        known = len(collided) + len(deepest)
        for s in sorted(proof.touching):  # contacts between the postures: said as theirs are
            q = _posture_at(stowed, home, s)
            _examine(geom, q, pairs, body, moving, collided, deepest)
        if len(collided) + len(deepest) == known:  # pieces that touch, solids that do not
            certified = False
            break
    on_the_way = {s: v for s, v in proof.values.items() if s > 0.0}  # s = 0: the stowed
    s_min = min(on_the_way, key=lambda s: on_the_way[s][1], default=None)  # fit's figures
    d_min, between = (np.inf, ("", "")) if s_min is None else on_the_way[s_min][1:]
    collisions = sorted(collided.values(), key=lambda c: c.distance)
    hits = sorted(deepest.values(), key=lambda h: h.distance)
    return UnfoldResult(
        collisions, hits, len(postures), certified, float(d_min), between, len(proof.values)
    )


def _examine(
    geom: PayloadGeometry,
    q: Mapping[str, float],
    pairs: Sequence[tuple[str, str]],
    body: list[tuple[str, Any, tuple]],
    moving: Sequence[str],
    collided: dict[frozenset[str], PairContact],
    deepest: dict[str, BodyHit],
) -> None:
    """Add posture ``q``'s colliding pairs and links in the vehicle body, each kept at its
    deepest, to ``collided`` and ``deepest``."""
    poses = geom.poses(q)
    boxes = {n: geom.piece_bounds(n, poses[n]) for n in geom.links}
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


class _UnfoldProof:
    """The proof that the unfolding's line holds no contact between its postures (see
    :func:`unfolding_check`), over the pairs and links not already reported."""

    def __init__(
        self,
        geom: PayloadGeometry,
        body: list[tuple[str, Any, tuple]],
        stowed: Mapping[str, float],
        home: Mapping[str, float],
        pairs: Sequence[tuple[str, str]],
        moving: Sequence[str],
        collided: Mapping[frozenset[str], PairContact],
        deepest: Mapping[str, BodyHit],
    ) -> None:
        self.geom, self.stowed, self.home = geom, stowed, home
        rate = unfolding_rates(geom, stowed, home)
        tasks = [(a, b, None, rate[a] + rate[b]) for a, b in pairs
                 if frozenset((a, b)) not in collided]  # fmt: skip
        tasks += [(link, name, (obj, bounds), rate[link]) for link in moving
                  if link not in deepest for name, obj, bounds in body]  # fmt: skip
        self.tasks = [t for t in tasks if t[3] > 0.0]  # what does not move was checked
        fastest = max(rate.values(), default=0.0)
        self.min_step = PROOF_MIN_MOTION_M / fastest if fastest > 0 else 1.0
        self.values: dict[float, tuple[float, float, tuple[str, str]]] = {}
        self.touching: set[float] = set()
        # the tasks' bounding boxes as arrays: the first's link, the second's link or the
        # obstacle's fixed bounds (zero rows where a link's are taken instead)
        index = {n: i for i, n in enumerate(geom.links)}
        self._a = np.array([index[t[0]] for t in self.tasks], dtype=np.intp)
        self._b = np.array([index.get(t[1], 0) for t in self.tasks], dtype=np.intp)
        self._fixed = np.array([t[2] is not None for t in self.tasks], dtype=bool)
        bounds = [t[2][1] if t[2] is not None else (np.zeros(3), np.zeros(3)) for t in self.tasks]
        self._fixed_lo = np.array([b[0] for b in bounds], dtype=float).reshape(-1, 3)
        self._fixed_hi = np.array([b[1] for b in bounds], dtype=float).reshape(-1, 3)
        self._rates = np.array([t[3] for t in self.tasks], dtype=float)

    def distance(self, s: float) -> tuple[float, float, tuple[str, str]]:
        """(The smallest distance over its rate [1: the line's parameter], the smallest
        distance [m], the two things closest) at ``s``; both exact: the things are visited
        by their bounding boxes' gap (:func:`~payload.envelope.geometry.aabb_gap`'s, for
        all at once) and left once neither can be smaller."""
        geom = self.geom
        poses = geom.poses(_posture_at(self.stowed, self.home, s))
        boxes = [geom.piece_bounds(n, poses[n]) for n in geom.links]
        lo = np.array([b[0] for b in boxes])
        hi = np.array([b[1] for b in boxes])
        fixed = self._fixed[:, None]
        lo_b = np.where(fixed, self._fixed_lo, lo[self._b])
        hi_b = np.where(fixed, self._fixed_hi, hi[self._b])
        apart = np.maximum(np.maximum(lo[self._a] - hi_b, lo_b - hi[self._a]), 0.0)
        gaps = np.sqrt(np.einsum("ij,ij->i", apart, apart))
        scaled_gaps = gaps / self._rates
        scaled, least, where = np.inf, np.inf, ("", "")
        posed: dict[str, list] = {}  # each link's posed pieces, made once (link_distance's)

        def pieces(link: str) -> list:
            if link not in posed:
                posed[link] = geom.piece_objects(link, poses[link])
            return posed[link]

        for k in np.argsort(scaled_gaps, kind="stable").tolist():
            gap, a, b, obj, r = gaps[k], *self.tasks[k]
            if gap > 0.0 and scaled_gaps[k] > scaled and gap > least:
                continue
            if obj is None:
                d = min(signed_distance(x, y) for x in pieces(a) for y in pieces(b))
            else:
                d = min(signed_distance(o, obj[0]) for o in pieces(a))
            scaled = min(scaled, d / r)
            if d < least:
                least, where = d, (a, b)
        return float(scaled), float(least), where

    def run(self, grid: np.ndarray) -> bool:
        """Evaluate ``grid`` and halve every stretch not proved; whether all were (a
        stretch with an end in contact needs no proof: the end is in ``touching``)."""
        if not self.tasks:
            return True
        for s in grid:
            self.values[float(s)] = self.distance(float(s))
        stack = [(float(a), float(b)) for a, b in itertools.pairwise(grid)]
        certified = True
        while stack:
            a, b = stack.pop()
            da, db = self.values[a][0], self.values[b][0]
            if da <= 0 or db <= 0:
                self.touching.update(s for s, d in ((a, da), (b, db)) if d <= 0)
                continue
            if da + db > b - a:
                continue
            if b - a < self.min_step:
                certified = False
                continue
            m = 0.5 * (a + b)
            self.values[m] = self.distance(m)
            stack += [(a, m), (m, b)]
        return certified


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
    "PROOF_MIN_MOTION_M",
    "UNFOLD_STEP_M",
    "UNFOLD_STEP_RAD",
    "deployment_sweep",
    "unfolding_check",
    "unfolding_postures",
    "unfolding_rates",
    "unfolding_samples",
]
