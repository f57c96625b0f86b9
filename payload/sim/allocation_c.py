"""The allocation's two per-step searches as compiled C, with numpy's bits.

:meth:`Propulsion._extent <payload.sim.propulsion.Propulsion._extent>` (the binding facet
of the reachable-wrench polytope) and :meth:`Propulsion._least_thrust
<payload.sim.propulsion.Propulsion._least_thrust>` (the least-total-thrust basic
solution) run every control step of a trial. In numpy each is about fifteen calls on
arrays of a few thousand numbers, so their cost is numpy's per-call overhead more than
arithmetic. Here each is one C call on the same tables (:class:`CompiledSearches`; the
controller's step around them and the thrusts are :mod:`payload.sim.vehicle_c`):

* the matrix-vector products are numpy's own: the CBLAS ``dgemv`` of the OpenBLAS numpy
  loaded (:func:`payload.native.numpy_dgemv`), called as numpy's ``matmul`` calls it, so
  the products have numpy's bits on every machine (OpenBLAS picks its kernel by the
  processor for both);
* a row sum adds its six numbers left to right, as numpy's ``sum(axis=1)`` does on rows
  of six (its pairwise summation starts only at eight);
* ``argmin`` keeps the first least value (numpy's test ``!(v >= least)``, NaN included);
* ``clip`` is numpy's ``min(max(x, lo), hi)`` with ``max(-0.0, 0.0) = 0.0``;
* divisions, subtractions, additions and comparisons are single IEEE operations, and
  the flags forbid contraction into fused multiply-adds (:data:`payload.native.CFLAGS`).

Without a C compiler, or without numpy's bundled OpenBLAS, or if a self-check on probe
inputs finds a single differing bit, :func:`compiled_searches` returns None and the numpy
code runs (``PAYLOAD_NATIVE=0`` asks for that too).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import threading
from typing import Any

import numpy as np

from payload import native

log = logging.getLogger(__name__)

SOURCE = r"""
#include <stdlib.h>

/* NZ, the number of nozzles, is defined by the caller (load_with_searches) */
enum { NB = 6, NPAT = 1 << (NZ - NB) };

typedef struct {
    dgemv_fn gemv;
    int64_t nf; const double *normals, *offsets;        /* facets (nf, 6), (nf) */
    int64_t nk; const double *inverses, *basis_ub;       /* (6 nk, 6), (nk, 6) */
    const int64_t *basis, *rest;                         /* (nk, 6) each */
    const double *fixed;                                 /* (nk, 64, 6) */
    int64_t nm; const int64_t *ck, *cj;                  /* candidates (nm) */
    const double *c_off, *c_ceiling, *c_fixed;           /* (nm, 6), (nm, 6), (nm) */
    const double *thrust_max;                            /* (12) */
    double tol;
    const double *wrench;                                /* (6), the call's input */
    double *thrust, *ratio, *along, *t0;                 /* outputs and work */
} searches;

void *payload_searches_new(
    void *gemv, int64_t nf, const double *normals, const double *offsets,
    int64_t nk, const double *inverses, const double *basis_ub, const int64_t *basis,
    const int64_t *rest, const double *fixed, int64_t nm, const int64_t *ck,
    const int64_t *cj, const double *c_off, const double *c_ceiling, const double *c_fixed,
    const double *thrust_max, double tol, const double *wrench, double *thrust,
    double *ratio, double *along, double *t0)
{
    searches *s = malloc(sizeof *s);
    if (!s) return NULL;
    s->gemv = (dgemv_fn)gemv;
    s->nf = nf; s->normals = normals; s->offsets = offsets;
    s->nk = nk; s->inverses = inverses; s->basis_ub = basis_ub;
    s->basis = basis; s->rest = rest; s->fixed = fixed;
    s->nm = nm; s->ck = ck; s->cj = cj;
    s->c_off = c_off; s->c_ceiling = c_ceiling; s->c_fixed = c_fixed;
    s->thrust_max = thrust_max; s->tol = tol; s->wrench = wrench;
    s->thrust = thrust; s->ratio = ratio; s->along = along; s->t0 = t0;
    return s;
}

void payload_searches_free(void *p) { free(p); }

/* numpy's argmin step: the first least value; a NaN is the least and stops the search */
#define ARGMIN_STEP(v, i, best, least, stop)                                       \
    do {                                                                           \
        if ((best) < 0) { (best) = (i); (least) = (v); (stop) = ((v) != (v)); }    \
        else if (!(stop) && !((v) >= (least))) {                                   \
            (best) = (i); (least) = (v); (stop) = ((v) != (v));                    \
        }                                                                          \
    } while (0)

/* numpy's clip(x, 0, hi): min(max(x, 0), hi), max(-0.0, 0.0) = 0.0 */
static void clip_thrust(double *t, const double *hi)
{
    for (int i = 0; i < NZ; i++) {
        double m = (t[i] > 0.0 || t[i] != t[i]) ? t[i] : 0.0;
        t[i] = (m < hi[i] || m != m) ? m : hi[i];
    }
}

/* Propulsion._extent: the binding facet (-1: none) and the largest scale in *ratio */
int64_t payload_extent(void *p)
{
    searches *s = p;
    s->gemv(ROW_MAJOR, NO_TRANS, s->nf, NB, 1.0, s->normals, NB, s->wrench, 1, 0.0,
            s->along, 1);
    int any = 0;
    for (int64_t k = 0; k < s->nf; k++)
        if (s->along[k] > 1e-15) { any = 1; break; }
    if (!any) { *s->ratio = INFINITY; return -1; }
    int64_t best = -1; double least = 0.0; int stop = 0;
    for (int64_t k = 0; k < s->nf; k++) {
        double v = s->along[k] > 1e-15 ? s->offsets[k] / s->along[k] : INFINITY;
        ARGMIN_STEP(v, k, best, least, stop);
    }
    *s->ratio = least;
    return best;
}

static double row_sum(const double *r)
{
    double a = r[0];
    for (int i = 1; i < NB; i++) a += r[i];
    return a;
}

/* Propulsion._least_thrust: 1 with the thrusts in s->thrust, 0 if none is feasible */
int payload_least_thrust(void *p)
{
    searches *s = p;
    const double tol = s->tol, neg = -tol;
    double *t0 = s->t0, *out = s->thrust;
    s->gemv(ROW_MAJOR, NO_TRANS, NB * s->nk, NB, 1.0, s->inverses, NB, s->wrench, 1, 0.0,
            t0, 1);
    int64_t best = -1; double least = 0.0; int stop = 0;
    for (int64_t k = 0; k < s->nk; k++) {
        const double *r = t0 + NB * k;
        int ok = 1;
        for (int i = 0; i < NB; i++) ok &= (r[i] >= neg);
        if (!ok) continue;
        double v = row_sum(r);
        ARGMIN_STEP(v, k, best, least, stop);
    }
    if (best >= 0) {
        const double *r = t0 + NB * best, *ub = s->basis_ub + NB * best;
        int ok = 1;
        for (int i = 0; i < NB; i++) ok &= (r[i] <= ub[i] + tol);
        if (ok) {
            for (int i = 0; i < NZ; i++) out[i] = 0.0;
            for (int i = 0; i < NB; i++) out[s->basis[NB * best + i]] = r[i];
            clip_thrust(out, s->thrust_max);
            return 1;
        }
    }
    best = -1; least = 0.0; stop = 0;
    for (int64_t m = 0; m < s->nm; m++) {
        const double *r = t0 + NB * s->ck[m], *off = s->c_off + NB * m;
        const double *ceil = s->c_ceiling + NB * m;
        double tb[NB];
        int ok = 1;
        for (int i = 0; i < NB; i++) {
            tb[i] = r[i] - off[i];
            ok &= (tb[i] >= neg) & (tb[i] <= ceil[i]);
        }
        if (!ok) continue;
        double v = row_sum(tb) + s->c_fixed[m];
        ARGMIN_STEP(v, m, best, least, stop);
    }
    if (best < 0) return 0;
    int64_t k = s->ck[best], j = s->cj[best];
    const double *r = t0 + NB * k, *off = s->c_off + NB * best;
    for (int i = 0; i < NZ; i++) out[i] = 0.0;
    for (int i = 0; i < NB; i++) out[s->rest[NB * k + i]] = s->fixed[(k * NPAT + j) * NB + i];
    for (int i = 0; i < NB; i++) out[s->basis[NB * k + i]] = r[i] - off[i];
    clip_thrust(out, s->thrust_max);
    return 1;
}

"""
"""The kernels' C (:func:`payload.native.build_library` compiles it)."""

_PROBES = 400
"""Probe wrenches of the self-check (:func:`compiled_searches`)."""


class CompiledSearches:
    """The two searches of one :class:`~payload.sim.propulsion.Propulsion` in C.

    Args:
        prop: The propulsion model; its tables are built (if not yet) and kept alive
            here, since the library reads them in place.
        lib: The loaded library (:data:`SOURCE`).
        gemv: The address of numpy's CBLAS ``dgemv``.
    """

    def __init__(self, prop: Any, lib: ctypes.CDLL, gemv: int) -> None:
        normals, offsets = prop.facets
        idx, _, _, fixed = prop._bases
        ck, cj, c_off, c_fixed = prop._candidates

        def f64(a: Any) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=np.float64)

        def i64(a: Any) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=np.int64)

        self._keep = [
            f64(normals),
            f64(offsets),
            f64(prop._stacked_inverses),
            f64(prop._basis_bounds),
            i64(idx),
            i64(prop._basis_rest),
            f64(fixed),
            i64(ck),
            i64(cj),
            f64(c_off),
            f64(prop._candidate_ceiling),
            f64(c_fixed),
            f64(prop.thrust_max),
        ]
        self.wrench = np.zeros(6)
        self.thrust = np.zeros(len(prop.thrust_max))
        self._ratio = np.zeros(1)
        self._along = np.zeros(len(self._keep[0]))
        self._t0 = np.zeros(6 * len(self._keep[4]))
        ptr = ctypes.c_void_p
        new = lib.payload_searches_new
        new.restype = ptr
        new.argtypes = [ptr, ctypes.c_int64, ptr, ptr, ctypes.c_int64, ptr, ptr, ptr, ptr, ptr]
        new.argtypes += [ctypes.c_int64, ptr, ptr, ptr, ptr, ptr, ptr, ctypes.c_double]
        new.argtypes += [ptr] * 5
        k = self._keep
        handle = new(
            gemv,
            len(k[0]), k[0].ctypes.data, k[1].ctypes.data,
            len(k[4]), k[2].ctypes.data, k[3].ctypes.data, k[4].ctypes.data,
            k[5].ctypes.data, k[6].ctypes.data,
            len(k[7]), k[7].ctypes.data, k[8].ctypes.data, k[9].ctypes.data,
            k[10].ctypes.data, k[11].ctypes.data, k[12].ctypes.data, prop._least_tol,
            self.wrench.ctypes.data, self.thrust.ctypes.data, self._ratio.ctypes.data,
            self._along.ctypes.data, self._t0.ctypes.data,
        )  # fmt: skip
        if not handle:
            raise MemoryError("the allocation kernels' state")
        self._lib = lib
        self._handle = ptr(handle)
        self._free = lib.payload_searches_free
        self._free.argtypes = [ptr]
        extent = lib.payload_extent
        extent.restype = ctypes.c_int64
        extent.argtypes = [ptr]
        least = lib.payload_least_thrust
        least.restype = ctypes.c_int
        least.argtypes = [ptr]
        self._extent = functools.partial(extent, self._handle)
        self._least = functools.partial(least, self._handle)
        # one set of buffers: a thread's call (ctypes releases the GIL) must not meet
        # another's (a Propulsion is shared by a process's trials: shared_propulsion)
        self._lock = threading.Lock()

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None:
            self._free(handle)

    def extent(self, wrench: np.ndarray) -> tuple[float, int]:
        """:meth:`Propulsion._extent <payload.sim.propulsion.Propulsion._extent>`."""
        with self._lock:
            self.wrench[:] = wrench
            k = self._extent()
            return float(self._ratio[0]), k

    def least_thrust(self, wrench: np.ndarray) -> np.ndarray | None:
        """:meth:`Propulsion._least_thrust <payload.sim.propulsion.Propulsion._least_thrust>`."""
        with self._lock:
            self.wrench[:] = wrench
            return self.thrust.copy() if self._least() else None


def _same(a: Any, b: Any) -> bool:
    """The same result in every bit (floats by their bytes: the sign of zero counts)."""
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, tuple):
        return a[1] == b[1] and np.float64(a[0]).tobytes() == np.float64(b[0]).tobytes()
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def probe_wrenches(prop: Any, n: int = _PROBES, seed: int = 0) -> np.ndarray:
    """Wrenches that take every path of both searches: inside the polytope, on and near
    its boundary (where the unbounded optimum breaks a bound and the dual-feasible
    candidates decide), outside it, and along single axes: (n, 6)."""
    rng = np.random.default_rng(seed)
    normals, offsets = prop.facets
    out = []
    for i in range(n):
        d = rng.normal(size=6)
        if i % 5 == 4:
            d = np.zeros(6)
            d[i % 6] = rng.choice((-1.0, 1.0))
        along = normals @ d
        pos = along > 0
        lam = float(np.min(offsets[pos] / along[pos]))
        out.append(d * lam * (rng.uniform(0.2, 1.3) if i % 3 else rng.uniform(0.97, 1.0)))
    return np.array(out)


@native.reported("allocation searches")
def compiled_searches(prop: Any) -> CompiledSearches | None:
    """The compiled searches for ``prop``, or None to run numpy's (no compiler, no numpy
    OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that differs from the
    numpy code in a single bit on :func:`probe_wrenches`: :data:`_PROBES`, or their first
    tenth once a build for as many nozzles passed, here or in an earlier process:
    :func:`payload.native.probes`)."""
    nozzles = len(prop.thrust_max)
    loaded = load_with_searches("allocation kernels", nozzles)
    if loaded is None:
        return None
    kernels = CompiledSearches(prop, *loaded)

    def check(n: int) -> bool:
        for w in probe_wrenches(prop, n):
            if not (
                _same(kernels.extent(w), prop._extent_numpy(w))
                and _same(kernels.least_thrust(w), prop._least_thrust_numpy(w))
            ):
                log.warning("allocation kernels: numpy (the compiled searches differ on %s)", w)
                return False
        return True

    if not native.self_checked(loaded[0], nozzles, _PROBES, check):
        return None
    return kernels


def load_with_searches(
    what: str, nozzles: int, name: str = "allocation", extra: str = ""
) -> tuple[ctypes.CDLL, int] | None:
    """The library of :data:`SOURCE` (and ``extra`` C that uses its searches) for a
    propulsion of ``nozzles`` nozzles, and numpy's dgemv; or None (logged) to run the
    numpy code."""
    gemv = native.numpy_dgemv()
    if gemv is None:
        log.info("%s: numpy (no numpy OpenBLAS dgemv)", what)
        return None
    lib = native.load_kernel(
        name, SOURCE + extra, f"the {what}", log, prelude=f"#define NZ {int(nozzles)}\n"
    )
    return None if lib is None else (lib, gemv)


__all__ = [
    "SOURCE",
    "CompiledSearches",
    "compiled_searches",
    "load_with_searches",
    "probe_wrenches",
]
