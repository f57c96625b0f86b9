"""The base safety filter's geometry: every (shape, obstacle) pair's bound, and the
barrier rows of the pairs that could bind, in one pass.

:class:`~payload.teleop.base_filter.BaseSafetyFilter` calls :func:`barrier_rows` once per
control step. It is the same arithmetic as the filter's description (the module docstring
of :mod:`payload.teleop.base_filter`), written as loops over scalars. The functions here
are plain Python, the reference: in NumPy the step is a few hundred small array calls
whose fixed cost alone exceeds the filter's 200 us budget, so the filter runs them
compiled, as C (:mod:`payload.teleop.barrier_c`, checked against these functions to the
bit when built) or, without a C compiler or with ``PAYLOAD_NATIVE=0``, by Numba
(:func:`numba_kernels`: LLVM, IEEE arithmetic, no fast-math; cached on disk next to this
module, so only the first process compiles them). Numba is imported only then: loading
it and its cached functions took about 0.4 s of every start with the filter.

The divisions are by the filter's positive settings and by norms kept above 1e-12, and
the square root is of a non-negative number, so Python, C and Numba (``error_model=
"numpy"``) meet no division by zero or negative root on the filter's inputs.
"""

from __future__ import annotations

import functools
import math
import types
from collections.abc import Callable

import numpy as np


def _stop_speed(distance: float, accel: float, jerk: float, lag: float) -> float:
    """The largest closing speed [m/s] a jerk-limited brake stops from within ``distance``
    [m] with deceleration ``accel`` [m/s^2] (see
    :func:`payload.teleop.base_filter.stop_speed`)."""
    b = lag + 2.0 * accel / jerk
    d = max(distance, 0.0)
    u = accel * (math.sqrt(b * b + 2.0 * d / accel) - b)
    return max(u - accel * lag - accel * accel / (2.0 * jerk), 0.0)


stop_speed_one = _stop_speed
""":func:`_stop_speed`, as :func:`barrier_rows` calls it (Numba's compiled copy in
:func:`numba_kernels`)."""
stop_speed_many = np.vectorize(_stop_speed, otypes=[float])
""":func:`_stop_speed` over arrays (broadcast), uncompiled: for checks and figures."""


def _barrier(
    pts: np.ndarray,
    k: int,
    obs_lo: np.ndarray,
    obs_hi: np.ndarray,
    m: int,
    rot: np.ndarray,
    centre: np.ndarray,
    body_accel: np.ndarray,
    params: np.ndarray,
) -> tuple[float, float, float, float, float, float]:
    """Point ``pts[k]``'s barrier against box ``m``: (n_x, n_y, n_z, yaw lever
    ``n . (e_z x r)`` [m], bound ``b`` [m/s], distance [m])."""
    margin, jerk, lag, gain, recovery = params[0], params[1], params[2], params[3], params[4]
    n0, n1, n2, d = _normal(pts, k, obs_lo, obs_hi, m)
    nb0 = max(abs(rot[0, 0] * n0 + rot[1, 0] * n1 + rot[2, 0] * n2), 1e-12)
    nb1 = max(abs(rot[0, 1] * n0 + rot[1, 1] * n1 + rot[2, 1] * n2), 1e-12)
    nb2 = max(abs(rot[0, 2] * n0 + rot[1, 2] * n1 + rot[2, 2] * n2), 1e-12)
    accel = min(min(body_accel[0] / nb0, body_accel[1] / nb1), body_accel[2] / nb2)
    gap = d - margin
    b = -stop_speed_one(gap, accel, jerk, lag)
    if gap < 0.0:  # inside the margin: move out at a small speed
        b = min(-gain * gap, recovery)
    arm = n1 * (pts[k, 0] - centre[0]) - n0 * (pts[k, 1] - centre[1])
    return n0, n1, n2, arm, b, d


def barrier_rows(
    xmat: np.ndarray,
    xpos: np.ndarray,
    vehicle: int,
    bodies: np.ndarray,
    boxes: np.ndarray,
    local: np.ndarray,
    first_point: np.ndarray,
    obs: np.ndarray,
    req: np.ndarray,
    params: np.ndarray,
    per_face: int,
    rows: np.ndarray,
    out: np.ndarray,
    lower: np.ndarray,
    pts: np.ndarray,
) -> tuple[int, float]:
    """The barrier rows ``A x >= b`` of the pairs that could bind; returns how many, and
    the least slack among them [m/s] (inf: none).

    Args:
        xmat: Every body's rotation, MuJoCo's ``data.xmat`` (bodies, 9).
        xpos: Every body's position, ``data.xpos`` (bodies, 3) [m].
        vehicle: Astrobee's body.
        bodies: The body of each shape (S,).
        boxes: Each shape's box centre in its body's frame and its half-extents,
            (2, S, 3) [m].
        local: Every shape's sample points in its body's frame, (K, 3) [m].
        first_point: Index of each shape's first point in ``local``, and K, (S + 1,).
        obs: Lower and upper corners of the obstacle boxes, (2, M, 3) [m].
        req: The request (v_x, v_y, v_z [m/s], yaw rate [rad/s]), world frame, (4,).
        params: (margin [m], jerk [m/s^3], lag [s], recovery gain [1/s], recovery
            speed [m/s], deceleration per body axis (3) [m/s^2]).
        per_face: Sample points kept per pair, those of least slack at the request; each
            gives two rows, with and without the yaw term.
        rows: Out: the rows ``A`` (R, 4); pairs in shape-major order, least slack first.
        out: Out: their bounds ``b`` [m/s] and their point's slack at the request (the
            lesser of its two rows') [m/s], (2, R).
        lower: Out: a lower bound of each pair's distance (S, M) [m]; the least sampled
            distance for the pairs checked point by point.
        pts: Scratch: world positions of the sample points (K, 3) [m].
    """
    margin, jerk, lag = params[0], params[1], params[2]
    body_accel = params[5:8]
    rot = xmat[vehicle].reshape((3, 3))
    centre = xpos[vehicle]
    obs_lo, obs_hi = obs[0], obs[1]
    n_shapes, n_obs = bodies.shape[0], obs_lo.shape[0]
    w = abs(req[3])
    axis_accel = np.empty(3)
    for i in range(3):  # deceleration along each world axis (its body components)
        best = np.inf
        for j in range(3):
            best = min(best, body_accel[j] / max(abs(rot[i, j]), 1e-12))
        axis_accel[i] = best
    s_centre = np.empty(3)
    ext = np.empty(3)
    toward = np.empty(3)
    away = np.empty(3)
    sel = np.empty(per_face, dtype=np.int64)
    sel_slack = np.empty(per_face)
    count = 0
    least_slack = np.inf
    for s in range(n_shapes):
        frame = xmat[bodies[s]].reshape((3, 3))
        origin = xpos[bodies[s]]
        for i in range(3):
            c = origin[i]
            e = 0.0
            for j in range(3):
                c += frame[i, j] * boxes[0, s, j]
                e += abs(frame[i, j]) * boxes[1, s, j]
            s_centre[i], ext[i] = c, e
        lever = np.empty(3)
        for i in range(3):
            lever[i] = w * (abs(s_centre[i] - centre[i]) + ext[i])
        lev = (lever[1], lever[0], 0.0)
        for i in range(3):
            toward[i] = req[i] + lev[i]
            away[i] = lev[i] - req[i]
        placed = False
        for m in range(n_obs):
            safe = False
            gap_max = -np.inf
            for i in range(3):
                above = obs_lo[m, i] - (s_centre[i] + ext[i])
                below = (s_centre[i] - ext[i]) - obs_hi[m, i]
                gap = max(above, below)
                gap_max = max(gap_max, gap)
                if gap > margin:
                    closing = toward[i] if above > below else away[i]
                    if closing <= stop_speed_one(gap - margin, axis_accel[i], jerk, lag):
                        safe = True
            lower[s, m] = gap_max
            if safe:
                continue
            if not placed:  # this shape's sample points in the world, once per step
                for k in range(first_point[s], first_point[s + 1]):
                    for i in range(3):
                        pts[k, i] = (
                            origin[i]
                            + frame[i, 0] * local[k, 0]
                            + frame[i, 1] * local[k, 1]
                            + frame[i, 2] * local[k, 2]
                        )
                placed = True
            kept = 0
            least = np.inf
            for k in range(first_point[s], first_point[s + 1]):
                n0, n1, n2, arm, b, d = _barrier(
                    pts, k, obs_lo, obs_hi, m, rot, centre, body_accel, params
                )
                least = min(least, d)
                sk = req[0] * n0 + req[1] * n1 + req[2] * n2 + min(req[3] * arm, 0.0) - b
                # keep the per_face least slack (ties: the earlier point first)
                pos = kept
                while pos > 0 and sel_slack[pos - 1] > sk:
                    pos -= 1
                if pos < per_face:
                    for q in range(min(kept, per_face - 1), pos, -1):
                        sel[q], sel_slack[q] = sel[q - 1], sel_slack[q - 1]
                    sel[pos], sel_slack[pos] = k, sk
                    kept = min(kept + 1, per_face)
            lower[s, m] = least
            for q in range(kept):
                n0, n1, n2, arm, b, d = _barrier(
                    pts, sel[q], obs_lo, obs_hi, m, rot, centre, body_accel, params
                )
                for with_yaw in range(2):
                    rows[count, 0], rows[count, 1], rows[count, 2] = n0, n1, n2
                    rows[count, 3] = arm if with_yaw else 0.0
                    out[0, count] = b
                    out[1, count] = sel_slack[q]
                    count += 1
                least_slack = min(least_slack, sel_slack[q])
    return count, least_slack


def enclosing_box(
    geom_xpos: np.ndarray,
    geom_xmat: np.ndarray,
    corner_geom: np.ndarray,
    corners: np.ndarray,
    origin: np.ndarray,
    frame: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The box enclosing geom corners, in a body's frame: (lo (3,), hi (3,)) [m].

    Args:
        geom_xpos: Every geom's position, MuJoCo's ``data.geom_xpos`` (geoms, 3) [m].
        geom_xmat: Every geom's rotation, ``data.geom_xmat`` (geoms, 9).
        corner_geom: The geom of each corner (N,).
        corners: The corners in their geom's frame (N, 3) [m].
        origin: The body's position (3,) [m]; ``frame`` its rotation (3, 3).
    """
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    r = np.empty(3)
    for k in range(corner_geom.shape[0]):
        g = corner_geom[k]
        for i in range(3):  # the corner in the world, relative to the body's origin
            r[i] = (
                geom_xpos[g, i]
                + geom_xmat[g, 3 * i] * corners[k, 0]
                + geom_xmat[g, 3 * i + 1] * corners[k, 1]
                + geom_xmat[g, 3 * i + 2] * corners[k, 2]
                - origin[i]
            )
        r0, r1, r2 = r[0], r[1], r[2]
        for j in range(3):  # the corner relative to the body, in the body's frame
            v = frame[0, j] * r0 + frame[1, j] * r1 + frame[2, j] * r2
            lo[j] = min(lo[j], v)
            hi[j] = max(hi[j], v)
    return lo, hi


def _normal(
    pts: np.ndarray, k: int, obs_lo: np.ndarray, obs_hi: np.ndarray, m: int
) -> tuple[float, float, float, float]:
    """Unit normal (out of box ``m``) and signed distance [m] of point ``pts[k]``: from
    the box's closest point, or, inside it, to its nearest face (negative)."""
    p0, p1, p2 = pts[k, 0], pts[k, 1], pts[k, 2]
    d0 = p0 - min(max(p0, obs_lo[m, 0]), obs_hi[m, 0])
    d1 = p1 - min(max(p1, obs_lo[m, 1]), obs_hi[m, 1])
    d2 = p2 - min(max(p2, obs_lo[m, 2]), obs_hi[m, 2])
    d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if d > 1e-12:
        return d0 / d, d1 / d, d2 / d, d
    best, axis, sign = np.inf, 0, 1.0
    for i in range(3):
        below, above = pts[k, i] - obs_lo[m, i], obs_hi[m, i] - pts[k, i]
        depth = min(below, above)
        if depth < best:
            best, axis = depth, i
            sign = -1.0 if below < above else 1.0
    return (
        sign if axis == 0 else 0.0,
        sign if axis == 1 else 0.0,
        sign if axis == 2 else 0.0,
        -best,
    )


NUMBA_INLINE: tuple[str, ...] = ("_normal", "_barrier")
"""The helpers Numba inlines into :func:`barrier_rows` (as C's ``static`` functions)."""


@functools.cache
def numba_kernels() -> tuple[Callable[..., tuple[int, float]], Callable[..., tuple]]:
    """:func:`barrier_rows` and :func:`enclosing_box` compiled by Numba (``cache=True``:
    loaded from its disk cache after the first process): the filter's kernels where the
    C is not built. The functions are copies of this module's, whose globals name the
    compiled helpers, so the module's own functions stay plain Python."""
    import numba

    scope = dict(globals())

    def jit(name: str, **options: str) -> None:
        fn = globals()[name]
        copy = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__)
        scope[name] = numba.njit(cache=True, error_model="numpy", **options)(copy)

    jit("_stop_speed")
    scope["stop_speed_one"] = scope["_stop_speed"]
    for name in NUMBA_INLINE:
        jit(name, inline="always")
    jit("barrier_rows")
    jit("enclosing_box")
    return scope["barrier_rows"], scope["enclosing_box"]


__all__ = [
    "NUMBA_INLINE",
    "barrier_rows",
    "enclosing_box",
    "numba_kernels",
    "stop_speed_many",
    "stop_speed_one",
]
