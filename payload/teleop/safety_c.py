"""The tracking supervisor's hand check as compiled C, with numpy's bits.

:meth:`payload.teleop.safety.TrackingSupervisor._valid` judges both hands every control
step: every joint finite, every joint within the reach of the wrist, the wrist within its
workspace around the neutral pose and not jumping faster than a hand can move. In numpy
that is a dozen small-array calls a hand. Here the numbers are one C call with the same
operations in the same order (see :mod:`payload.sim.allocation_c` for the method):

* a joint's distance from the wrist is ``sqrt((dx*dx + dy*dy) + dz*dz)``, numpy's
  ``add.reduce`` over a row of three (left to right), and the extent their maximum;
* the wrist's distances are :func:`payload.vecmath.norm`'s, through numpy's own CBLAS
  ``ddot``.

The kernel only says which check fails first; a hand it finds invalid goes through the
numpy check, which words the reason. It is checked against the numpy check on random
hands when it is built; without a compiler, numpy's OpenBLAS or with ``PAYLOAD_NATIVE=0``
the numpy check runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable

import numpy as np

from payload import native

log = logging.getLogger(__name__)

SOURCE = r"""


/* The checks of TrackingSupervisor._valid on a tracked hand: joints (n x 3, row-major),
   the wrist its row `wrist`. p: max_extent, workspace radius, the jump allowed now.
   neutral, last: the neutral wrist and the last valid wrist (3), each when has_*.
   0: valid; 1: a non-finite joint; 2: a joint beyond max_extent; 3: the wrist beyond the
   radius; 4: the wrist jumped. */
int payload_hand_valid(void *ddot, const double *joints, int64_t n, int64_t wrist,
                       const double *p, const double *neutral, int has_neutral,
                       const double *last, int has_last)
{
    ddot_fn dot = (ddot_fn)ddot;
    for (int64_t i = 0; i < 3 * n; i++)
        if (!isfinite(joints[i])) return 1;
    const double *w = joints + 3 * wrist;
    double extent = 0.0;
    for (int64_t i = 0; i < n; i++) {
        const double dx = joints[3 * i] - w[0], dy = joints[3 * i + 1] - w[1],
                     dz = joints[3 * i + 2] - w[2];
        const double r = sqrt((dx * dx + dy * dy) + dz * dz);
        if (i == 0 || r > extent) extent = r;
    }
    if (extent > p[0]) return 2;
    double v[3];
    if (has_neutral) {
        for (int k = 0; k < 3; k++) v[k] = w[k] - neutral[k];
        if (sqrt(dot(3, v, 1, v, 1)) > p[1]) return 3;
    }
    if (has_last) {
        for (int k = 0; k < 3; k++) v[k] = w[k] - last[k];
        if (sqrt(dot(3, v, 1, v, 1)) > p[2]) return 4;
    }
    return 0;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""


class CompiledHandCheck:
    """The hand check of one side (its neutral wrist and limits bound in).

    Args:
        lib: The kernel's library.
        ddot: The address of numpy's CBLAS ``ddot``.
        joints: Joints per hand.
        wrist: The wrist's row.
        max_extent: The largest joint distance from the wrist [m].
        neutral: The neutral wrist, a contiguous float64 array (3,) [m] read in place at
            every check, or None (no workspace check).

    Raises:
        ValueError: Another neutral (the numpy check runs).
        radius: The workspace radius around it [m].
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        ddot: int,
        joints: int,
        wrist: int,
        max_extent: float,
        neutral: np.ndarray | None,
        radius: float,
    ) -> None:
        self.shape = (joints, 3)
        has_neutral = neutral is not None
        self._joints = np.zeros(self.shape)
        if neutral is None:
            neutral = np.zeros(3)
        elif not (
            type(neutral) is np.ndarray
            and neutral.dtype == np.float64
            and neutral.shape == (3,)
            and neutral.flags.c_contiguous
        ):
            raise ValueError("the neutral wrist is not a contiguous float64 3-vector")
        self._neutral = neutral  # read in place: a change to the caller's array counts
        self._last = np.zeros(3)
        self._params = np.array([max_extent, radius, 0.0])
        fn = lib.payload_hand_valid
        ptr = ctypes.c_void_p
        fn.restype = ctypes.c_int
        i64 = ctypes.c_int64
        fn.argtypes = [ptr, ptr, i64, i64, ptr, ptr, ctypes.c_int, ptr, ctypes.c_int]
        self._call = functools.partial(
            fn, ddot, self._joints.ctypes.data, joints, wrist, self._params.ctypes.data,
            self._neutral.ctypes.data, int(has_neutral), self._last.ctypes.data,
        )  # fmt: skip
        self.entry = (
            ctypes.cast(fn, ptr).value, ddot, joints, wrist, self._params,
            self._neutral.ctypes.data, int(has_neutral),
        )  # fmt: skip
        """For a caller that runs the check from its own C: the function, numpy's ``ddot``,
        the joints per hand, the wrist's row, the limits (max extent, radius, then the
        jump's place), the neutral wrist's address and whether it is checked."""

    def __call__(self, joints: np.ndarray, last: np.ndarray | None, jump: float) -> int:
        """The first failing check's code (0: valid) for ``joints``, with ``last`` the
        last valid wrist (None: no jump check) and ``jump`` the distance allowed."""
        np.copyto(self._joints, joints)
        if last is not None:
            np.copyto(self._last, last)
            self._params[2] = jump
        return self._call(last is not None)


CHECK_HANDS = 2000
"""Random hands of the hand check's full self-check (:func:`compiled_hand_check`)."""


@native.reported("hand check")
def compiled_hand_check(
    joints: int,
    wrist: int,
    max_extent: float,
    neutral: np.ndarray | None,
    radius: float,
    reference: Callable[[np.ndarray, np.ndarray | None, float], bool],
) -> CompiledHandCheck | None:
    """The compiled check of one side, or None to run the numpy check: no compiler, no
    numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check on random hands
    (valid, stretched, displaced, jumping and non-finite ones) that judges one otherwise
    than ``reference(joints, last, jump)``, the numpy check's verdict: 2000 of them, or
    their first 200 once a build for as many joints passed (here or in an
    earlier process: :func:`payload.native.probes`)."""
    loaded = native.load_blas_kernel(
        "hand_check", SOURCE, "the hand check kernel", log, native.NUMPY_DDOT
    )
    if loaded is None:
        return None
    try:
        kernel = CompiledHandCheck(*loaded, joints, wrist, max_extent, neutral, radius)
    except ValueError:
        return None  # a neutral the kernel cannot read in place: the numpy check
    centre = np.zeros(3) if neutral is None else np.asarray(neutral, dtype=np.float64)

    def check(n: int) -> bool:
        rng = np.random.default_rng(0)
        verdicts = set()
        for k in range(n):
            # hands around the neutral pose, some stretched to the reach limit, some far off
            wrist_at = centre + rng.normal(scale=(0.02, 0.2, 1.0)[k % 3] * max(radius, 0.1), size=3)
            hand = wrist_at + rng.normal(scale=max_extent * (0.2, 0.55)[k % 2], size=(joints, 3))
            hand[wrist] = wrist_at
            if k % 97 == 11:
                hand[k % joints, k % 3] = (np.nan, np.inf)[k % 2]
            last = None if k % 5 == 0 else wrist_at + rng.normal(scale=0.01, size=3)
            jump = float(rng.uniform(0.0, 0.03))
            mine = kernel(hand, last, jump) == 0
            if mine != reference(hand, last, jump):
                log.warning("hand check: numpy (the compiled check differs)")
                return False
            verdicts.add(mine)
        return verdicts == {True, False}  # the probes, short or full, met both verdicts

    if not native.self_checked(loaded[0], (joints, wrist), CHECK_HANDS, check):
        return None
    return kernel


__all__ = ["SOURCE", "CompiledHandCheck", "compiled_hand_check"]
