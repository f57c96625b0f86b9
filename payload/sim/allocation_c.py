"""The vehicle's control step as compiled C, with numpy's bits: the allocation's searches,
the nozzle controller's step and the thrusts into MuJoCo.

:meth:`Propulsion._extent <payload.sim.propulsion.Propulsion._extent>` (the binding facet
of the reachable-wrench polytope) and :meth:`Propulsion._least_thrust
<payload.sim.propulsion.Propulsion._least_thrust>` (the least-total-thrust basic
solution) run every control step of a trial. In numpy each is about fifteen calls on
arrays of a few thousand numbers, so their cost is numpy's per-call overhead more than
arithmetic. Here each is one C call on the same tables (:class:`CompiledSearches`), and
so are the controller's step around them (:class:`CompiledControl`, also with numpy's
``ddot`` for its norms and Python's ``min``/``max`` tie rules) and the thrusts'
``mj_applyFT`` calls (:class:`CompiledThrusts`, MuJoCo's own function):

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
inputs finds a single differing bit, :func:`compiled_searches`, :func:`compiled_control`
and :func:`compiled_thrusts` return None and the numpy code runs (``PAYLOAD_NATIVE=0``
asks for that too).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import threading
from typing import Any

import numpy as np

from payload import native
from payload.sim.errors import SimError

log = logging.getLogger(__name__)

SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

typedef void (*dgemv_fn)(int, int, int64_t, int64_t, double, const double *, int64_t,
                         const double *, int64_t, double, double *, int64_t);
/* NZ, the number of nozzles, is defined by the caller (_load) */
enum { ROW_MAJOR = 101, NO_TRANS = 111, NB = 6, NPAT = 1 << (NZ - NB) };

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

/* ---- the vehicle controller's step (payload.sim.vehicle.VehicleController.update) ---- */
typedef double (*ddot_fn)(int64_t, const double *, int64_t, const double *, int64_t);

typedef struct {
    searches *s;
    ddot_fn dot;
    const double *matrix;                   /* (6, 12) nozzle wrench per newton */
    int matrix_order; int64_t matrix_ld;    /* its layout, as numpy hands it to dgemv */
    const double *inertia, *com;            /* (3, 3), (3) */
    int inertia_order; int64_t inertia_ld;
    double mass, gain_lin, gain_ang, speed, omega;
    const double *budget;                   /* (3) reference_share * accel_max */
    const double *jerk, *amax;              /* (6) each: the profile's bounds */
    double *vel, *acc;                      /* (6) each: the profile's state, in place */
    const double *in;                       /* (12): command lin, ang; measured lin, ang */
    double *res;                            /* (14): w (6), delivered (6), lam, scale */
    int64_t *facet;
} control;

void *payload_control_new(void *searches_state, void *dot, const double *matrix,
    int matrix_order, int64_t matrix_ld, const double *inertia, int inertia_order,
    int64_t inertia_ld, const double *com, double mass, double gain_lin, double gain_ang,
    double speed, double omega, const double *budget, const double *jerk, const double *amax,
    const double *in, double *res, int64_t *facet)
{
    control *c = malloc(sizeof *c);
    if (!c) return NULL;
    c->s = searches_state; c->dot = (ddot_fn)dot;
    c->matrix = matrix; c->matrix_order = matrix_order; c->matrix_ld = matrix_ld;
    c->inertia = inertia; c->inertia_order = inertia_order; c->inertia_ld = inertia_ld;
    c->com = com; c->mass = mass;
    c->gain_lin = gain_lin; c->gain_ang = gain_ang; c->speed = speed; c->omega = omega;
    c->budget = budget; c->jerk = jerk; c->amax = amax; c->vel = NULL; c->acc = NULL;
    c->in = in; c->res = res; c->facet = facet;
    return c;
}

void payload_control_free(void *p) { free(p); }

/* the profile's state arrays (JerkLimitedProfile.velocity, .acceleration), updated in place */
void payload_control_state(void *p, double *vel, double *acc)
{
    control *c = p;
    c->vel = vel; c->acc = acc;
}

/* vecmath.cross / vehicle._cross: the same products and differences */
static void cross3(const double *a, const double *b, double *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Python's min(a, b) and max(a, b) of floats: the first unless the second is less/greater */
static double py_min(double a, double b) { return (b < a) ? b : a; }
static double py_max(double a, double b) { return (b > a) ? b : a; }

/* JerkLimitedProfile.step on Python floats, axis by axis */
static void profile_step(control *c, const double *target, double dt)
{
    const double lin = 0.5 * dt;
    for (int i = 0; i < NB; i++) {
        double tg = target[i], v = c->vel[i], a0 = c->acc[i], j = c->jerk[i], a_max = c->amax[i];
        double e = tg - v;
        double s = e >= 0.0 ? 1.0 : -1.0;
        double a = s * a0;
        double dist = fabs(e);
        double quad = 1.0 / (2.0 * j);
        double cst = a * lin - dist;
        double x;
        if (cst <= 0.0)
            x = (-lin + sqrt(lin * lin - 4.0 * quad * py_min(cst, 0.0))) / (2.0 * quad);
        else
            x = (lin - sqrt(lin * lin + 4.0 * quad * py_max(cst, 0.0))) / (2.0 * quad);
        x = py_min(py_max(x, a - j * dt), a + j * dt);
        x = py_min(py_max(x, -a_max), a_max);
        double v_new = v + s * 0.5 * (a + x) * dt;
        double a_new = s * x;
        int arrived = fabs(tg - v_new) <= 1e-12 + 1e-9 * fabs(tg) && fabs(a_new) <= j * dt;
        c->vel[i] = arrived ? tg : v_new;
        c->acc[i] = arrived ? 0.0 : a_new;
    }
}

/* VehicleController.update with nozzles, up to the allocation:
   0 allocated (thrusts in the searches' buffer, delivered wrench in res[6:12], scale res[13]);
   1 zero wrench; 2 outside the polytope (lam res[12], facet); 3 no basic solution (lam,
   facet, scale); 4 a non-finite wrench. In 2 to 4 the requested wrench is in res[0:6]. */
int payload_control_step(void *p, double dt)
{
    control *c = p;
    searches *s = c->s;
    const double *in = c->in;
    double *res = c->res;
    double lin[3] = {in[0], in[1], in[2]}, ang[3] = {in[3], in[4], in[5]};
    const double *v = in + 6, *w = in + 9;
    /* clamp */
    double sp = sqrt(c->dot(3, lin, 1, lin, 1)), om = sqrt(c->dot(3, ang, 1, ang, 1));
    if (sp > c->speed) {
        double f = c->speed / sp;
        for (int i = 0; i < 3; i++) lin[i] = lin[i] * f;
    }
    if (om > c->omega) {
        double f = c->omega / om;
        for (int i = 0; i < 3; i++) ang[i] = ang[i] * f;
    }
    double cen[3];
    cross3(ang, lin, cen);
    int any = 0; double least = 0.0;
    for (int i = 0; i < 3; i++) {
        cen[i] = fabs(cen[i]);
        if (cen[i] > c->budget[i]) {
            double r = c->budget[i] / cen[i];
            if (!any || r < least) least = r;
            any = 1;
        }
    }
    if (any) for (int i = 0; i < 3; i++) ang[i] = ang[i] * least;
    double target[NB] = {lin[0], lin[1], lin[2], ang[0], ang[1], ang[2]};
    profile_step(c, target, dt);
    const double *ref = c->vel, *acc = c->acc;
    /* the wrench */
    double cwv[3], force[3], alpha[3], ia[3], iw[3], ciw[3], ccf[3], torque[3];
    cross3(w, v, cwv);
    for (int i = 0; i < 3; i++)
        force[i] = c->mass * ((acc[i] + c->gain_lin * (ref[i] - v[i])) + cwv[i]);
    for (int i = 0; i < 3; i++) alpha[i] = acc[3 + i] + c->gain_ang * (ref[3 + i] - w[i]);
    s->gemv(c->inertia_order, NO_TRANS, 3, 3, 1.0, c->inertia, c->inertia_ld, alpha, 1, 0.0,
            ia, 1);
    s->gemv(c->inertia_order, NO_TRANS, 3, 3, 1.0, c->inertia, c->inertia_ld, w, 1, 0.0, iw, 1);
    cross3(w, iw, ciw);
    cross3(c->com, force, ccf);
    for (int i = 0; i < 3; i++) torque[i] = (ia[i] + ciw[i]) + ccf[i];
    /* Propulsion.allocate */
    int finite = 1, nonzero = 0;
    for (int i = 0; i < 3; i++) { res[i] = force[i]; res[3 + i] = torque[i]; }
    for (int i = 0; i < NB; i++) { finite &= isfinite(res[i]) != 0; nonzero |= res[i] != 0.0; }
    if (!finite) return 4;
    if (!nonzero) return 1;
    double *ws = (double *)s->wrench;
    for (int i = 0; i < NB; i++) ws[i] = res[i];
    int64_t k = payload_extent(s);
    double lam = *s->ratio;
    res[12] = lam; *c->facet = k;
    if (lam < 1.0) return 2;
    double scale = py_min(1.0, lam * (1.0 - 1e-9));
    res[13] = scale;
    for (int i = 0; i < NB; i++) ws[i] = scale * res[i];
    if (!payload_least_thrust(s)) return 3;
    s->gemv(c->matrix_order, NO_TRANS, NB, NZ, 1.0, c->matrix, c->matrix_ld, s->thrust, 1, 0.0,
            res + 6, 1);
    return 0;
}

/* ---- thrusts into MuJoCo (payload.sim.driver.SimDriver.apply_thrusts) ---- */
typedef void (*applyft_fn)(const void *, void *, const double *, const double *, const double *,
                           int, double *);

void payload_apply_thrusts(void *gemv, void *apply, const void *m, void *d, const double *rot,
    const double *origin, const double *dirs, const double *pos, const double *thrust, int body,
    double *qfrc)
{
    dgemv_fn mv = (dgemv_fn)gemv;
    applyft_fn ft = (applyft_fn)apply;
    const double zero[3] = {0.0, 0.0, 0.0};
    for (int k = 0; k < NZ; k++) {
        if (!(thrust[k] > 0.0)) continue;
        double fd[3], f[3], rp[3], pt[3];
        for (int i = 0; i < 3; i++) fd[i] = dirs[3 * k + i] * thrust[k];
        mv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, rot, 3, fd, 1, 0.0, f, 1);
        mv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, rot, 3, pos + 3 * k, 1, 0.0, rp, 1);
        for (int i = 0; i < 3; i++) pt[i] = origin[i] + rp[i];
        ft(m, d, f, zero, pt, body, qfrc);
    }
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
    numpy code in a single bit on :func:`probe_wrenches`)."""
    loaded = _load("allocation kernels", len(prop.thrust_max))
    if loaded is None:
        return None
    kernels = CompiledSearches(prop, *loaded)
    for w in probe_wrenches(prop):
        if not (
            _same(kernels.extent(w), prop._extent_numpy(w))
            and _same(kernels.least_thrust(w), prop._least_thrust_numpy(w))
        ):
            log.warning("allocation kernels: numpy (the compiled searches differ on %s)", w)
            return None
    return kernels


def _load(what: str, nozzles: int) -> tuple[ctypes.CDLL, int] | None:
    """The kernels' library for a propulsion of ``nozzles`` nozzles and numpy's dgemv, or
    None (logged) to run the numpy code."""
    gemv = native.numpy_dgemv()
    if gemv is None:
        log.info("%s: numpy (no numpy OpenBLAS dgemv)", what)
        return None
    lib = native.load_kernel(
        "allocation", SOURCE, "the allocation kernels", log, prelude=f"#define NZ {int(nozzles)}\n"
    )
    return None if lib is None else (lib, gemv)


class CompiledControl:
    """The step of :meth:`VehicleController.update
    <payload.sim.vehicle.VehicleController.update>` with nozzles in C: the twist clamp,
    the jerk-limited profile (its state updated in place), the wrench, and the
    allocation's searches (:class:`CompiledSearches`); the controller makes the result's
    objects, and finishes the rare allocations outside those searches (a saturated wrench
    on a facet, the linear programme) with the numpy code (``Propulsion._finish``).

    Args:
        controller: The controller (nozzle propulsion).
        searches: Its propulsion's compiled searches.
        lib: The kernels' library.
        ddot: The address of numpy's CBLAS ``ddot``.
    """

    def __init__(
        self, controller: Any, searches: CompiledSearches, lib: ctypes.CDLL, ddot: int
    ) -> None:
        self.controller = controller
        self.searches = searches
        mass, com, inertia = controller.plant
        matrix, inertia = controller.nozzles.matrix, np.asarray(inertia)
        layouts = [native.gemv_layout(matrix), native.gemv_layout(inertia)]
        if None in layouts:
            raise SimError("the controller kernel needs contiguous float64 matrices")
        (m_order, m_ld), (i_order, i_ld) = layouts
        self._keep = [
            matrix,
            inertia,
            np.ascontiguousarray(com, dtype=np.float64),
            np.ascontiguousarray(controller.reference_share * controller.accel_max),
            np.ascontiguousarray(controller.profile.jerk, dtype=np.float64),
            np.ascontiguousarray(controller.profile.accel, dtype=np.float64),
        ]
        self._in = np.zeros(12)
        self._res = np.zeros(14)
        self._facet = np.zeros(1, dtype=np.int64)
        ptr, dbl = ctypes.c_void_p, ctypes.c_double
        new = lib.payload_control_new
        new.restype = ptr
        i64, cint = ctypes.c_int64, ctypes.c_int
        new.argtypes = [ptr, ptr, ptr, cint, i64, ptr, cint, i64, ptr, dbl, dbl, dbl, dbl, dbl]
        new.argtypes += [ptr, ptr, ptr, ptr, ptr, ptr]
        k = self._keep
        handle = new(
            searches._handle, ddot, k[0].ctypes.data, m_order, m_ld, k[1].ctypes.data, i_order,
            i_ld, k[2].ctypes.data,
            float(mass), float(controller.gain_linear), float(controller.gain_angular),
            float(controller.mode.speed), float(controller.mode.omega), k[3].ctypes.data,
            k[4].ctypes.data, k[5].ctypes.data, self._in.ctypes.data, self._res.ctypes.data,
            self._facet.ctypes.data,
        )  # fmt: skip
        if not handle:
            raise MemoryError("the controller kernel's state")
        self._handle = ptr(handle)
        self._free = lib.payload_control_free
        self._free.argtypes = [ptr]
        self._state = lib.payload_control_state
        self._state.argtypes = [ptr, ptr, ptr]
        step = lib.payload_control_step
        step.restype = ctypes.c_int
        step.argtypes = [ptr, dbl]
        self._step = functools.partial(step, self._handle)
        self._bound: tuple[Any, Any] = (None, None)

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None:
            self._free(handle)

    def _bind(self, profile: Any) -> None:
        """Point the kernel at the profile's state arrays (new ones after a reset)."""
        for name in ("velocity", "acceleration"):
            arr = getattr(profile, name)
            own = arr.base is None and arr.flags.writeable and arr.flags.c_contiguous
            if not (own and arr.dtype == np.float64 and arr.shape == (6,)):
                setattr(profile, name, np.array(arr, dtype=np.float64).reshape(6))
        self._bound = (profile.velocity, profile.acceleration)
        self._state(self._handle, profile.velocity.ctypes.data, profile.acceleration.ctypes.data)

    def step(self, command: Any, linear: np.ndarray, angular: np.ndarray, dt: float) -> tuple:
        """One control step (the arguments of ``VehicleController.update``), the profile's
        state updated in place: ``(0, thrust, force, torque, scale)`` allocated; ``(1,)``
        a zero wrench; ``(2, w, lam, facet)`` outside the polytope and ``(3, w, lam,
        facet)`` without a basic solution (the numpy code finishes those); ``(4, w)`` a
        non-finite wrench ``w`` (6,)."""
        profile = self.controller.profile
        if profile.velocity is not self._bound[0] or profile.acceleration is not self._bound[1]:
            self._bind(profile)
        inp, res = self._in, self._res
        with self.searches._lock:
            inp[0:3] = command.linear
            inp[3:6] = command.angular
            inp[6:9] = linear
            inp[9:12] = angular
            code = self._step(dt)
            if code == 0:
                return (
                    0,
                    self.searches.thrust.copy(),
                    res[6:9].copy(),
                    res[9:12].copy(),
                    float(res[13]),
                )
            if code == 1:
                return (1,)
            return code, res[:6].copy(), float(res[12]), int(self._facet[0])


def _same_update(a: tuple, b: tuple) -> bool:
    """Two (wrench, allocation, velocity, acceleration) results alike in every bit."""
    (wa, aa, va, ca), (wb, ab, vb, cb) = a, b
    arrays = [
        (wa.force, wb.force),
        (wa.torque, wb.torque),
        (aa.thrust, ab.thrust),
        (aa.force, ab.force),
        (aa.torque, ab.torque),
        (va, vb),
        (ca, cb),
    ]
    return aa.scale == ab.scale and all(x.tobytes() == y.tobytes() for x, y in arrays)


def check_control(controller: Any, kernel: CompiledControl, steps: int = 160) -> bool:
    """Run ``steps`` control steps of piecewise-constant random commands (moving, turning,
    at rest, beyond the mode's speed) from the same states through the numpy code and
    the kernel; True if every wrench, allocation and profile state has the same bits.
    The controller's profile state and allocation are restored afterwards."""
    from payload.schema import VehicleTwist

    profile = controller.profile
    saved = (profile.velocity.copy(), profile.acceleration.copy(), controller.allocation)
    rng = np.random.default_rng(2)
    mode = controller.mode
    command = VehicleTwist.zero()
    try:
        for i in range(steps):
            if i % 40 == 0:
                scale = rng.choice((0.0, 0.5, 1.0, 2.0))
                command = VehicleTwist(
                    rng.normal(size=3) * mode.speed * scale,
                    rng.normal(size=3) * mode.omega * scale,
                    0.0,
                )
            lin = profile.velocity[:3] + rng.normal(scale=1e-3, size=3)
            ang = profile.velocity[3:] + rng.normal(scale=1e-3, size=3)
            start = (profile.velocity.copy(), profile.acceleration.copy())
            wrench = controller._update_numpy(command, lin, ang, 0.02)
            want = (wrench, controller.allocation, profile.velocity, profile.acceleration)
            after = (profile.velocity, profile.acceleration)
            profile.velocity, profile.acceleration = start[0].copy(), start[1].copy()
            wrench = controller._update_kernel(kernel, command, lin, ang, 0.02)
            got = (wrench, controller.allocation, profile.velocity, profile.acceleration)
            if not _same_update(want, got):
                return False
            profile.velocity, profile.acceleration = after
        return True
    finally:
        profile.velocity, profile.acceleration, controller.allocation = saved


@native.reported("vehicle controller")
def compiled_control(controller: Any) -> CompiledControl | None:
    """The compiled control step for a nozzle ``controller``, or None to run the numpy
    code (no kernels, no numpy ``ddot``, or a self-check (:func:`check_control`) that
    differs in a single bit)."""
    searches = controller.nozzles._kernels if controller.nozzles is not None else None
    loaded = None
    if searches is not None:
        loaded = _load("controller kernel", len(controller.nozzles.thrust_max))
    ddot = native.numpy_blas(native.NUMPY_DDOT)
    if loaded is None or ddot is None:
        return None
    try:
        kernel = CompiledControl(controller, searches, loaded[0], ddot)
    except SimError as exc:
        log.warning("controller kernel: numpy (%s)", exc)
        return None
    if not check_control(controller, kernel):
        log.warning("controller kernel: numpy (the compiled step differs)")
        return None
    return kernel


class CompiledThrusts:
    """:meth:`SimDriver.apply_thrusts <payload.sim.driver.SimDriver.apply_thrusts>` in C:
    per open nozzle the same two matrix-vector products (numpy's ``dgemv``) and the same
    ``mj_applyFT`` call of MuJoCo's own library.

    Args:
        model: The MuJoCo model.
        data: The MuJoCo data (the kernel is for this one: a driver's reset makes another).
        body: Astrobee's body id.
        nozzles: The propulsion model (nozzle directions and positions).
        lib: The kernels' library.
        gemv: The address of numpy's CBLAS ``dgemv``.
        apply_ft: The address of MuJoCo's ``mj_applyFT``.
    """

    def __init__(
        self,
        model: Any,
        data: Any,
        body: int,
        nozzles: Any,
        lib: ctypes.CDLL,
        gemv: int,
        apply_ft: int,
    ) -> None:
        self.model, self.data = model, data
        self._dirs = np.ascontiguousarray(nozzles.directions, dtype=np.float64)
        self._pos = np.ascontiguousarray(nozzles.positions, dtype=np.float64)
        self.thrust = np.zeros(len(self._dirs))
        fn = lib.payload_apply_thrusts
        ptr = ctypes.c_void_p
        fn.restype = None
        fn.argtypes = [ptr] * 9 + [ctypes.c_int, ptr]
        row = data.xmat[body]
        self._call = functools.partial(
            fn, gemv, apply_ft, model._address, data._address, row.ctypes.data,
            data.xipos[body].ctypes.data, self._dirs.ctypes.data, self._pos.ctypes.data,
            self.thrust.ctypes.data, body,
        )  # fmt: skip
        self._qfrc = data.qfrc_applied.ctypes.data

    def __call__(self, thrust: np.ndarray, qfrc: np.ndarray | None = None) -> None:
        """Add the thrusts' generalised forces to ``qfrc`` (the data's ``qfrc_applied``)."""
        self.thrust[:] = thrust
        self._call(self._qfrc if qfrc is None else qfrc.ctypes.data)


@native.reported("thrusts")
def compiled_thrusts(
    model: Any, data: Any, body: int, nozzles: Any, python: Any
) -> CompiledThrusts | None:
    """The compiled thrust application, or None to run ``python`` (the numpy loop,
    ``python(thrust, qfrc)``): no kernels, no MuJoCo symbol, or a self-check on random
    thrusts in this data's state that differs from ``python`` in a single bit."""
    n = len(nozzles.thrust_max)
    loaded = _load("thrust kernel", n)
    apply_ft = native.mujoco_function("mj_applyFT")
    if loaded is None or apply_ft is None:
        return None
    kernel = CompiledThrusts(model, data, body, nozzles, loaded[0], loaded[1], apply_ft)
    rng = np.random.default_rng(3)
    for _ in range(50):
        thrust = rng.uniform(0.0, 1.0, size=n) * (rng.random(n) < 0.6)
        mine, theirs = np.zeros(model.nv), np.zeros(model.nv)
        kernel(thrust, mine)
        python(thrust, theirs)
        if mine.tobytes() != theirs.tobytes():
            log.warning("thrust kernel: numpy (the compiled thrusts differ)")
            return None
    return kernel


__all__ = [
    "SOURCE",
    "CompiledControl",
    "CompiledSearches",
    "CompiledThrusts",
    "check_control",
    "compiled_control",
    "compiled_searches",
    "compiled_thrusts",
    "probe_wrenches",
]
