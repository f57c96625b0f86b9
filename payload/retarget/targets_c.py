"""A pair calibration's targets as compiled C, with numpy's bits.

:meth:`payload.retarget.calibration.PairCalibration.to_targets` maps the human features
to the robot pair's targets twice a control step: the calibrated opening, span and
centre, and four rotations of 3-vectors, about twenty numpy calls. Here it is one C call
with the same operations in the same order (the rotations through numpy's own CBLAS
``dgemv`` with the layout numpy passes; ``centre_gain * rotation`` formed once by numpy,
as ``centre_gain * rot @ v`` groups it; Python's ``min``/``max`` tie rules for the
opening; see :mod:`payload.sim.allocation_c` for the method), checked against the numpy
code on random features when it is built. Non-finite features go to the numpy code,
which raises its error; without a compiler, numpy's OpenBLAS or with
``PAYLOAD_NATIVE=0`` the numpy code runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.retarget.features import N_FEATURES, PairFeatures

log = logging.getLogger(__name__)

SOURCE = r"""


/* c: human pinch and open spans, span min and max, robot pinch and open centres, human
   pinch and open centres (16); rot and grot (centre_gain * rot) with their layouts.
   out (13) = [span, rot d, centre, rot u1, rot u2]; 1 if h (13) is not finite. */
int payload_targets(void *gemv_p, const double *c, const double *rot, int rot_order,
                    int64_t rot_ld, const double *grot, int grot_order, int64_t grot_ld,
                    const double *h, double *out)
{
    dgemv_fn gemv = (dgemv_fn)gemv_p;
    for (int k = 0; k < N_FEATURES; k++)
        if (!isfinite(h[k])) return 1;
    double x = (h[0] - c[0]) / (c[1] - c[0]);
    double m = (0.0 > x) ? 0.0 : x;         /* Python max(x, 0.0) */
    double alpha = (1.0 < m) ? 1.0 : m;     /* Python min(m, 1.0) */
    out[0] = c[2] + alpha * (c[3] - c[2]);
    double c_robot[3], diff[3], moved[3];
    for (int i = 0; i < 3; i++) {
        c_robot[i] = (1.0 - alpha) * c[4 + i] + alpha * c[7 + i];
        double c_human = (1.0 - alpha) * c[10 + i] + alpha * c[13 + i];
        diff[i] = h[4 + i] - c_human;
    }
    gemv(grot_order, NO_TRANS, 3, 3, 1.0, grot, grot_ld, diff, 1, 0.0, moved, 1);
    for (int i = 0; i < 3; i++) out[4 + i] = c_robot[i] + moved[i];
    gemv(rot_order, NO_TRANS, 3, 3, 1.0, rot, rot_ld, h + 7, 1, 0.0, out + 7, 1);
    gemv(rot_order, NO_TRANS, 3, 3, 1.0, rot, rot_ld, h + 10, 1, 0.0, out + 10, 1);
    gemv(rot_order, NO_TRANS, 3, 3, 1.0, rot, rot_ld, h + 1, 1, 0.0, out + 1, 1);
    return 0;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledTargets:
    """``to_targets`` of one calibration, compiled.

    Args:
        calibration: The :class:`~payload.retarget.calibration.PairCalibration`.
        lib: The kernel's library.
        gemv: The address of numpy's CBLAS ``dgemv``.
    """

    def __init__(self, calibration: Any, lib: ctypes.CDLL, gemv: int) -> None:
        rg = calibration.range
        rot = np.asarray(calibration.rotation)
        grot = calibration.centre_gain * rot  # as numpy groups centre_gain * rot @ v
        layouts = [native.gemv_layout(rot), native.gemv_layout(grot)]
        if None in layouts or rot.shape != (3, 3):
            raise ValueError("the calibration's rotation is not a contiguous 3x3 float64")
        consts = np.array(
            [
                calibration.human_pinch.span,
                calibration.human_open.span,
                rg.span_min,
                rg.span_max,
                *rg.pinch.centre,
                *rg.open.centre,
                *calibration.human_pinch.centre,
                *calibration.human_open.centre,
            ],
            dtype=np.float64,
        )
        self._keep = (consts, rot, grot)
        self._in = np.zeros(N_FEATURES)
        self._out = np.zeros(N_FEATURES)
        fn = lib.payload_targets
        ptr, i64, cint = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
        fn.restype = ctypes.c_int
        fn.argtypes = [ptr, ptr, ptr, cint, i64, ptr, cint, i64, ptr, ptr]
        (r_order, r_ld), (g_order, g_ld) = layouts
        self.entry: tuple[int, ...] = (
            ctypes.cast(fn, ptr).value, gemv, consts.ctypes.data, rot.ctypes.data, r_order,
            r_ld, grot.ctypes.data, g_order, g_ld,
        )  # fmt: skip
        """``payload_targets``'s address and its leading arguments, for C that calls it
        (:mod:`payload.teleop.pair_c`): then the human features and the targets (13,) each."""
        buffers = (self._in.ctypes.data, self._out.ctypes.data)
        self._call = functools.partial(fn, *self.entry[1:], *buffers)
        self._lock = threading.Lock()  # one set of buffers; ctypes releases the GIL

    def __call__(self, human: np.ndarray) -> PairFeatures | None:
        """The targets of stacked human features (13,), or None when they are not finite
        (the numpy code raises the error)."""
        with self._lock:
            self._in[:] = human
            if self._call():
                return None
            out = self._out
            return PairFeatures(float(out[0]), out[1:4].copy(), out[4:7].copy(), out[7:].copy())


CHECK_FEATURES = 200
"""Random features of the targets' full self-check (:func:`compiled_targets`)."""


@native.reported("pair targets")
def compiled_targets(
    calibration: Any, reference: Callable[[np.ndarray], PairFeatures]
) -> CompiledTargets | None:
    """The compiled ``to_targets`` of ``calibration``, or None to run ``reference`` (the
    numpy code): no compiler, no numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or
    a self-check on :data:`CHECK_FEATURES` random features (pinch, open, beyond both;
    their first tenth once a full check passed, here or in an earlier process:
    :func:`payload.native.probes`) that differs from ``reference`` in a single bit."""
    loaded = native.load_blas_kernel(
        "targets", SOURCE, "the targets kernel", log, native.NUMPY_DGEMV,
        prelude=f"#define N_FEATURES {N_FEATURES}\n",
    )  # fmt: skip
    if loaded is None:
        return None
    try:
        kernel = CompiledTargets(calibration, *loaded)
    except ValueError as exc:
        log.warning("pair targets: numpy (%s)", exc)
        return None

    def check(n: int) -> bool:
        rng = np.random.default_rng(0)
        lo, hi = calibration.human_pinch.span, calibration.human_open.span
        for _ in range(n):
            h = np.concatenate(
                [
                    [rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo))],
                    rng.normal(size=3),
                    rng.normal(scale=0.1, size=3),
                    rng.normal(size=6),
                ]
            )
            got, want = kernel(h), reference(h)
            if got is None or any(
                np.asarray(g).tobytes() != np.asarray(w).tobytes() for g, w in zip(got, want)
            ):
                log.warning("pair targets: numpy (the compiled targets differ)")
                return False
        return True

    if not native.self_checked(loaded[0], "pair targets", CHECK_FEATURES, check):
        return None
    return kernel


__all__ = ["CHECK_FEATURES", "SOURCE", "CompiledTargets", "compiled_targets"]
