"""The One Euro filter's step on (n, 3) keypoints as compiled C, with numpy's bits.

:class:`payload.teleop.filters.OneEuroFilter` filters both hands' 25 joints every
control step: about twenty numpy calls on (25, 3) arrays. Here the step after the
first sample is one C call with the same operations in the same order (elementwise
IEEE arithmetic; each row's squared speed summed left to right, as numpy's
``add.reduce`` does on rows of three; the constants ``2 pi`` and the speed-filter
weight come from the Python code), checked against the numpy step on random samples when
it is built. Without a compiler or with ``PAYLOAD_NATIVE=0`` the numpy step runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native

log = logging.getLogger(__name__)

SOURCE = r"""

/* One step for samples x (n, 3): the estimate xs and the speed estimate ds (n, 3) are
   updated in place (each element from its own previous value); dt, the speed filter's
   weight a_d, 2 pi, the cutoff at rest and the speed coefficient. */
void payload_one_euro(const double *x, double *xs, double *ds, int64_t n, double dt,
                      double a_d, double two_pi, double min_cutoff, double beta)
{
    for (int64_t k = 0; k < 3 * n; k++) {
        double dx = (x[k] - xs[k]) / dt;
        ds[k] = a_d * dx + (1 - a_d) * ds[k];
    }
    for (int64_t r = 0; r < n; r++) {
        const double *d = ds + 3 * r;
        double speed = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        double tau = 1.0 / (two_pi * (min_cutoff + beta * speed));
        double a = 1.0 / (1.0 + tau / dt);
        for (int i = 0; i < 3; i++)
            xs[3 * r + i] = a * x[3 * r + i] + (1 - a) * xs[3 * r + i];
    }
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledOneEuro:
    """The filter's step on (n, 3) samples, compiled (:data:`SOURCE`)."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        fn = lib.payload_one_euro
        ptr, dbl = ctypes.c_void_p, ctypes.c_double
        fn.restype = None
        fn.argtypes = [ptr, ptr, ptr, ctypes.c_int64, dbl, dbl, dbl, dbl, dbl]
        self._fn = fn
        self.address = ctypes.cast(fn, ctypes.c_void_p).value
        """The step's C function (for callers that run it from their own C)."""
        self.two_pi = 2.0 * math.pi
        """The step's ``2 pi`` argument."""

    def stepper(
        self, x_state: np.ndarray, dx_state: np.ndarray, min_cutoff: float, beta: float
    ) -> Callable[[np.ndarray, float, float], None]:
        """``step(x, dt, a_d)``: one filter step for sample ``x`` that updates the estimate
        ``x_state`` and the speed estimate ``dx_state`` (C-contiguous float64, (n, 3)) in
        place; ``x`` is copied into a buffer of the stepper's own first."""
        for a in (x_state, dx_state):
            if not (a.dtype == np.float64 and a.flags.c_contiguous and a.shape == x_state.shape):
                raise ValueError("the filter's estimates must be C-contiguous float64 (n, 3)")
        buf = np.empty_like(x_state)
        fixed = [ctypes.c_void_p(a.ctypes.data) for a in (buf, x_state, dx_state)]
        call = functools.partial(self._fn, *fixed, len(x_state))
        two_pi = self.two_pi

        def step(x: np.ndarray, dt: float, a_d: float) -> None:
            np.copyto(buf, x)
            call(dt, a_d, two_pi, min_cutoff, beta)

        step.keep = (buf, x_state, dx_state)  # type: ignore[attr-defined]
        step.kernel = self  # type: ignore[attr-defined]
        return step


CHECK_SAMPLES = 300
"""Random samples of the filter step's full self-check (:func:`compiled_one_euro`)."""


@functools.cache
@native.reported("One Euro filter")
def compiled_one_euro(reference: Callable[..., Any]) -> CompiledOneEuro | None:
    """The process's compiled filter step, or None to run the numpy step (no compiler,
    ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that differs in a single bit from
    ``reference(x, prev_x, prev_dx, dt, a_d, min_cutoff, beta)``, the numpy step, on
    :data:`CHECK_SAMPLES` random samples, histories, periods and settings, or their first
    tenth once a full check passed, here or in an earlier process:
    :func:`payload.native.probes`)."""
    lib = native.load_kernel("one_euro", SOURCE, "the One Euro filter kernel", log)
    if lib is None:
        return None
    kernel = CompiledOneEuro(lib)

    def check(n_probes: int) -> bool:
        rng = np.random.default_rng(0)
        for i in range(n_probes):
            n = (25, 1, 4)[i % 3]
            x, prev_x = rng.normal(scale=0.3, size=(2, n, 3))
            prev_dx = rng.normal(scale=0.5, size=(n, 3)) * (i % 7 != 0)
            dt, a_d = float(rng.uniform(1e-3, 0.1)), float(rng.uniform(0.05, 1.0))
            min_cutoff, beta = float(rng.uniform(0.1, 3.0)), float(rng.uniform(0.0, 2.0))
            want = reference(x, prev_x, prev_dx, dt, a_d, min_cutoff, beta)
            xs, ds = prev_x.copy(), prev_dx.copy()
            kernel.stepper(xs, ds, min_cutoff, beta)(x, dt, a_d)
            if xs.tobytes() != want[0].tobytes() or ds.tobytes() != want[1].tobytes():
                log.warning("One Euro filter: numpy (the compiled step differs)")
                return False
        return True

    if not native.self_checked(lib, "One Euro filter", CHECK_SAMPLES, check):
        return None
    return kernel


__all__ = ["CHECK_SAMPLES", "SOURCE", "CompiledOneEuro", "compiled_one_euro"]
