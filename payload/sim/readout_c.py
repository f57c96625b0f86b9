"""The simulator's per-step read-out as compiled C, with numpy's bits.

After every control step the loop reads the world (:meth:`SimDriver.world_state
<payload.sim.driver.SimDriver.world_state>`: Astrobee's and the CTB's poses, Astrobee's
body twist) and the payload (:meth:`SimDriver.read <payload.sim.driver.SimDriver.read>`:
joint positions, velocities, efforts and the health flags). In numpy that is about twenty
calls on arrays of three to seventeen numbers. Here each is one C call reading the MuJoCo
data's arrays in place (their addresses are fixed for the data's lifetime) into a fresh
buffer (the time, a field of the data's struct, stays Python's ``float(data.time)``):

* copies and gathers are copies of the same numbers;
* the body-frame velocity ``rot.T @ v`` is numpy's CBLAS ``dgemv`` called as numpy's
  ``matmul`` calls it for the transposed rotation (column-major, as in
  :mod:`payload.trials.foxglove_c`);
* the health tests are the same comparisons (``|force| >= overload``, ``q <= lo``,
  ``q >= hi``; a NaN fails them all, as in numpy).

The fingertip contacts are :class:`~payload.sim.contact.ContactMonitor`'s (compiled in
:mod:`payload.sim.contacts_c`, which reads the contact list where MuJoCo's arena has it).
:func:`compiled_readout` checks the kernel against the numpy read-out on random states
written into the data when it is built, and returns None (the numpy code runs) without a
C compiler or numpy's OpenBLAS, with ``PAYLOAD_NATIVE=0``, or on a single differing bit.
"""

from __future__ import annotations

import ctypes
import itertools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.schema import Health

log = logging.getLogger(__name__)

WORLD_LAYOUT = (
    ("astrobee_pos", 3),
    ("astrobee_quat", 4),
    ("astrobee_linear", 3),
    ("astrobee_angular", 3),
    ("ctb_pos", 3),
    ("ctb_quat", 4),
)
"""The world read-out's fields in its buffer, in order (the CTB's only with a CTB)."""

WORLD_SLICES: dict[str, slice] = {
    name: slice(at - size, at)
    for (name, size), at in zip(WORLD_LAYOUT, itertools.accumulate(s for _, s in WORLD_LAYOUT))
}
"""Each field's part of the world read-out's buffer."""

POSE_SIZE = WORLD_SLICES["astrobee_quat"].stop - WORLD_SLICES["astrobee_pos"].start
"""A free joint's ``qpos`` (position, then quaternion): one copy into the buffer, so the
layout keeps each body's position and quaternion side by side."""
if not all(  # a body's position, then its quaternion, as its free joint's qpos has them
    WORLD_SLICES[f"{body}_quat"].start == WORLD_SLICES[f"{body}_pos"].stop
    and WORLD_SLICES[f"{body}_quat"].stop - WORLD_SLICES[f"{body}_pos"].start == POSE_SIZE
    for body in ("astrobee", "ctb")
):
    raise ImportError("readout_c.WORLD_LAYOUT: each pose must be a position then a quaternion")

PAYLOAD_LAYOUT: tuple[tuple[str, int | None], ...] = (
    ("q", None),
    ("deploy", 1),
    ("dq", None),
    ("effort", None),
)
"""The payload read-out's fields in its buffer, in order (None: one per manipulation
joint)."""


def payload_slices(n: int) -> dict[str, slice]:
    """Each field's part of the payload read-out's buffer, for ``n`` manipulation joints."""
    out: dict[str, slice] = {}
    at = 0
    for name, size in PAYLOAD_LAYOUT:
        width = n if size is None else size
        out[name] = slice(at, at + width)
        at += width
    return out


SOURCE = r"""
/* OFF_POS, POSE, OFF_LINEAR, OFF_ANGULAR, OFF_CTB (WORLD_LAYOUT), PAYLOAD_OFFSETS (a field
   per PAYLOAD_LAYOUT field, in its order), and OVERLOAD and LIMIT (the Health flags) are
   defined by the loader */
typedef struct {
    dgemv_fn gemv;
    const double *qpos, *qvel, *xmat, *force;
    int64_t a_qpos, a_dof, ctb_qpos;           /* Astrobee's and the CTB's (-1: none) */
    int64_t nq, stage;                          /* manipulation joints, stage qpos */
    const int64_t *q_idx, *dof_idx, *effort_idx, *ctrl_idx;
    int64_t nctrl;
    const double *overload, *lo, *hi;          /* (nctrl), (nq), (nq) */
    PAYLOAD_OFFSETS                             /* PAYLOAD_LAYOUT's: off_q, off_deploy, ... */
} readout;

/* WORLD_LAYOUT: pose, body linear and angular velocity[, the CTB's pose] */
void payload_world(const readout *r, double *out)
{
    const double *q = r->qpos + r->a_qpos, *v = r->qvel + r->a_dof;
    for (int i = 0; i < POSE; i++) out[OFF_POS + i] = q[i];
    r->gemv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, r->xmat, 3, v, 1, 0.0, out + OFF_LINEAR, 1);
    for (int i = 0; i < 3; i++) out[OFF_ANGULAR + i] = v[3 + i];
    if (r->ctb_qpos >= 0)
        for (int i = 0; i < POSE; i++) out[OFF_CTB + i] = r->qpos[r->ctb_qpos + i];
}

/* PAYLOAD_LAYOUT: q, deploy, dq, effort; returns the health bits */
int payload_read(const readout *r, double *out)
{
    int64_t n = r->nq;
    int health = 0;
    for (int64_t i = 0; i < r->nctrl; i++)
        if (fabs(r->force[r->ctrl_idx[i]]) >= r->overload[i]) health |= OVERLOAD;
    for (int64_t i = 0; i < n; i++) {
        double q = r->qpos[r->q_idx[i]];
        out[r->off_q + i] = q;
        if (q <= r->lo[i] || q >= r->hi[i]) health |= LIMIT;
    }
    out[r->off_deploy] = r->qpos[r->stage];
    for (int64_t i = 0; i < n; i++) out[r->off_dq + i] = r->qvel[r->dof_idx[i]];
    for (int64_t i = 0; i < n; i++) out[r->off_effort + i] = r->force[r->effort_idx[i]];
    return health;
}
"""


class _Readout(ctypes.Structure):
    _fields_ = [
        ("gemv", ctypes.c_void_p),
        *[(f, ctypes.c_void_p) for f in ("qpos", "qvel", "xmat", "force")],
        *[(f, ctypes.c_int64) for f in ("a_qpos", "a_dof", "ctb_qpos", "nq", "stage")],
        *[(f, ctypes.c_void_p) for f in ("q_idx", "dof_idx", "effort_idx", "ctrl_idx")],
        ("nctrl", ctypes.c_int64),
        *[(f, ctypes.c_void_p) for f in ("overload", "lo", "hi")],
        *[(f"off_{name}", ctypes.c_int64) for name, _ in PAYLOAD_LAYOUT],
    ]


class CompiledReadout:
    """The world and payload read-outs of one MuJoCo data (see the module).

    Args:
        lib: The kernel's library.
        gemv: The address of numpy's CBLAS ``dgemv``.
        data: The MuJoCo data (read in place).
        body: Astrobee's body id (its rotation ``xmat[body]``).
        a_qpos, a_dof: Astrobee's free joint's first ``qpos`` and ``qvel`` index.
        ctb_qpos: The CTB's free joint's first ``qpos`` index (-1: no CTB).
        q_idx, dof_idx: The manipulation joints' ``qpos`` and ``qvel`` indices (N,).
        stage: The stage's ``qpos`` index.
        effort_idx: The manipulation actuators (N,) (their ``actuator_force`` is the effort).
        ctrl_idx: Every payload actuator (the overload test), with ``overload`` its bound.
        lo, hi: The manipulation joints' at-limit thresholds (N,).
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        gemv: int,
        data: Any,
        body: int,
        a_qpos: int,
        a_dof: int,
        ctb_qpos: int,
        q_idx: np.ndarray,
        dof_idx: np.ndarray,
        stage: int,
        effort_idx: np.ndarray,
        ctrl_idx: np.ndarray,
        overload: Any,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> None:
        self.data = data
        for name in ("qpos", "qvel", "xmat", "actuator_force"):
            a = getattr(data, name)
            if not (a.dtype == np.float64 and a.flags.c_contiguous):
                raise ValueError(f"{name} is not a C-contiguous float64 array")
        ints = [np.ascontiguousarray(x, dtype=np.int64) for x in (q_idx, dof_idx, effort_idx,
                                                                    ctrl_idx)]  # fmt: skip
        n = len(ints[0])
        if not (len(ints[1]) == len(ints[2]) == len(lo) == len(hi) == n):
            raise ValueError("the joint, velocity, effort and limit lists differ in length")
        bounds = np.broadcast_to(np.asarray(overload, dtype=np.float64), ints[3].shape)
        reals = [np.ascontiguousarray(x, dtype=np.float64) for x in (bounds, lo, hi)]
        self._keep = (ints, reals)
        self.payload = payload_slices(n)
        """Each field's part of :meth:`read`'s buffer (:data:`PAYLOAD_LAYOUT`)."""
        self._ctx = _Readout(
            gemv, data.qpos.ctypes.data, data.qvel.ctypes.data,
            data.xmat[body].ctypes.data, data.actuator_force.ctypes.data,
            a_qpos, a_dof, ctb_qpos, n, stage,
            *[x.ctypes.data for x in ints], len(ints[3]),
            *[x.ctypes.data for x in reals],
            *[self.payload[name].start for name, _ in PAYLOAD_LAYOUT],
        )  # fmt: skip
        self.n = n
        self.payload_size = self.payload[PAYLOAD_LAYOUT[-1][0]].stop
        last = "ctb_quat" if ctb_qpos >= 0 else "astrobee_angular"
        self.world_size = WORLD_SLICES[last].stop
        self._world = lib.payload_world
        self._world.restype = None
        self._world.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._read = lib.payload_read
        self._read.restype = ctypes.c_int
        self._read.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._ptr = ctypes.addressof(self._ctx)

    def world(self) -> np.ndarray:
        """The world read-out, a fresh array laid out as :data:`WORLD_LAYOUT`."""
        out = np.empty(self.world_size)
        self._world(self._ptr, out.ctypes.data)
        return out

    def read(self) -> tuple[np.ndarray, int]:
        """(The payload read-out, a fresh array laid out as :attr:`payload`; the health,
        as :class:`~payload.schema.Health`'s ``OVERLOAD`` and ``LIMIT`` bits)."""
        out = np.empty(self.payload_size)
        return out, self._read(self._ptr, out.ctypes.data)


@native.reported("read-out")
def compiled_readout(
    make: Callable[[ctypes.CDLL, int], CompiledReadout],
    check: Callable[[CompiledReadout, int], bool],
) -> CompiledReadout | None:
    """``make(lib, gemv)``'s read-out, or None to run the numpy read-outs: no compiler,
    no numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or ``check(kernel, probes)``
    (the caller's comparison with its numpy read-outs on ``probes`` random states: 200, or
    the first 20 once a read-out of the same shape passed, here or in an earlier process)
    False."""
    at = {name: part.start for name, part in WORLD_SLICES.items()}
    prelude = (
        f"#define OFF_POS {at['astrobee_pos']}\n#define POSE {POSE_SIZE}\n"
        f"#define OFF_LINEAR {at['astrobee_linear']}\n"
        f"#define OFF_ANGULAR {at['astrobee_angular']}\n"
        f"#define OFF_CTB {at['ctb_pos']}\n"
        f"#define OVERLOAD {int(Health.OVERLOAD)}\n#define LIMIT {int(Health.LIMIT)}\n"
        "#define PAYLOAD_OFFSETS "
        + " ".join(f"int64_t off_{name};" for name, _ in PAYLOAD_LAYOUT)
        + "\n"
    )
    return native.checked_blas_kernel(
        "readout", SOURCE, "read-out", log, make, check, _shape, 200, native.NUMPY_DGEMV,
        prelude=prelude,
    )  # fmt: skip


def _shape(kernel: CompiledReadout) -> tuple[int, int]:
    """What shapes the read-out's code paths (its check stamp's key)."""
    return (kernel.n, kernel.world_size)


__all__ = [
    "PAYLOAD_LAYOUT",
    "POSE_SIZE",
    "SOURCE",
    "WORLD_LAYOUT",
    "WORLD_SLICES",
    "CompiledReadout",
    "compiled_readout",
    "payload_slices",
]
