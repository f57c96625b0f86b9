"""The station clearance as compiled C: the quick bound, then the distances near a wall.

:meth:`payload.sim.station.StationMonitor.read` runs every control step of every trial,
and on most steps (mid-module) it ends at its first test: a box around every moving
geom's box (its frame's origin plus a fixed reach) whose union comes within
:data:`~payload.sim.station.CLEARANCE_CAP` of no station box. That test is maxima,
minima, additions, subtractions and comparisons, exact in any order, so one C call gives
the numpy test's answer (NaN included: a NaN position propagates through the maxima and
fails every comparison, as in numpy). Near a wall (about a quarter of a trial's steps)
a second call reads the clearance as
:meth:`~payload.sim.station.StationMonitor._clearance_numpy` does: the moving geoms' world
boxes with their three products summed as numpy's ``einsum`` sums them on this machine
(the first and third, then the second), the station boxes near their union, and
MuJoCo's own ``mj_geomDistance`` (from the library its bindings loaded) for the pairs
within the cap, in numpy's order. Both are checked against the numpy code on random poses
when built (the clearance's boxes too, bit for bit). Without a compiler, without the
MuJoCo symbol (then the bound alone is compiled) or with ``PAYLOAD_NATIVE=0`` the numpy
code runs.

MuJoCo's function is called directly, not through its Python bindings: an ``mju_error``
inside it would reach MuJoCo's own error handler (which ends the process) rather than
raise ``mujoco.FatalError``; the distance query raises none for the geoms it is given
(the same holds for ``mj_applyFT`` in :mod:`payload.sim.vehicle_c`).
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.rotations import random_rotations

log = logging.getLogger(__name__)

SOURCE = r"""

/* numpy's maximum/minimum reductions: a NaN wins and stays */
static double nmax(double a, double b) { return (b > a || b != b) && a == a ? b : a; }
static double nmin(double a, double b) { return (b < a || b != b) && a == a ? b : a; }

/* 1 if some station box (lo, hi: (ns, 3)) comes within cap of the union of the boxes
   xpos[geom] +- reach (geoms: ng indices), else 0 */
int payload_station_near(const double *xpos, const int64_t *geoms, const double *reach,
                         int64_t ng, const double *s_lo, const double *s_hi, int64_t ns,
                         double cap)
{
    double hi[3], lo[3];
    for (int i = 0; i < 3; i++) {
        hi[i] = xpos[3 * geoms[0] + i] + reach[0];
        lo[i] = xpos[3 * geoms[0] + i] - reach[0];
    }
    for (int64_t g = 1; g < ng; g++)
        for (int i = 0; i < 3; i++) {
            hi[i] = nmax(hi[i], xpos[3 * geoms[g] + i] + reach[g]);
            lo[i] = nmin(lo[i], xpos[3 * geoms[g] + i] - reach[g]);
        }
    for (int64_t s = 0; s < ns; s++) {
        int all = 1;
        for (int i = 0; i < 3; i++)
            all &= (s_lo[3 * s + i] - hi[i] < cap) & (lo[i] - s_hi[3 * s + i] < cap);
        if (all) return 1;
    }
    return 0;
}

typedef double (*geomdist_fn)(const void *, void *, int, int, double, double *);

/* StationMonitor._clearance_numpy: the moving geoms' world boxes (centre xpos + R c and
   half-size |R| h, each row's three products summed as numpy's einsum sums them here:
   the first and third, then the second), the station boxes within cap of their union,
   then MuJoCo's distance for every pair whose boxes come within cap (moving geom by
   moving geom, station box by station box), the least of them and cap. */
double payload_station_clearance(void *geomdist, const void *m, void *d, const double *xpos,
    const double *xmat, const double *aabb, const int64_t *geoms, int64_t ng,
    const int64_t *station, const double *s_lo, const double *s_hi, int64_t ns, double cap,
    double *lo, double *hi, int64_t *near, double *fromto)
{
    geomdist_fn dist = (geomdist_fn)geomdist;
    double ulo[3], uhi[3];
    for (int64_t g = 0; g < ng; g++) {
        const double *r = xmat + 9 * geoms[g], *c = aabb + 6 * geoms[g], *h = c + 3;
        for (int i = 0; i < 3; i++) {
            const double *ri = r + 3 * i;
            double centre = xpos[3 * geoms[g] + i]
                          + ((ri[0] * c[0] + ri[2] * c[2]) + ri[1] * c[1]);
            double half = (fabs(ri[0]) * h[0] + fabs(ri[2]) * h[2]) + fabs(ri[1]) * h[1];
            lo[3 * g + i] = centre - half;
            hi[3 * g + i] = centre + half;
            ulo[i] = g ? nmin(ulo[i], lo[3 * g + i]) : lo[3 * g + i];
            uhi[i] = g ? nmax(uhi[i], hi[3 * g + i]) : hi[3 * g + i];
        }
    }
    int64_t nn = 0;
    for (int64_t s = 0; s < ns; s++) {
        int all = 1;
        for (int i = 0; i < 3; i++)
            all &= (s_lo[3 * s + i] - uhi[i] < cap) & (ulo[i] - s_hi[3 * s + i] < cap);
        if (all) near[nn++] = s;
    }
    double best = cap;
    for (int64_t g = 0; g < ng; g++)
        for (int64_t k = 0; k < nn; k++) {
            const int64_t s = near[k];
            double gap = 0.0;
            for (int i = 0; i < 3; i++) {
                double a = s_lo[3 * s + i] - hi[3 * g + i], b = lo[3 * g + i] - s_hi[3 * s + i];
                double e = nmax(a, b);  /* np.maximum, then the max over the axes */
                gap = i ? nmax(gap, e) : e;
            }
            if (gap < cap) {
                double got = dist(m, d, (int)geoms[g], (int)station[s], cap, fromto);
                if (got < best) best = got;  /* Python's min(best, got) */
            }
        }
    return best;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledStationBound:
    """The quick bound, and the clearance after it, for one MuJoCo data's geom poses.

    Args:
        lib: The kernel's library.
        data: The MuJoCo data (its ``geom_xpos`` and ``geom_xmat`` are read in place).
        geoms: The moving geoms (G,).
        reach: Their reach (G,) [m].
        s_lo: The station boxes' lower corners (S, 3) [m].
        s_hi: Their upper corners (S, 3) [m].
        cap: The clearance cap [m].
        model: The MuJoCo model (for :meth:`clearance`).
        station: The station geoms of the boxes (S,).
        geomdist: The address of MuJoCo's ``mj_geomDistance`` (None: no clearance).
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        data: Any,
        geoms: np.ndarray,
        reach: np.ndarray,
        s_lo: np.ndarray,
        s_hi: np.ndarray,
        cap: float,
        model: Any,
        station: np.ndarray,
        geomdist: int | None,
    ) -> None:
        self.data = data
        self._keep = [
            np.ascontiguousarray(geoms, dtype=np.int64),
            np.ascontiguousarray(reach, dtype=np.float64).reshape(-1),
            np.ascontiguousarray(s_lo, dtype=np.float64),
            np.ascontiguousarray(s_hi, dtype=np.float64),
        ]
        fn = lib.payload_station_near
        ptr, i64 = ctypes.c_void_p, ctypes.c_int64
        fn.restype = ctypes.c_int
        fn.argtypes = [ptr, ptr, ptr, i64, ptr, ptr, i64, ctypes.c_double]
        g, r, lo, hi = self._keep
        for name in ("geom_xpos", "geom_xmat"):
            a = getattr(data, name)
            if not (a.dtype == np.float64 and a.flags.c_contiguous):
                raise ValueError(f"{name} is not a C-contiguous float64 array")
        xpos = data.geom_xpos
        self._near = functools.partial(
            fn, xpos.ctypes.data, g.ctypes.data, r.ctypes.data, len(g), lo.ctypes.data,
            hi.ctypes.data, len(lo), cap,
        )  # fmt: skip
        self._clearance = None
        if geomdist is None:
            return
        aabb = model.geom_aabb
        if not (aabb.dtype == np.float64 and aabb.flags.c_contiguous):
            raise ValueError("geom_aabb is not a C-contiguous float64 array")
        ids = np.ascontiguousarray(station, dtype=np.int64)
        scratch = [np.zeros((len(g), 3)), np.zeros((len(g), 3)), np.zeros(len(lo), np.int64)]
        fromto = np.zeros(6)
        self.boxes = (scratch[0], scratch[1])
        """The moving geoms' world boxes (lower and upper corners, (G, 3) each) as the last
        :meth:`clearance` computed them."""
        self._keep += [ids, *scratch, fromto, model]
        clear = lib.payload_station_clearance
        clear.restype = ctypes.c_double
        clear.argtypes = [ptr] * 7 + [i64, ptr, ptr, ptr, i64, ctypes.c_double] + [ptr] * 4
        self._clearance = functools.partial(
            clear, geomdist, model._address, data._address, xpos.ctypes.data,
            data.geom_xmat.ctypes.data, aabb.ctypes.data, g.ctypes.data, len(g),
            ids.ctypes.data, lo.ctypes.data, hi.ctypes.data, len(lo), cap,
            *(a.ctypes.data for a in scratch), fromto.ctypes.data,
        )  # fmt: skip

    def near(self) -> bool:
        """Whether some station box comes within the cap of the moving geoms' bound."""
        return bool(self._near())

    def clearance(self) -> float | None:
        """The least distance of the moving geoms from the station, at most the cap
        (:meth:`payload.sim.station.StationMonitor._clearance_numpy`'s), or None
        when the kernel was made without it."""
        return None if self._clearance is None else self._clearance()


CHECK_POSES = 400
"""Random poses of the moving geoms in the station bound's full self-check
(:func:`compiled_station_bound`)."""


@native.reported("station bound")
def compiled_station_bound(
    data: Any,
    geoms: np.ndarray,
    reach: np.ndarray,
    s_lo: np.ndarray,
    s_hi: np.ndarray,
    cap: float,
    reference: Callable[[], bool],
    *,
    model: Any,
    station: np.ndarray,
    clearance: Callable[[], float],
    boxes: Callable[[], tuple[np.ndarray, np.ndarray]],
) -> CompiledStationBound | None:
    """The compiled bound and clearance (the bound alone without MuJoCo's
    ``mj_geomDistance`` symbol) for ``data`` of ``model`` (``station``: the station geoms
    of the boxes), or None to run ``reference`` (the numpy test of the data's current
    positions) and ``clearance`` (the numpy clearance, ``boxes`` its moving boxes): no
    compiler, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that answers otherwise
    than ``reference`` or ``clearance``, or makes other moving boxes than ``boxes``, in a
    single bit, on random poses (written into the data's ``geom_xpos`` and ``geom_xmat``
    and restored): 400 of them, or their first 40 once a build of the same shape passed
    (in this process, or in an earlier one: :func:`payload.native.probes`)."""
    if len(geoms) == 0 or len(s_lo) == 0:  # nothing to bound: the numpy test answers
        return None
    lib = native.load_kernel("station", SOURCE, "the station bound kernel", log)
    if lib is None:
        return None
    geomdist = native.mujoco_function("mj_geomDistance")
    measures = geomdist is not None  # else the bound alone is made (and checked)
    try:
        kernel = CompiledStationBound(
            lib, data, geoms, reach, s_lo, s_hi, cap, model, station, geomdist
        )
    except ValueError as exc:
        log.warning("station bound: numpy (%s)", exc)
        return None
    span_lo, span_hi = s_lo.min(axis=0) - 1.0, s_hi.max(axis=0) + 1.0
    shape = (len(geoms), len(station), measures)

    def check(n: int) -> bool:
        saved = data.geom_xpos.copy(), data.geom_xmat.copy()
        rng = np.random.default_rng(0)
        measured = 0
        try:
            for i in range(n):
                # the moving geoms clustered somewhere around the station (some near a box),
                # turned every way
                centre = rng.uniform(span_lo, span_hi)
                data.geom_xpos[geoms] = centre + rng.normal(scale=0.2, size=(len(geoms), 3))
                data.geom_xmat[geoms] = random_rotations(rng, len(geoms))
                if i % 97 == 5:
                    data.geom_xpos[geoms[i % len(geoms)], i % 3] = np.nan
                near = kernel.near()
                if near != reference():
                    log.warning("station bound: numpy (the compiled bound differs)")
                    return False
                if near and measures:
                    mine, theirs = kernel.clearance(), clearance()
                    lo, hi = boxes()
                    if (
                        mine is None
                        or np.float64(mine).tobytes() != np.float64(theirs).tobytes()
                        or lo.tobytes() != kernel.boxes[0].tobytes()
                        or hi.tobytes() != kernel.boxes[1].tobytes()
                    ):
                        log.warning("station bound: numpy (the compiled clearance differs)")
                        return False
                    measured += theirs < cap
        finally:
            data.geom_xpos[:], data.geom_xmat[:] = saved
        if measures and not measured:  # pragma: no cover - about half the probes come near
            log.warning("station bound: numpy (the clearance's self-check measured nothing)")
            return False
        return True

    if not native.self_checked(lib, shape, CHECK_POSES, check):
        return None
    return kernel


__all__ = ["SOURCE", "CompiledStationBound", "compiled_station_bound"]
