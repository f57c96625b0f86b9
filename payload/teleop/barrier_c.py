"""The base safety filter's geometry as compiled C: :func:`~payload.teleop.filter_kernel.
barrier_rows` and :func:`~payload.teleop.filter_kernel.enclosing_box`, with their bits.

The same loops as the Python reference in :mod:`payload.teleop.filter_kernel`, written
as C with the same operations in the same order (no contraction into fused
multiply-adds: :data:`payload.native_build.CFLAGS`), Python's ``min`` and ``max`` of two
floats (the first unless the second is less, or greater) and ``math.sqrt``'s ``sqrt``.
:func:`compiled_barrier` builds it and checks it against the Python functions on random
shapes, obstacles, poses and requests (every array the functions write compared to the
bit); without a compiler, with ``PAYLOAD_NATIVE=0``, a failed build or a check that
differs, the filter runs Numba's compilation of the Python
(:func:`~payload.teleop.filter_kernel.numba_kernels`).

The C replaces Numba in the filter because loading Numba and its cached functions cost
about 0.4 s of every start with the filter (``teleop serve``, ``hw run``, a ``safe``
trial), and compiling them in a fresh checkout about 5 s; the C is one small library,
built once and checked in a few milliseconds.
"""

from __future__ import annotations

import ctypes
import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.rotations import random_rotations
from payload.teleop import filter_kernel as ref

log = logging.getLogger(__name__)

SOURCE = r"""
/* Python's min and max of two floats: the first unless the second is less (greater) */
static double pymin(double a, double b) { return b < a ? b : a; }
static double pymax(double a, double b) { return b > a ? b : a; }

/* filter_kernel._stop_speed */
static double stop_speed(double distance, double accel, double jerk, double lag)
{
    double b = lag + 2.0 * accel / jerk;
    double d = pymax(distance, 0.0);
    double u = accel * (sqrt(b * b + 2.0 * d / accel) - b);
    return pymax(u - accel * lag - accel * accel / (2.0 * jerk), 0.0);
}

/* filter_kernel._normal: n (3) and the signed distance, of point p against box lo..hi */
static double normal(const double *p, const double *lo, const double *hi, double *n)
{
    double d0 = p[0] - pymin(pymax(p[0], lo[0]), hi[0]);
    double d1 = p[1] - pymin(pymax(p[1], lo[1]), hi[1]);
    double d2 = p[2] - pymin(pymax(p[2], lo[2]), hi[2]);
    double d = sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    if (d > 1e-12) {
        n[0] = d0 / d; n[1] = d1 / d; n[2] = d2 / d;
        return d;
    }
    double best = INFINITY, sign = 1.0;
    int axis = 0;
    for (int i = 0; i < 3; i++) {
        double below = p[i] - lo[i], above = hi[i] - p[i];
        double depth = pymin(below, above);
        if (depth < best) {
            best = depth; axis = i;
            sign = below < above ? -1.0 : 1.0;
        }
    }
    n[0] = axis == 0 ? sign : 0.0;
    n[1] = axis == 1 ? sign : 0.0;
    n[2] = axis == 2 ? sign : 0.0;
    return -best;
}

/* filter_kernel._barrier: r = (n_x, n_y, n_z, arm, b, d) of point p against box lo..hi */
static void barrier(const double *p, const double *lo, const double *hi, const double *rot,
                    const double *centre, const double *body_accel, const double *params,
                    double *r)
{
    double margin = params[0], jerk = params[1], lag = params[2];
    double gain = params[3], recovery = params[4];
    double n[3];
    double d = normal(p, lo, hi, n);
    double n0 = n[0], n1 = n[1], n2 = n[2];
    double nb0 = pymax(fabs(rot[0] * n0 + rot[3] * n1 + rot[6] * n2), 1e-12);
    double nb1 = pymax(fabs(rot[1] * n0 + rot[4] * n1 + rot[7] * n2), 1e-12);
    double nb2 = pymax(fabs(rot[2] * n0 + rot[5] * n1 + rot[8] * n2), 1e-12);
    double accel = pymin(pymin(body_accel[0] / nb0, body_accel[1] / nb1), body_accel[2] / nb2);
    double gap = d - margin;
    double b = -stop_speed(gap, accel, jerk, lag);
    if (gap < 0.0) b = pymin(-gain * gap, recovery);
    r[0] = n0; r[1] = n1; r[2] = n2;
    r[3] = n1 * (p[0] - centre[0]) - n0 * (p[1] - centre[1]);
    r[4] = b; r[5] = d;
}

/* filter_kernel.barrier_rows (its arguments in order; n_body, n_shapes, n_boxes, n_local,
   n_obs, n_rows the sizes of xmat and xpos, bodies, boxes (2, n_boxes, 3), local and
   pts, obs and rows; sel and sel_slack scratch of per_face); returns the count of rows
   and writes the least slack, or -1 (nothing written) for a body or point index out of
   range, -2 (rows written up to the end) for more rows than rows holds: where the Python
   raises IndexError */
int64_t payload_barrier_rows(
    const double *xmat, const double *xpos, int64_t n_body, int64_t vehicle,
    const int64_t *bodies, int64_t n_shapes, const double *boxes, int64_t n_boxes,
    const double *local, int64_t n_local, const int64_t *first_point,
    const double *obs, int64_t n_obs, const double *req, const double *params,
    int64_t per_face, double *rows, double *out, int64_t n_rows, double *lower, double *pts,
    int64_t *sel, double *sel_slack, double *least_out)
{
    if (vehicle < 0 || vehicle >= n_body || first_point[0] < 0
        || first_point[n_shapes] > n_local)
        return -1;
    for (int64_t s = 0; s < n_shapes; s++)
        if (bodies[s] < 0 || bodies[s] >= n_body || first_point[s + 1] < first_point[s])
            return -1;
    double margin = params[0], jerk = params[1], lag = params[2];
    const double *body_accel = params + 5;
    const double *rot = xmat + 9 * vehicle, *centre = xpos + 3 * vehicle;
    const double *obs_lo = obs, *obs_hi = obs + 3 * n_obs;
    double w = fabs(req[3]);
    double axis_accel[3], s_centre[3], ext[3], lever[3], toward[3], away[3], r[6];
    for (int i = 0; i < 3; i++) {
        double best = INFINITY;
        for (int j = 0; j < 3; j++)
            best = pymin(best, body_accel[j] / pymax(fabs(rot[3 * i + j]), 1e-12));
        axis_accel[i] = best;
    }
    int64_t count = 0;
    double least_slack = INFINITY;
    for (int64_t s = 0; s < n_shapes; s++) {
        const double *frame = xmat + 9 * bodies[s], *origin = xpos + 3 * bodies[s];
        for (int i = 0; i < 3; i++) {
            double c = origin[i], e = 0.0;
            for (int j = 0; j < 3; j++) {
                c += frame[3 * i + j] * boxes[3 * s + j];
                e += fabs(frame[3 * i + j]) * boxes[3 * n_boxes + 3 * s + j];
            }
            s_centre[i] = c; ext[i] = e;
        }
        for (int i = 0; i < 3; i++) lever[i] = w * (fabs(s_centre[i] - centre[i]) + ext[i]);
        double lev[3] = {lever[1], lever[0], 0.0};
        for (int i = 0; i < 3; i++) {
            toward[i] = req[i] + lev[i];
            away[i] = lev[i] - req[i];
        }
        int placed = 0;
        for (int64_t m = 0; m < n_obs; m++) {
            const double *lo = obs_lo + 3 * m, *hi = obs_hi + 3 * m;
            int safe = 0;
            double gap_max = -INFINITY;
            for (int i = 0; i < 3; i++) {
                double above = lo[i] - (s_centre[i] + ext[i]);
                double below = (s_centre[i] - ext[i]) - hi[i];
                double gap = pymax(above, below);
                gap_max = pymax(gap_max, gap);
                if (gap > margin) {
                    double closing = above > below ? toward[i] : away[i];
                    if (closing <= stop_speed(gap - margin, axis_accel[i], jerk, lag)) safe = 1;
                }
            }
            lower[n_obs * s + m] = gap_max;
            if (safe) continue;
            if (!placed) {
                for (int64_t k = first_point[s]; k < first_point[s + 1]; k++)
                    for (int i = 0; i < 3; i++)
                        pts[3 * k + i] = origin[i] + frame[3 * i] * local[3 * k]
                                         + frame[3 * i + 1] * local[3 * k + 1]
                                         + frame[3 * i + 2] * local[3 * k + 2];
                placed = 1;
            }
            int64_t kept = 0;
            double least = INFINITY;
            for (int64_t k = first_point[s]; k < first_point[s + 1]; k++) {
                barrier(pts + 3 * k, lo, hi, rot, centre, body_accel, params, r);
                least = pymin(least, r[5]);
                double sk = req[0] * r[0] + req[1] * r[1] + req[2] * r[2]
                            + pymin(req[3] * r[3], 0.0) - r[4];
                int64_t pos = kept;
                while (pos > 0 && sel_slack[pos - 1] > sk) pos--;
                if (pos < per_face) {
                    int64_t top = kept < per_face - 1 ? kept : per_face - 1;
                    for (int64_t q = top; q > pos; q--) {
                        sel[q] = sel[q - 1];
                        sel_slack[q] = sel_slack[q - 1];
                    }
                    sel[pos] = k;
                    sel_slack[pos] = sk;
                    kept = kept + 1 < per_face ? kept + 1 : per_face;
                }
            }
            lower[n_obs * s + m] = least;
            for (int64_t q = 0; q < kept; q++) {
                barrier(pts + 3 * sel[q], lo, hi, rot, centre, body_accel, params, r);
                if (count + 2 > n_rows) return -2;
                for (int with_yaw = 0; with_yaw < 2; with_yaw++) {
                    rows[4 * count] = r[0];
                    rows[4 * count + 1] = r[1];
                    rows[4 * count + 2] = r[2];
                    rows[4 * count + 3] = with_yaw ? r[3] : 0.0;
                    out[count] = r[4];
                    out[n_rows + count] = sel_slack[q];
                    count++;
                }
                least_slack = pymin(least_slack, sel_slack[q]);
            }
        }
    }
    *least_out = least_slack;
    return count;
}

/* filter_kernel.enclosing_box: lo (3) then hi (3) into box; -1 (nothing written) for a
   geom index out of range (n_geom: the geoms of geom_xpos and geom_xmat) */
int payload_enclosing_box(const double *geom_xpos, const double *geom_xmat, int64_t n_geom,
                          const int64_t *corner_geom, int64_t n, const double *corners,
                          const double *origin, const double *frame, double *box)
{
    for (int64_t k = 0; k < n; k++)
        if (corner_geom[k] < 0 || corner_geom[k] >= n_geom) return -1;
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    double r[3];
    for (int64_t k = 0; k < n; k++) {
        int64_t g = corner_geom[k];
        for (int i = 0; i < 3; i++)
            r[i] = geom_xpos[3 * g + i] + geom_xmat[9 * g + 3 * i] * corners[3 * k]
                   + geom_xmat[9 * g + 3 * i + 1] * corners[3 * k + 1]
                   + geom_xmat[9 * g + 3 * i + 2] * corners[3 * k + 2] - origin[i];
        for (int j = 0; j < 3; j++) {
            double v = frame[j] * r[0] + frame[3 + j] * r[1] + frame[6 + j] * r[2];
            lo[j] = pymin(lo[j], v);
            hi[j] = pymax(hi[j], v);
        }
    }
    for (int j = 0; j < 3; j++) { box[j] = lo[j]; box[3 + j] = hi[j]; }
    return 0;
}
"""

_F64, _I64 = np.dtype(np.float64), np.dtype(np.int64)

SEEN_MOST = 64
"""Arrays whose addresses :class:`CompiledBarrier` keeps (then it starts afresh)."""


def _ptr(a: np.ndarray, dtype: np.dtype, name: str) -> int:
    """The address of ``a``'s data, which the C reads as a C-contiguous array of
    ``dtype``; ValueError otherwise (the caller's arrays always are: a wrong one is a bug
    the C must not read past)."""
    if a.dtype != dtype or not a.flags.c_contiguous:
        raise ValueError(f"{name}: not a C-contiguous {dtype} array")
    return a.ctypes.data


class CompiledBarrier:
    """The C's two functions, called with the Python functions' arguments."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        ptr, i64 = ctypes.c_void_p, ctypes.c_int64
        rows = lib.payload_barrier_rows
        rows.restype = i64
        rows.argtypes = [ptr, ptr, i64, i64, ptr, i64, ptr, i64, ptr, i64, ptr, ptr, i64]
        rows.argtypes += [ptr, ptr, i64]
        rows.argtypes += [ptr, ptr, i64, ptr, ptr, ptr, ptr, ptr]
        self._rows = rows
        box = lib.payload_enclosing_box
        box.restype = ctypes.c_int
        box.argtypes = [ptr, ptr, i64, ptr, i64, ptr, ptr, ptr, ptr]
        self._box = box
        self._least = np.zeros(1)
        self._scratch: tuple[np.ndarray, np.ndarray] = (np.zeros(1, np.int64), np.zeros(1))
        self._seen: dict[int, tuple[np.ndarray, int]] = {}

    def _address(self, a: np.ndarray, dtype: np.dtype, name: str) -> int:
        """:func:`_ptr` of ``a``, kept for the array (the filter passes the same arrays at
        every step: their checks and ctypes' address object cost more than the C)."""
        seen = self._seen.get(id(a))
        if seen is not None and seen[0] is a:
            return seen[1]
        address = _ptr(a, dtype, name)
        if len(self._seen) >= SEEN_MOST:
            self._seen.clear()
        self._seen[id(a)] = (a, address)
        return address

    def barrier_rows(
        self,
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
        """:func:`payload.teleop.filter_kernel.barrier_rows`, in C."""
        n_shapes, n_obs, n_rows = bodies.shape[0], obs.shape[1], rows.shape[0]
        if (
            obs.shape != (2, n_obs, 3)
            or rows.shape != (n_rows, 4)
            or req.shape[0] < 4
            or per_face < 0
            or bodies.ndim != 1
            or first_point.ndim != 1
            or local.shape[1:] != (3,)
        ):
            raise ValueError("barrier_rows: arrays of other shapes than the filter's")
        if (
            boxes.ndim != 3
            or boxes.shape[0] != 2
            or boxes.shape[1] < n_shapes
            or boxes.shape[2] != 3
            or first_point.shape[0] < n_shapes + 1
            or lower.shape != (n_shapes, n_obs)
            or out.shape != (2, n_rows)
            or params.shape[0] < 8
            or pts.shape != local.shape
            or xmat.shape[1:] != (9,)
            or xpos.shape != (xmat.shape[0], 3)
            or not 0 <= vehicle < xmat.shape[0]
        ):
            raise ValueError("barrier_rows: arrays of other shapes than the filter's")
        sel, sel_slack = self._scratch
        if sel.shape[0] < per_face:
            self._scratch = sel, sel_slack = np.zeros(per_face, np.int64), np.zeros(per_face)
        at = self._address
        count = self._rows(
            at(xmat, _F64, "xmat"), at(xpos, _F64, "xpos"), xmat.shape[0], vehicle,
            at(bodies, _I64, "bodies"), n_shapes, at(boxes, _F64, "boxes"),
            boxes.shape[1], at(local, _F64, "local"), local.shape[0],
            at(first_point, _I64, "first_point"),
            at(obs, _F64, "obs"), n_obs, at(req, _F64, "req"),
            at(params, _F64, "params"), per_face, at(rows, _F64, "rows"),
            at(out, _F64, "out"), n_rows, at(lower, _F64, "lower"),
            at(pts, _F64, "pts"), at(sel, _I64, "sel"), at(sel_slack, _F64, "sel_slack"),
            at(self._least, _F64, "least"),
        )  # fmt: skip
        if count < 0:
            what = "a body or sample point index" if count == -1 else "more rows than rows holds"
            raise IndexError(f"barrier_rows: {what} out of range")
        return int(count), float(self._least[0])

    def enclosing_box(
        self,
        geom_xpos: np.ndarray,
        geom_xmat: np.ndarray,
        corner_geom: np.ndarray,
        corners: np.ndarray,
        origin: np.ndarray,
        frame: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`payload.teleop.filter_kernel.enclosing_box`, in C."""
        n = corner_geom.shape[0]
        if (
            corners.shape != (n, 3)
            or origin.shape != (3,)
            or frame.shape != (3, 3)
            or geom_xmat.shape[1:] != (9,)
            or geom_xpos.shape != (geom_xmat.shape[0], 3)
        ):
            raise ValueError("enclosing_box: arrays of other shapes than the filter's")
        box = np.empty(6)
        at = self._address
        if self._box(
            at(geom_xpos, _F64, "geom_xpos"), at(geom_xmat, _F64, "geom_xmat"),
            geom_xmat.shape[0], at(corner_geom, _I64, "corner_geom"), n,
            at(corners, _F64, "corners"), at(origin, _F64, "origin"), at(frame, _F64, "frame"),
            box.ctypes.data,
        ) != 0:  # fmt: skip
            raise IndexError("enclosing_box: a geom index out of range")
        return box[:3], box[3:]


CHECK_PROBES = 120
"""Random scenes of the kernel's full self-check (:func:`compiled_barrier`)."""


def probe_scene(k: int) -> dict[str, Any]:
    """The ``k``-th random scene of the self-check: three to five bodies (the vehicle any
    of them), two or three shapes (and every other scene a box more than shapes, as the
    filter's without the CTB) with four to twelve sample points each, two to five
    obstacle boxes near them (some around a point, so points lie inside one), a request
    and the filter's settings; ``per_face`` from one to four. The same scene for the
    same ``k``."""
    rng = np.random.default_rng(1000 + k)
    n_bodies = int(rng.integers(3, 6))
    xmat = random_rotations(rng, n_bodies)
    if k % 7 == 3:  # axis-aligned: bodies' rotations with zeros and signed zeros
        xmat[:] = np.eye(3).ravel()
        xmat[:, 1] = -0.0
    xpos = rng.normal(scale=0.5, size=(n_bodies, 3))
    n_shapes = int(rng.integers(2, 4))
    bodies = rng.integers(0, n_bodies, size=n_shapes).astype(np.int64)
    n_boxes = n_shapes + k % 2  # as the filter's, a box for a shape not passed (the CTB)
    boxes = np.stack([rng.normal(scale=0.1, size=(n_boxes, 3)),
                      rng.uniform(0.02, 0.2, size=(n_boxes, 3))])  # fmt: skip
    counts = rng.integers(4, 13, size=n_shapes)
    first_point = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    local = rng.normal(scale=0.15, size=(int(first_point[-1]), 3))
    n_obs = int(rng.integers(2, 6))
    centres = xpos[bodies[rng.integers(0, n_shapes, size=n_obs)]] + rng.normal(
        scale=0.4, size=(n_obs, 3)
    )
    half = rng.uniform(0.05, 0.6, size=(n_obs, 3))
    obs = np.stack([centres - half, centres + half])
    if k % 3 == 1:  # an obstacle around a sample point: points inside it
        s = int(rng.integers(0, n_shapes))
        frame = xmat[bodies[s]].reshape(3, 3)
        p = xpos[bodies[s]] + frame @ local[first_point[s]]
        obs[0, 0], obs[1, 0] = p - 0.05, p + 0.05
    scale = (0.0, 0.05, 0.3, 1.0)[k % 4]
    req = np.concatenate([rng.normal(scale=scale, size=3), rng.normal(scale=scale, size=1)])
    if k % 5 == 2:
        req[3] = -0.0
    params = np.array([
        rng.uniform(0.0, 0.1),  # margin [m]
        rng.uniform(0.1, 5.0),  # jerk [m/s^3]
        rng.uniform(0.0, 0.3),  # lag [s]
        rng.uniform(0.5, 5.0),  # recovery gain [1/s]
        rng.uniform(0.005, 0.05),  # recovery speed [m/s]
        *rng.uniform(0.005, 0.2, size=3),  # deceleration per body axis [m/s^2]
    ])  # fmt: skip
    per_face = int(rng.integers(1, 5))
    most = 2 * per_face * n_shapes * n_obs
    return {
        "xmat": xmat, "xpos": xpos, "vehicle": int(rng.integers(0, n_bodies)),
        "bodies": bodies, "boxes": boxes,
        "local": local, "first_point": first_point, "obs": obs, "req": req,
        "params": params, "per_face": per_face, "most": most,
    }  # fmt: skip


def run_rows(rows_fn: Callable[..., tuple[int, float]], scene: dict[str, Any]) -> list[bytes]:
    """Everything ``rows_fn`` (a :func:`~payload.teleop.filter_kernel.barrier_rows`)
    answers and writes for ``scene``, as bytes: the count, the least slack, the rows and
    bounds it filled, every pair's lower bound and the points it placed."""
    sc = scene
    most = sc["most"]
    rows, out = np.full((most, 4), np.nan), np.full((2, most), np.nan)
    lower = np.full((sc["bodies"].shape[0], sc["obs"].shape[1]), np.nan)
    pts = np.zeros_like(sc["local"])
    count, least = rows_fn(
        sc["xmat"], sc["xpos"], sc["vehicle"], sc["bodies"], sc["boxes"], sc["local"],
        sc["first_point"], sc["obs"], sc["req"], sc["params"], sc["per_face"], rows, out,
        lower, pts,
    )  # fmt: skip
    parts = [np.int64(count).tobytes(), np.float64(least).tobytes(), rows[:count].tobytes()]
    return [*parts, out[:, :count].tobytes(), lower.tobytes(), pts.tobytes()]


def run_box(box_fn: Callable[..., tuple], scene: dict[str, Any]) -> list[bytes]:
    """What ``box_fn`` (an :func:`~payload.teleop.filter_kernel.enclosing_box`) answers
    for the scene's bodies taken as geoms, each shape's local points as corners."""
    sc = scene
    corner_geom = np.repeat(sc["bodies"], 4).astype(np.int64)
    corners = np.ascontiguousarray(sc["local"][: corner_geom.shape[0]])
    if corners.shape[0] < corner_geom.shape[0]:
        corner_geom = corner_geom[: corners.shape[0]].copy()
    frame = np.ascontiguousarray(sc["xmat"][0].reshape(3, 3))
    lo, hi = box_fn(sc["xpos"], sc["xmat"], corner_geom, corners, sc["xpos"][0].copy(), frame)
    return [np.asarray(lo, float).tobytes(), np.asarray(hi, float).tobytes()]


def check_barrier(kernel: CompiledBarrier, n: int) -> bool:
    """Whether ``kernel`` answers as the Python functions do, to the bit, on the first
    ``n`` probe scenes (:func:`probe_scene`), and on an empty one."""
    for k in range(n):
        scene = probe_scene(k)
        if run_rows(kernel.barrier_rows, scene) != run_rows(ref.barrier_rows, scene):
            return False
        if run_box(kernel.enclosing_box, scene) != run_box(ref.enclosing_box, scene):
            return False
    none, empty = np.zeros(0, np.int64), np.zeros((0, 3))
    eye = np.eye(3)
    got = kernel.enclosing_box(empty, np.zeros((0, 9)), none, empty, np.zeros(3), eye)
    want = ref.enclosing_box(empty, np.zeros((0, 9)), none, empty, np.zeros(3), eye)
    return all(math.isinf(v) for v in (*got[0], *got[1])) and all(
        a.tobytes() == b.tobytes() for a, b in zip(got, want)
    )


@native.reported("base filter geometry")
def compiled_barrier() -> CompiledBarrier | None:
    """The compiled :func:`~payload.teleop.filter_kernel.barrier_rows` and
    :func:`~payload.teleop.filter_kernel.enclosing_box`, checked against the Python on
    :data:`CHECK_PROBES` random scenes (their first tenth once a check passed: the
    kernel's code has no data of its own), or None (no compiler, ``PAYLOAD_NATIVE=0``, a
    failed build or check): the filter then runs Numba's."""
    lib = native.load_kernel("barrier", SOURCE, "the base filter's geometry kernel", log)
    if lib is None:
        return None
    kernel = CompiledBarrier(lib)
    if not native.self_checked(lib, "barrier", CHECK_PROBES, lambda n: check_barrier(kernel, n)):
        log.warning("the base filter's geometry kernel: Numba (the compiled kernel differs)")
        return None
    return kernel


def geometry_kernels() -> tuple[Callable[..., tuple[int, float]], Callable[..., tuple]]:
    """The filter's ``barrier_rows`` and ``enclosing_box``: the C's
    (:func:`compiled_barrier`), else Numba's compilation of the Python
    (:func:`payload.teleop.filter_kernel.numba_kernels`)."""
    kernel = compiled_barrier()
    if kernel is not None:
        return kernel.barrier_rows, kernel.enclosing_box
    return ref.numba_kernels()


__all__ = [
    "CHECK_PROBES",
    "CompiledBarrier",
    "check_barrier",
    "compiled_barrier",
    "geometry_kernels",
    "probe_scene",
]
