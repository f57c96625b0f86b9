"""The base channel's jerk limiter on vectors as compiled C, with numpy's bits.

:meth:`payload.teleop.channels.JerkLimiter.step` shapes the vehicle's requested velocity
every control step: norms, dot products and about forty numpy calls on 3-vectors. Here a
vector step is one C call with the same operations in the same order (norms and dot
products through numpy's own CBLAS ``ddot``, Python's ``min``/``max`` tie rules, the
state updated in place; see :mod:`payload.sim.allocation_c` for the method), checked
against the numpy step on random requests when it is built. Without a compiler,
numpy's OpenBLAS or with ``PAYLOAD_NATIVE=0`` the numpy step runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.schema import CONTROL_DT

log = logging.getLogger(__name__)

MAX_DIM = 16
"""The largest vector the kernel takes (the base channel's is 3)."""

SOURCE = r"""

#define MAX_DIM @MAX_DIM@


static ddot_fn dot;
void payload_limiter_init(void *d) { dot = (ddot_fn)d; }

static double nrm(const double *v, int64_t n) { return sqrt(dot(n, v, 1, v, 1)); }

/* JerkLimiter._step_vector toward tgt (n): value and rate (n) updated in place.
   p: max_rate, max_jerk, max_value (has_max), zero_error, zero_value. */
void payload_limiter_step(const double *tgt, double *value, double *rate, int64_t n,
                          double dt, const double *p, int has_max)
{
    const double max_rate = p[0], max_jerk = p[1], max_value = p[2];
    const double zero_error = p[3], zero_value = p[4];
    double t[MAX_DIM], e[MAX_DIM], w[MAX_DIM], a_t[MAX_DIM], da[MAX_DIM], u[MAX_DIM];
    for (int64_t i = 0; i < n; i++) t[i] = tgt[i];
    if (has_max) {
        double tn = nrm(t, n);
        if (tn > max_value) {
            double f = max_value / tn;
            for (int64_t i = 0; i < n; i++) t[i] = t[i] * f;
        }
    }
    int moving = 0;
    for (int64_t i = 0; i < n; i++) { e[i] = t[i] - value[i]; moving |= e[i] != 0.0; }
    const double jdt = max_jerk * dt;
    if (!moving && nrm(rate, n) <= jdt) {           /* at rest on the target */
        for (int64_t i = 0; i < n; i++) rate[i] = 0.0;
        return;
    }
    for (int64_t i = 0; i < n; i++) w[i] = e[i] / dt;  /* landing */
    if (nrm(w, n) <= jdt) {
        double d[MAX_DIM];
        for (int64_t i = 0; i < n; i++) d[i] = w[i] - rate[i];
        if (nrm(d, n) <= jdt) {
            for (int64_t i = 0; i < n; i++) { rate[i] = w[i]; value[i] = t[i]; }
            return;
        }
    }
    double nr = nrm(rate, n);
    for (int64_t i = 0; i < n; i++) w[i] = e[i] - rate[i] * nr / (2 * max_jerk);  /* e_eff */
    double ne = nrm(w, n);
    if (ne < zero_error) {
        for (int64_t i = 0; i < n; i++) a_t[i] = 0.0;
    } else {
        double s = sqrt(2 * max_jerk * ne);
        double m = (s < max_rate) ? s : max_rate;   /* min(max_rate, s) */
        for (int64_t i = 0; i < n; i++) a_t[i] = w[i] / ne * m;
    }
    for (int64_t i = 0; i < n; i++) da[i] = a_t[i] - rate[i];
    double vn = nrm(value, n);
    if (has_max && vn > zero_value) {
        for (int64_t i = 0; i < n; i++) u[i] = value[i] / vn;
        double room = max_value - vn;
        double cap = sqrt(2 * max_jerk * ((room > 0.0) ? room : 0.0));  /* max(0.0, room) */
        double radial_now = dot(n, rate, 1, u, 1);
        double aw = dot(n, a_t, 1, u, 1);
        double radial_want = (cap < aw) ? cap : aw;                     /* min(aw, cap) */
        double x = radial_want - radial_now;
        double lo = (-jdt > x) ? -jdt : x;                              /* max(x, -jdt) */
        double dr = (jdt < lo) ? jdt : lo;                              /* min(lo, jdt) */
        double s = dot(n, da, 1, u, 1);
        double tang[MAX_DIM];
        for (int64_t i = 0; i < n; i++) tang[i] = da[i] - s * u[i];
        double b2 = jdt * jdt - dr * dr;
        double budget = sqrt((b2 > 0.0) ? b2 : 0.0);                    /* max(0.0, b2) */
        double tn = nrm(tang, n);
        if (tn > budget) {
            double f = budget / tn;
            for (int64_t i = 0; i < n; i++) tang[i] *= f;
        }
        double nw[MAX_DIM];
        for (int64_t i = 0; i < n; i++) { da[i] = dr * u[i] + tang[i]; nw[i] = rate[i] + da[i]; }
        double nn = nrm(nw, n);
        if (nn > max_rate) {
            double f = max_rate / nn;
            for (int64_t i = 0; i < n; i++) da[i] = nw[i] * f - rate[i];
        }
    } else {
        double dn = nrm(da, n);
        if (dn > jdt) {
            double f = jdt / dn;
            for (int64_t i = 0; i < n; i++) da[i] *= f;
        }
    }
    for (int64_t i = 0; i < n; i++) {
        rate[i] = rate[i] + da[i];
        value[i] = value[i] + rate[i] * dt;
    }
}
""".replace("@MAX_DIM@", str(MAX_DIM))
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


def limiter_params(limiter: Any) -> np.ndarray:
    """A limiter's settings as ``payload_limiter_step`` takes them (``p``): max rate, max
    jerk, max value (0 without a cap; the call says whether there is one), zero error,
    zero value."""
    return np.array(
        [
            limiter.max_rate,
            limiter.max_jerk,
            0.0 if limiter.max_value is None else limiter.max_value,
            limiter.ZERO_ERROR,
            limiter.ZERO_VALUE,
        ],
        dtype=np.float64,
    )


class CompiledLimiter:
    """The vector step, compiled (:data:`SOURCE`), bound to limiters by :meth:`stepper`."""

    def __init__(self, lib: ctypes.CDLL, ddot: int) -> None:
        init = lib.payload_limiter_init
        init.argtypes = [ctypes.c_void_p]
        init(ddot)
        fn = lib.payload_limiter_step
        ptr = ctypes.c_void_p
        fn.restype = None
        fn.argtypes = [ptr, ptr, ptr, ctypes.c_int64, ctypes.c_double, ptr, ctypes.c_int]
        self._fn = fn

    def stepper(self, limiter: Any) -> Callable[[Any, float], None] | None:
        """``step(target, dt)`` updating ``limiter.value`` and ``limiter.rate`` (its
        current arrays) in place, or None for a limiter the kernel does not take."""
        value, rate = limiter.value, limiter.rate
        n = len(value)
        for a in (value, rate):
            if not (a.dtype == np.float64 and a.flags.c_contiguous and a.shape == (n,)):
                return None
        if not 1 <= n <= MAX_DIM:
            return None
        if not (limiter.max_jerk > 0 and limiter.max_rate >= 0):
            return None  # numpy's step says what is wrong (math.sqrt of a negative)
        has_max = limiter.max_value is not None
        params = limiter_params(limiter)
        buf = np.empty(n)
        ptr = ctypes.c_void_p
        call = functools.partial(
            self._fn, ptr(buf.ctypes.data), ptr(value.ctypes.data), ptr(rate.ctypes.data), n
        )
        tail = (ptr(params.ctypes.data), int(has_max))

        def step(target: Any, dt: float) -> None:
            np.copyto(buf, target)
            call(dt, *tail)

        step.keep = (buf, params, value, rate)  # type: ignore[attr-defined]
        return step


@functools.cache
@native.reported("jerk limiter")
def compiled_limiter(factory: Callable[..., Any]) -> CompiledLimiter | None:
    """The process's compiled vector step, or None to run the numpy step (no compiler,
    no numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that differs
    in a single bit from the numpy step of limiters made by ``factory(dim, max_rate,
    max_jerk, max_value)``, on random requests with and without a value cap)."""
    loaded = native.load_blas_kernel(
        "limiter", SOURCE, "the jerk limiter kernel", log, native.NUMPY_DDOT
    )
    if loaded is None:
        return None
    kernel = CompiledLimiter(*loaded)
    rng = np.random.default_rng(0)
    for cap in (None, 0.19, 0.05):
        mine, theirs = factory(3, 0.0175, 0.02, cap), factory(3, 0.0175, 0.02, cap)
        step = kernel.stepper(mine)
        if step is None:
            return None
        target = np.zeros(3)
        for k in range(400):
            if k % 60 == 0:  # hold, move, beyond the cap, back to rest
                target = rng.normal(scale=(0.0, 0.05, 0.3, 1e-3)[(k // 60) % 4], size=3)
            step(target, CONTROL_DT)
            theirs._step_vector(target, CONTROL_DT)
            if mine.value.tobytes() != theirs.value.tobytes() or (
                mine.rate.tobytes() != theirs.rate.tobytes()
            ):
                log.warning("jerk limiter: numpy (the compiled step differs)")
                return None
            theirs.value, theirs.rate = mine.value.copy(), mine.rate.copy()
    return kernel


__all__ = ["MAX_DIM", "SOURCE", "CompiledLimiter", "compiled_limiter", "limiter_params"]
