"""A hand's eq. 2 features as compiled C, with numpy's bits.

:func:`payload.teleop.pipeline.human_features` runs for both hands every control step:
the wrist frame from four joints (:func:`~payload.teleop.hands.wrist_frame`), the thumb
and index points in it (:func:`~payload.teleop.hands.pinch_points`) and the pair features
(:func:`~payload.retarget.features.features_from_points`), about thirty numpy calls on
3-vectors. Here they are one C call that does the same operations in the same order
(the norms through numpy's own CBLAS ``ddot``, the frame's transposed rotation through
its ``dgemv`` with the layout numpy passes for ``t[:3, :3].T``; see
:mod:`payload.sim.allocation_c` for the method), checked against the numpy code on
random hands when it is built. A hand the C finds degenerate or not finite goes to the
numpy code, which raises its error; without a compiler, numpy's OpenBLAS or with
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
from payload.retarget.errors import RetargetError
from payload.retarget.features import _EPS, N_FEATURES
from payload.teleop.hands import (
    INDEX_DISTAL,
    INDEX_KNUCKLE,
    INDEX_TIP,
    MIDDLE_KNUCKLE,
    PINKY_KNUCKLE,
    THUMB_DISTAL,
    THUMB_TIP,
    WRIST,
)

log = logging.getLogger(__name__)

SOURCE = r"""


static double norm3(ddot_fn dot, const double *v) { return sqrt(dot(3, v, 1, v, 1)); }

/* vecmath.cross: the same products and differences */
static void cross3(const double *a, const double *b, double *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* features._unit: v / |v|, 0 if |v| is not above eps */
static int unit3(ddot_fn dot, const double *v, double eps, double *out, double *n)
{
    *n = norm3(dot, v);
    if (!(*n > eps)) return 0;
    for (int i = 0; i < 3; i++) out[i] = v[i] / *n;
    return 1;
}

/* human_features(hand) as the stacked vector [l, d_hat, c, u1, u2] (13) of joints (n, 3);
   idx: wrist, middle, index and pinky knuckles, thumb tip and distal, index tip and
   distal. 0: done; 1: not finite or degenerate (the numpy code says which). */
int payload_hand_features(void *gemv_p, void *dot_p, const double *J, const int64_t *idx,
                          double eps, double *out)
{
    dgemv_fn gemv = (dgemv_fn)gemv_p;
    ddot_fn dot = (ddot_fn)dot_p;
    const double *w = J + 3 * idx[0];
    double along[3], across[3], x[3], y[3], z[3], t[16];
    for (int i = 0; i < 3; i++) {
        along[i] = J[3 * idx[1] + i] - w[i];
        across[i] = J[3 * idx[2] + i] - J[3 * idx[3] + i];
    }
    double n = norm3(dot, along);
    for (int i = 0; i < 3; i++) x[i] = along[i] / n;
    cross3(x, across, z);
    n = norm3(dot, z);
    for (int i = 0; i < 3; i++) z[i] = z[i] / n;
    cross3(z, x, y);
    for (int i = 0; i < 16; i++) t[i] = (i % 5 == 0) ? 1.0 : 0.0;
    for (int i = 0; i < 3; i++) {
        t[4 * i] = x[i]; t[4 * i + 1] = y[i]; t[4 * i + 2] = z[i]; t[4 * i + 3] = w[i];
    }
    /* pinch_points: rot.T @ (v - pos), rot = t[:3, :3] (numpy: column-major, lda 4) */
    double pts[4][3]; /* p1, p2, a1, a2 as features_from_points takes them */
    const int64_t which[4] = {idx[4], idx[6], idx[5], idx[7]};
    for (int k = 0; k < 4; k++) {
        double d[3];
        for (int i = 0; i < 3; i++) d[i] = J[3 * which[k] + i] - t[4 * i + 3];
        gemv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, t, 4, d, 1, 0.0, pts[k], 1);
    }
    for (int k = 0; k < 4; k++)
        for (int i = 0; i < 3; i++)
            if (!isfinite(pts[k][i])) return 1;
    double v[3], span, n1, n2;
    for (int i = 0; i < 3; i++) v[i] = pts[1][i] - pts[0][i];
    if (!unit3(dot, v, eps, out + 1, &span)) return 1;
    for (int i = 0; i < 3; i++) v[i] = pts[0][i] - pts[2][i];
    if (!unit3(dot, v, eps, out + 7, &n1)) return 1;
    for (int i = 0; i < 3; i++) v[i] = pts[1][i] - pts[3][i];
    if (!unit3(dot, v, eps, out + 10, &n2)) return 1;
    out[0] = span;
    for (int i = 0; i < 3; i++) out[4 + i] = 0.5 * (pts[0][i] + pts[1][i]);
    return 0;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""

_JOINTS = (
    WRIST,
    MIDDLE_KNUCKLE,
    INDEX_KNUCKLE,
    PINKY_KNUCKLE,
    THUMB_TIP,
    THUMB_DISTAL,
    INDEX_TIP,
    INDEX_DISTAL,
)


class CompiledHandFeatures:
    """:func:`~payload.teleop.pipeline.human_features` of a hand's joints, compiled.

    Args:
        lib: The kernel's library (:data:`SOURCE`).
        gemv: The address of numpy's CBLAS ``dgemv``.
        ddot: The address of numpy's CBLAS ``ddot``.
    """

    def __init__(self, lib: ctypes.CDLL, gemv: int, ddot: int) -> None:
        self._idx = np.array(_JOINTS, dtype=np.int64)
        self._out = np.zeros(N_FEATURES)
        fn = lib.payload_hand_features
        ptr = ctypes.c_void_p
        fn.restype = ctypes.c_int
        fn.argtypes = [ptr, ptr, ptr, ptr, ctypes.c_double, ptr]
        self._call = functools.partial(fn, gemv, ddot)
        self._args = (self._idx.ctypes.data, _EPS, self._out.ctypes.data)
        self.entry: tuple[int, int, int, int, float] = (
            ctypes.cast(fn, ptr).value,
            gemv,
            ddot,
            self._idx.ctypes.data,
            _EPS,
        )
        """``payload_hand_features``'s address and its leading arguments, for C that calls
        it (:mod:`payload.teleop.pair_c`): then the joints (n, 3) and the output (13,)."""
        self._lock = threading.Lock()  # one output buffer; ctypes releases the GIL

    def __call__(self, joints: np.ndarray) -> np.ndarray | None:
        """The stacked features ``[l, d_hat, c, u1, u2]`` (13,) of joints (n, 3), or None
        when they are not finite or degenerate (the numpy code raises the error)."""
        j = joints
        if not (j.dtype == np.float64 and j.flags.c_contiguous and j.ndim == 2):
            j = np.ascontiguousarray(j, dtype=np.float64)
        with self._lock:
            if self._call(j.ctypes.data, *self._args):
                return None
            return self._out.copy()


def random_hands(n: int, seed: int = 0) -> list[np.ndarray]:
    """Joint arrays (25, 3) of the parametric hand in random poses, sizes, apertures and
    places, with tracker-like noise, and some degenerate ones (the self-check's probes)."""
    from payload.rotations import quat_to_matrix
    from payload.teleop.handmodel import HandModel

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        model = HandModel(("left", "right")[i % 2], float(rng.uniform(0.8, 1.2)))
        q = rng.normal(size=4)
        joints = model.joints(
            rng.normal(scale=0.3, size=3),
            quat_to_matrix(q / np.sqrt(q @ q)),
            float(rng.uniform(-0.1, 1.1)),
            float(rng.uniform(0.0, 1.2)),
        )
        joints = joints + rng.normal(scale=2e-3, size=joints.shape) * (i % 3 == 0)
        if i % 50 == 7:  # thumb tip on the index tip: no direction
            joints[INDEX_TIP] = joints[THUMB_TIP]
        if i % 50 == 23:
            joints[THUMB_DISTAL, 1] = np.nan
        out.append(joints)
    return out


CHECK_HANDS = 300
"""Random hands of the hand features' full self-check (:func:`compiled_hand_features`)."""


@functools.cache
@native.reported("hand features")
def compiled_hand_features(reference: Callable[[Any], Any]) -> CompiledHandFeatures | None:
    """The process's compiled hand features, or None to run the numpy code (no
    compiler, no numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check on
    :func:`random_hands` that differs in a single bit from ``reference``, the numpy code:
    :func:`~payload.teleop.pipeline.human_features`; :data:`CHECK_HANDS` hands, or their
    first tenth once a full check passed, here or in an earlier process:
    :func:`payload.native.probes`)."""
    loaded = native.load_blas_kernel(
        "hand_features", SOURCE, "the hand features kernel", log,
        native.NUMPY_DGEMV, native.NUMPY_DDOT,
    )  # fmt: skip
    if loaded is None:
        return None
    kernel = CompiledHandFeatures(*loaded)
    from payload.teleop.hands import Hand

    def want_of(joints: np.ndarray) -> np.ndarray | None:
        try:
            return reference(Hand(joints, True)).as_vector()
        except RetargetError:
            return None

    def check(n: int) -> bool:
        with np.errstate(all="ignore"):
            for joints in random_hands(n):
                got, want = kernel(joints), want_of(joints)
                if (got is None) != (want is None) or (
                    got is not None and got.tobytes() != want.tobytes()
                ):
                    return False
        return True

    if not native.self_checked(loaded[0], "hand features", CHECK_HANDS, check):
        log.warning("hand features: numpy (the compiled features differ)")
        return None
    return kernel


__all__ = [
    "CHECK_HANDS",
    "SOURCE",
    "CompiledHandFeatures",
    "compiled_hand_features",
    "random_hands",
]
