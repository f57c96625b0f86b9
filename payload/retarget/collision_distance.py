"""Distances between segments, points and boxes in closed form, as CasADi expressions and
in numpy: the clearance terms of one pair's self-collision model
(:mod:`payload.retarget.collision`: a capsule is a segment and a radius, the structure is
boxes) and of its grouped evaluation (:mod:`payload.retarget.collision_eval`).

A capsule against a capsule is the segment-to-segment distance (Ericson's closest
points) less both radii; a capsule against a box is the smallest distance of the box
along the capsule's axis (:func:`segment_box_distance_expr`; an axis entering the box
gets the depth in the middle of its inside part) less the radius. The closed forms are
written once for CasADi and numpy (``o = _CASADI`` or ``_NUMPY``); ``sqrt(. + 1e-18)``
keeps them smooth.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from payload.retarget.collision_geometry import Box

_TINY = 1e-18


def _point_segment(p: Any, a: Any, b: Any, o: SimpleNamespace) -> Any:
    """Distance from point p to segment a-b, for CasADi (``o = _CASADI``) and numpy
    (``o = _NUMPY``, single points); ``sqrt(. + 1e-18)`` keeps it smooth."""
    d = b - a
    t = o.min(o.max(o.dot(p - a, d) / o.max(o.dot(d, d), 1e-30), 0.0), 1.0)
    w = a + t * d - p
    return o.sqrt(o.dot(w, w) + _TINY)


def _point_segment_ca(p: Any, a: Any, b: Any) -> Any:
    """Distance from point p to segment a-b (CasADi)."""
    return _point_segment(p, a, b, _CASADI)


def _point_segment_np(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from point p to segment a-b (numpy)."""
    return float(_point_segment(p, a, b, _NUMPY))


def _segment_distance_ca(p1, q1, p2, q2):
    """Distance between segments p1-q1 and p2-q2 (CasADi), Ericson's closest points."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = ca.dot(d1, d1), ca.dot(d2, d2), ca.dot(d2, r)
    c, b = ca.dot(d1, r), ca.dot(d1, d2)
    denom = a * e - b * b
    s = ca.if_else(
        denom > 1e-14, ca.fmin(ca.fmax((b * f - c * e) / ca.fmax(denom, 1e-30), 0), 1), 0
    )
    t = (b * s + f) / e
    s = ca.if_else(
        t < 0,
        ca.fmin(ca.fmax(-c / a, 0), 1),
        ca.if_else(t > 1, ca.fmin(ca.fmax((b - c) / a, 0), 1), s),
    )
    t = ca.fmin(ca.fmax(t, 0), 1)
    w = p1 + s * d1 - p2 - t * d2
    return ca.sqrt(ca.dot(w, w) + _TINY)


def segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> float:
    """Distance between segments p1-q1 and p2-q2 (numpy)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    c, b = d1 @ r, d1 @ d2
    denom = a * e - b * b
    s = float(np.clip((b * f - c * e) / denom, 0, 1)) if denom > 1e-14 else 0.0
    t = (b * s + f) / e
    if t < 0:
        t, s = 0.0, float(np.clip(-c / a, 0, 1))
    elif t > 1:
        t, s = 1.0, float(np.clip((b - c) / a, 0, 1))
    w = p1 + s * d1 - p2 - t * d2
    return float(np.sqrt(w @ w + _TINY))


def segment_distances(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Distances between segments p1-q1 and p2-q2 [m], one per row (numpy, shapes (m, 3);
    :func:`segment_distance` on arrays of segments)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    f, c = np.einsum("ij,ij->i", d2, r), np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)
    denom = a * e - b * b
    ok = denom > 1e-14
    s = np.where(ok, np.clip((b * f - c * e) / np.where(ok, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a, 0, 1), np.where(t > 1, np.clip((b - c) / a, 0, 1), s))
    t = np.clip(t, 0, 1)
    w = p1 + s[:, None] * d1 - p2 - t[:, None] * d2
    return np.sqrt(np.einsum("ij,ij->i", w, w) + _TINY)


def box_sdf(p: np.ndarray, box: Box) -> float:
    """Signed distance of point p (base frame) to a box [m] (numpy)."""
    qv = np.abs(box.rotation.T @ (p - box.centre)) - box.half
    out = np.maximum(qv, 0)
    return float(np.sqrt(out @ out + _TINY) + min(qv.max(), 0.0))


_TOUCH2 = 1e-24
"""A point of the segment whose squared distance outside the box is at most this [m^2]
is on or in the box (a face crossing computed with rounding lands within 1e-12 m)."""


_OPS = {
    "abs": (ca.fabs, np.abs),
    "max": (ca.fmax, np.maximum),
    "min": (ca.fmin, np.minimum),
    "where": (ca.if_else, np.where),
    "sqrt": (ca.sqrt, np.sqrt),
    "sign": (ca.sign, np.sign),
    "or_": (ca.logic_or, np.logical_or),
    "and_": (ca.logic_and, np.logical_and),
    "dot": (ca.dot, np.dot),
}
"""The elementary operations the closed forms below use, in CasADi and in numpy."""
_CASADI = SimpleNamespace(**{k: v[0] for k, v in _OPS.items()})
_NUMPY = SimpleNamespace(**{k: v[1] for k, v in _OPS.items()})


def _segment_box(x0: list, v: list, half: list, o: SimpleNamespace) -> Any:
    """The closed form of :func:`segment_box_distance_expr` on three coordinates each of
    the segment's start and direction in the box frame and the half sizes, written once
    for CasADi (``o = _CASADI``, scalars) and numpy (``o = _NUMPY``, arrays of segments)."""

    def at(t: Any) -> list:
        return [x0[j] + t * v[j] for j in range(3)]

    def slope(t: Any) -> Any:
        x = at(t)
        return sum(o.max(o.abs(x[j]) - half[j], 0.0) * o.sign(x[j]) * v[j] for j in range(3))

    def outside2(t: Any) -> Any:
        out = [o.max(o.abs(xj) - hj, 0.0) for xj, hj in zip(at(t), half)]
        return sum(e * e for e in out)

    def sdf(t: Any) -> Any:
        qv = [o.abs(xj) - hj for xj, hj in zip(at(t), half)]
        deepest = o.max(o.max(qv[0], qv[1]), qv[2])
        return o.sqrt(outside2(t) + _TINY) + o.min(deepest, 0.0)

    # breakpoints: the ends, and where a coordinate crosses a face plane (a coordinate
    # that does not move gives 0)
    ts: list = [0.0, 1.0]
    for j in range(3):
        moves = o.abs(v[j]) > 1e-15
        den = o.where(moves, v[j], 1.0)
        for sgn in (1.0, -1.0):
            t = o.where(moves, (sgn * half[j] - x0[j]) / den, 0.0)
            ts.append(o.min(o.max(t, 0.0), 1.0))
    t_l, t_r = 0.0, 1.0
    for t in ts:
        s = slope(t)
        t_l = o.max(t_l, o.where(s <= 0, t, 0.0))
        t_r = o.min(t_r, o.where(s > 0, t, 1.0))
    s_l, s_r = slope(t_l), slope(t_r)
    ok = o.and_(t_r > t_l, s_r - s_l > 0)
    t_star = o.where(ok, t_l - s_l * (t_r - t_l) / o.where(ok, s_r - s_l, 1.0), t_l)
    # Outside: the distance at the minimiser. Entering: the depth in the middle of the
    # part of the segment inside the box (its ends are breakpoints or segment ends).
    t_in, t_out = 1.0, 0.0
    for t in ts:
        touching = outside2(t) <= _TOUCH2
        t_in = o.min(t_in, o.where(touching, t, 1.0))
        t_out = o.max(t_out, o.where(touching, t, 0.0))
    enters = o.or_(outside2(t_star) <= _TOUCH2, t_out >= t_in)
    return sdf(o.where(enters, 0.5 * (t_in + t_out), t_star))


def segment_box_distance_expr(a: ca.SX, b: ca.SX, centre: Any, rotation: Any, half: Any) -> ca.SX:
    """Signed distance between segment a-b and a box (CasADi; the box's centre, rotation
    (columns: its axes) and half sizes may be constants or symbols), in closed form.

    Outside the box the squared distance along the segment, ``sum_j max(|x_j(t)| - h_j,
    0)^2``, is convex and piecewise quadratic in the segment parameter t, with pieces
    that change only where a coordinate crosses a face plane: its slope is linear
    between those breakpoints, so the minimiser lies where the slope changes sign,
    found by linear interpolation between the last breakpoint of non-positive slope and
    the first of positive slope; the value is the distance there, exact. A segment that
    enters the box gets the box's signed distance (<= 0) in the middle of its part
    inside the box, whose ends are breakpoints: not necessarily the deepest point, but
    continuous in the ends and pointing out of the box."""
    x0 = ca.mtimes(rotation.T, a - centre)
    v = ca.mtimes(rotation.T, b - a)
    return _segment_box(
        [x0[j] for j in range(3)], [v[j] for j in range(3)], [half[j] for j in range(3)], _CASADI
    )


def segment_box_distances(
    a: np.ndarray, b: np.ndarray, centre: np.ndarray, rotation: np.ndarray, half: np.ndarray
) -> np.ndarray:
    """Signed distances between segments and boxes [m], one per row (numpy; the closed
    form of :func:`segment_box_distance_expr`): ends ``a``, ``b`` (m, 3), box centres
    (m, 3), rotations (m, 3, 3) and half sizes (m, 3)."""
    x0 = np.einsum("mji,mj->mi", rotation, a - centre)
    v = np.einsum("mji,mj->mi", rotation, b - a)
    return np.asarray(_segment_box(list(x0.T), list(v.T), list(half.T), _NUMPY), dtype=float)


def segment_box_distance(a: np.ndarray, b: np.ndarray, box: Box) -> float:
    """Signed distance between segment a-b (base frame) and a box [m] (numpy)."""
    return float(
        segment_box_distances(
            a[None], b[None], box.centre[None], box.rotation[None], box.half[None]
        )[0]
    )


__all__ = [
    "box_sdf",
    "segment_box_distance",
    "segment_box_distance_expr",
    "segment_box_distances",
    "segment_distance",
    "segment_distances",
]
