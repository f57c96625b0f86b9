"""The station clearance's quick bound as compiled C.

:meth:`payload.sim.station.StationMonitor.read` runs every control step of every trial,
and on most steps (mid-module) it ends at its first test: a box around every moving
geom's box (its frame's origin plus a fixed reach) whose union comes within
:data:`~payload.sim.station.CLEARANCE_CAP` of no station box. That test is maxima,
minima, additions, subtractions and comparisons, exact in any order, so one C call gives
the numpy test's answer (NaN included: a NaN position propagates through the maxima and
fails every comparison, as in numpy); it is checked against the numpy test on random
poses when it is built. When the bound does not settle the reading, the numpy code reads
on as before. Without a compiler or with ``PAYLOAD_NATIVE=0`` the numpy test runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native

log = logging.getLogger(__name__)

SOURCE = r"""
#include <stdint.h>

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
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledStationBound:
    """The quick bound for one MuJoCo data's geom positions.

    Args:
        lib: The kernel's library.
        data: The MuJoCo data (its ``geom_xpos`` is read in place).
        geoms: The moving geoms (G,).
        reach: Their reach (G,) [m].
        s_lo: The station boxes' lower corners (S, 3) [m].
        s_hi: Their upper corners (S, 3) [m].
        cap: The clearance cap [m].
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
        xpos = data.geom_xpos
        if not (xpos.dtype == np.float64 and xpos.flags.c_contiguous):
            raise ValueError("geom_xpos is not a C-contiguous float64 array")
        self._near = functools.partial(
            fn, xpos.ctypes.data, g.ctypes.data, r.ctypes.data, len(g), lo.ctypes.data,
            hi.ctypes.data, len(lo), cap,
        )  # fmt: skip

    def near(self) -> bool:
        """Whether some station box comes within the cap of the moving geoms' bound."""
        return bool(self._near())


@native.reported("station bound")
def compiled_station_bound(
    data: Any,
    geoms: np.ndarray,
    reach: np.ndarray,
    s_lo: np.ndarray,
    s_hi: np.ndarray,
    cap: float,
    reference: Callable[[], bool],
) -> CompiledStationBound | None:
    """The compiled bound for ``data``, or None to run ``reference`` (the numpy test of
    the data's current positions): no compiler, ``PAYLOAD_NATIVE=0``, a failed build, or a
    self-check that answers otherwise than ``reference`` on random positions (written into
    the data's ``geom_xpos`` and restored)."""
    if len(geoms) == 0 or len(s_lo) == 0:  # nothing to bound: the numpy test answers
        return None
    lib = native.load_kernel("station", SOURCE, "the station bound kernel", log)
    if lib is None:
        return None
    try:
        kernel = CompiledStationBound(lib, data, geoms, reach, s_lo, s_hi, cap)
    except ValueError as exc:
        log.warning("station bound: numpy (%s)", exc)
        return None
    saved = data.geom_xpos.copy()
    rng = np.random.default_rng(0)
    span_lo, span_hi = s_lo.min(axis=0) - 1.0, s_hi.max(axis=0) + 1.0
    try:
        for i in range(400):
            # the moving geoms clustered somewhere around the station (some near a box)
            centre = rng.uniform(span_lo, span_hi)
            data.geom_xpos[geoms] = centre + rng.normal(scale=0.2, size=(len(geoms), 3))
            if i % 97 == 5:
                data.geom_xpos[geoms[i % len(geoms)], i % 3] = np.nan
            if kernel.near() != reference():
                log.warning("station bound: numpy (the compiled bound differs)")
                return None
    finally:
        data.geom_xpos[:] = saved
    return kernel


__all__ = ["SOURCE", "CompiledStationBound", "compiled_station_bound"]
