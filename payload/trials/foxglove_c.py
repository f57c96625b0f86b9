"""The Foxglove ``/tf`` poses as compiled C.

:meth:`payload.trials.foxglove.FoxgloveScene.transforms` runs at every fifth control step
of every recorded trial: per link of Astrobee and the payload (and the CTB), its pose in
its parent's frame, rounded to :data:`~payload.trials.foxglove.VIEW_RESOLUTION`. In numpy
that is a handful of small-array calls per link (about 85 us a message for 20 links). The
kernel makes the same calls in C, one call a message:

* the position is the parent's rotation transposed times the difference of the two
  origins, through numpy's own ``dgemv`` (:func:`payload.native.numpy_dgemv`), with the
  layout numpy's ``matmul`` passes for the transposed (Fortran-ordered) matrix;
* the rotation is MuJoCo's own ``mju_negQuat`` and ``mju_mulQuat``, the functions the
  numpy code calls through the bindings;
* the rounding is ``rint(x / r) * r``, numpy's ``round`` (ties to even, the default
  rounding mode), exact for a power-of-two resolution.

It is checked against the numpy code, bit for bit, on random poses when it is built; on any
difference, without a compiler, without numpy's OpenBLAS or with ``PAYLOAD_NATIVE=0``, the
numpy code runs.
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

typedef void (*quat1_fn)(double *, const double *);
typedef void (*quat2_fn)(double *, const double *, const double *);


/* per link i: out[7i..7i+2] = R(parent)^T (x(link) - x(parent)), out[7i+3..7i+6] =
   conj(q(parent)) q(link) (w x y z), then every value rounded to the resolution */
void payload_frame_poses(void *gemv, void *negq, void *mulq, int64_t n, const int64_t *links,
                         const int64_t *parents, const double *xmat, const double *xpos,
                         const double *xquat, double resolution, double *out)
{
    dgemv_fn mv = (dgemv_fn)gemv;
    quat1_fn neg = (quat1_fn)negq;
    quat2_fn mul = (quat2_fn)mulq;
    for (int64_t i = 0; i < n; i++) {
        const int64_t b = links[i], p = parents[i];
        double d[3], inv[4];
        for (int k = 0; k < 3; k++) d[k] = xpos[3 * b + k] - xpos[3 * p + k];
        /* the transposed row-major 3x3 is a column-major one, as numpy hands it on */
        mv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, xmat + 9 * p, 3, d, 1, 0.0, out + 7 * i, 1);
        neg(inv, xquat + 4 * p);
        mul(out + 7 * i + 3, inv, xquat + 4 * b);
    }
    for (int64_t j = 0; j < 7 * n; j++) out[j] = rint(out[j] / resolution) * resolution;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledFramePoses:
    """The rounded parent-frame poses of some links, for one MuJoCo data.

    Args:
        lib: The kernel's library.
        data: The MuJoCo data whose ``xmat``, ``xpos`` and ``xquat`` are read in place.
        links: The links' body ids (N,).
        parents: Their parents' body ids (N,).
        resolution: The rounding step (a power of two).
        functions: The addresses of numpy's ``dgemv`` and MuJoCo's ``mju_negQuat`` and
            ``mju_mulQuat``.
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        data: Any,
        links: np.ndarray,
        parents: np.ndarray,
        resolution: float,
        functions: tuple[int, int, int],
    ) -> None:
        self.data = data
        self._links = np.ascontiguousarray(links, dtype=np.int64)
        self._parents = np.ascontiguousarray(parents, dtype=np.int64)
        self.out = np.zeros((len(self._links), 7))
        for name in ("xmat", "xpos", "xquat"):
            a = getattr(data, name)
            if not (a.dtype == np.float64 and a.flags.c_contiguous):
                raise ValueError(f"{name} is not a C-contiguous float64 array")
        fn = lib.payload_frame_poses
        ptr = ctypes.c_void_p
        fn.restype = None
        fn.argtypes = [ptr, ptr, ptr, ctypes.c_int64, ptr, ptr, ptr, ptr, ptr, ctypes.c_double, ptr]
        self._call = functools.partial(
            fn, *functions, len(self._links), self._links.ctypes.data,
            self._parents.ctypes.data, data.xmat.ctypes.data, data.xpos.ctypes.data,
            data.xquat.ctypes.data, resolution, self.out.ctypes.data,
        )  # fmt: skip

    def __call__(self) -> np.ndarray:
        """The poses (N, 7): position, then quaternion w x y z, rounded (a fresh array)."""
        self._call()
        return self.out.copy()


CHECK_POSTURES = 200
"""Random postures of the frame poses' full self-check (:func:`compiled_frame_poses`)."""


@native.reported("frame poses")
def compiled_frame_poses(
    model: Any,
    data: Any,
    links: np.ndarray,
    parents: np.ndarray,
    resolution: float,
    reference: Callable[[], np.ndarray],
) -> CompiledFramePoses | None:
    """The compiled poses for ``data``, or None to run ``reference`` (the numpy poses of
    the data's current kinematics): no compiler, ``PAYLOAD_NATIVE=0``, no numpy OpenBLAS or
    MuJoCo symbol, or a self-check on random configurations (written into the data's
    ``qpos`` and restored) that differs from ``reference`` in a single bit: 200 of them,
    or their first 20 once a build for as many links passed (here or in an
    earlier process: :func:`payload.native.probes`)."""
    import mujoco

    if len(links) == 0:
        return None
    quats = native.mujoco_function("mju_negQuat"), native.mujoco_function("mju_mulQuat")
    if None in quats:
        return None
    loaded = native.load_blas_kernel(
        "frame_poses", SOURCE, "the frame poses kernel", log, native.NUMPY_DGEMV
    )
    if loaded is None:
        return None
    lib, functions = loaded[0], (loaded[1], *quats)
    try:
        kernel = CompiledFramePoses(lib, data, links, parents, resolution, functions)
    except ValueError as exc:
        log.warning("frame poses: numpy (%s)", exc)
        return None

    def check(n: int) -> bool:
        saved = data.qpos.copy()
        rng = np.random.default_rng(0)
        try:
            for _ in range(n):
                data.qpos[:] = rng.normal(scale=2.0, size=model.nq)
                mujoco.mj_normalizeQuat(model, data.qpos)
                mujoco.mj_kinematics(model, data)
                if kernel().tobytes() != np.asarray(reference()).tobytes():
                    log.warning("frame poses: numpy (the compiled poses differ)")
                    return False
        finally:
            data.qpos[:] = saved
            mujoco.mj_kinematics(model, data)
        return True

    if not native.self_checked(lib, len(links), CHECK_POSTURES, check):
        return None
    return kernel


__all__ = ["SOURCE", "CompiledFramePoses", "compiled_frame_poses"]
