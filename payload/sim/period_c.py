"""One control period's work before the physics, as two compiled calls, with numpy's bits.

:meth:`SimDriver.step <payload.sim.driver.SimDriver.step>` does, each control period,
before MuJoCo's 20 steps: with the vehicle controller on, Astrobee's body twist
(``rot.T @ v``), the controller's step (:class:`~payload.sim.vehicle_c.CompiledControl`)
and, when that allocated, Astrobee's applied forces cleared and the nozzle thrusts
applied (:class:`~payload.sim.vehicle_c.CompiledThrusts`); then always the servo targets'
slew toward the goals (``np.clip`` of the step), the actuators' controls and the watch on
the forces applied to the CTB. In Python that is about a dozen calls and their objects;
here it is two C calls (:class:`CompiledPeriod`) that call the same compiled kernels
through their addresses, with their own states, and do the rest as numpy does:

* the body twist is numpy's CBLAS ``dgemv`` called as ``matmul`` calls it for the
  transposed rotation (column-major, as in :mod:`payload.sim.readout_c`);
* the slew is ``np.clip``'s maximum then minimum, a NaN kept (numpy's ``clip`` loop),
  then the same sum;
* the watch is ``ndarray.max`` of the absolute values (a NaN wins) and Python's
  ``max`` of two floats (the first unless the second is greater).

A control step that did not allocate (a zero or non-finite wrench, a wrench outside the
polytope: the numpy code finishes those) returns its code, and the driver finishes the
vehicle's part in Python before the servos' call. :func:`compiled_period` checks the
calls against the driver's Python on random states when built; without the controller's
and the thrusts' kernels, a compiler, or with ``PAYLOAD_NATIVE=0`` the Python runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.sim.vehicle_c import ENTRY_TYPES

log = logging.getLogger(__name__)

SOURCE = (
    ENTRY_TYPES
    + r"""

typedef struct {
    control_fn control_step; void *control; double *in;   /* the controller's kernel */
    dgemv_fn gemv;
    const double *xmat, *qvel;            /* Astrobee's rotation (9), free joint's qvel (6) */
    double *xfrc, *qfrc_dof;              /* Astrobee's xfrc_applied (6), qfrc_applied (6) */
    thrusts_fn thrusts; void *apply_ft; const void *m; void *d;
    const double *xipos, *dirs, *pos, *thrust; int64_t body; double *qfrc;
    int64_t n; const double *goal; double *target, *step;   /* the servos (n) each */
    double *ctrl; const int64_t *ctrl_idx;
    const double *ctb_xfrc, *ctb_qfrc; double *ctb_max;         /* NULL: no CTB */
} period;

/* the vehicle: returns the control step's code (0: allocated, thrusts applied) */
int payload_period_vehicle(const period *p, double dt)
{
    p->gemv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, p->xmat, 3, p->qvel, 1, 0.0, p->in + 6, 1);
    for (int i = 0; i < 3; i++) p->in[9 + i] = p->qvel[3 + i];
    int code = p->control_step(p->control, dt);
    if (code != 0) return code;
    for (int i = 0; i < 6; i++) { p->xfrc[i] = 0.0; p->qfrc_dof[i] = 0.0; }
    p->thrusts((void *)p->gemv, p->apply_ft, p->m, p->d, p->xmat, p->xipos, p->dirs, p->pos,
               p->thrust, (int)p->body, p->qfrc);
    return 0;
}

/* numpy's clip loop for doubles: max then min, a NaN kept */
static double np_clip(double x, double lo, double hi)
{
    double y = isnan(x) ? x : (x > lo ? x : lo);
    return isnan(y) ? y : (y < hi ? y : hi);
}

/* ndarray.max of |x| (6): a NaN wins */
static double max_abs6(const double *x)
{
    double m = fabs(x[0]);
    for (int i = 1; i < 6; i++) {
        double v = fabs(x[i]);
        m = (m >= v || isnan(m)) ? m : v;
    }
    return m;
}

/* Python's max(a, b) of floats */
static double py_max2(double a, double b) { return (b > a) ? b : a; }

/* the servos: targets slewed toward the goals, the controls, the CTB watch */
void payload_period_servos(const period *p)
{
    for (int64_t i = 0; i < p->n; i++) {
        p->target[i] = p->target[i] + np_clip(p->goal[i] - p->target[i], -p->step[i], p->step[i]);
        p->ctrl[p->ctrl_idx[i]] = p->target[i];
    }
    if (p->ctb_xfrc)
        *p->ctb_max = py_max2(*p->ctb_max, py_max2(max_abs6(p->ctb_xfrc), max_abs6(p->ctb_qfrc)));
}
"""
)


class _Period(ctypes.Structure):
    _fields_ = [
        *[(f, ctypes.c_void_p) for f in ("control_step", "control", "inputs", "gemv")],
        *[(f, ctypes.c_void_p) for f in ("xmat", "qvel", "xfrc", "qfrc_dof")],
        *[(f, ctypes.c_void_p) for f in ("thrusts", "apply_ft", "m", "d")],
        *[(f, ctypes.c_void_p) for f in ("xipos", "dirs", "pos", "thrust")],
        ("body", ctypes.c_int64),
        ("qfrc", ctypes.c_void_p),
        ("n", ctypes.c_int64),
        *[(f, ctypes.c_void_p) for f in ("goal", "target", "step")],
        *[(f, ctypes.c_void_p) for f in ("ctrl", "ctrl_idx", "ctb_xfrc", "ctb_qfrc", "ctb_max")],
    ]


class CompiledPeriod:
    """The two calls of one control period (see the module) for one driver's data.

    Args:
        lib: The kernel's library.
        gemv: The address of numpy's CBLAS ``dgemv``.
        control: The controller's kernel (:class:`~payload.sim.vehicle_c.CompiledControl`).
        thrusts: The thrusts' kernel (:class:`~payload.sim.vehicle_c.CompiledThrusts`), for
            the same data.
        data: The MuJoCo data (read and written in place).
        body: Astrobee's body id; ``dof``: its free joint's first ``qvel`` index.
        goal, target: The servo goals and targets (N,), the driver's own arrays (in place).
        step: The targets' largest change a period (N,).
        ctrl_idx: The actuators of the N servos.
        ctb: The CTB's body id and free joint's first ``qvel`` index, or None.
        ctb_max: The CTB watch's largest force so far, a (1,) array (in place).
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        gemv: int,
        control: Any,
        thrusts: Any,
        data: Any,
        body: int,
        dof: int,
        goal: np.ndarray,
        target: np.ndarray,
        step: np.ndarray,
        ctrl_idx: np.ndarray,
        ctb: tuple[int, int] | None,
        ctb_max: np.ndarray,
    ) -> None:
        for name, a in (("goal", goal), ("target", target), ("ctb_max", ctb_max)):
            if not (a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable):
                raise ValueError(f"{name} is not a writeable C-contiguous float64 array")
        for name in ("qvel", "xmat", "xfrc_applied", "qfrc_applied", "ctrl", "xipos"):
            a = getattr(data, name)
            if not (a.dtype == np.float64 and a.flags.c_contiguous):
                raise ValueError(f"{name} is not a C-contiguous float64 array")
        if thrusts.data is not data or ctb_max.shape != (1,):
            raise ValueError("the thrusts' kernel is for other data, or ctb_max is not (1,)")
        if not (len(goal) == len(target) == len(ctrl_idx) == len(step)):
            raise ValueError("the goals, targets and actuators differ in length")
        self.data, self.goal, self.target, self.ctb_max = data, goal, target, ctb_max
        self.has_ctb = ctb is not None
        self.control = control
        idx = np.ascontiguousarray(ctrl_idx, dtype=np.int64)
        step = np.ascontiguousarray(step, dtype=np.float64)
        addr = functools.partial(ctypes.cast, typ=ctypes.c_void_p)
        control_step = control._step.func
        thrust_fn = thrusts._call.func
        d = data
        self._keep = (idx, step, control, thrusts)
        self._ctx = _Period(
            addr(control_step).value, control._handle.value, control._in.ctypes.data, gemv,
            d.xmat[body].ctypes.data, d.qvel[dof:].ctypes.data,
            d.xfrc_applied[body].ctypes.data, d.qfrc_applied[dof:].ctypes.data,
            addr(thrust_fn).value, thrusts.apply_ft, thrusts.model._address, d._address,
            d.xipos[body].ctypes.data, thrusts._dirs.ctypes.data, thrusts._pos.ctypes.data,
            control.searches.thrust.ctypes.data, body, d.qfrc_applied.ctypes.data,
            len(goal), goal.ctypes.data, target.ctypes.data, step.ctypes.data, d.ctrl.ctypes.data,
            idx.ctypes.data,
            d.xfrc_applied[ctb[0]].ctypes.data if ctb is not None else None,
            d.qfrc_applied[ctb[1] :].ctypes.data if ctb is not None else None,
            ctb_max.ctypes.data,
        )  # fmt: skip
        ptr = ctypes.addressof(self._ctx)
        vehicle = lib.payload_period_vehicle
        vehicle.restype = ctypes.c_int
        vehicle.argtypes = [ctypes.c_void_p, ctypes.c_double]
        self._vehicle = functools.partial(vehicle, ptr)
        servos = lib.payload_period_servos
        servos.restype = None
        servos.argtypes = [ctypes.c_void_p]
        self.servos = functools.partial(servos, ptr)
        """The servos' call: slew, controls, CTB watch."""

    def vehicle(self, command: Any, dt: float) -> tuple:
        """The vehicle's call for the twist ``command``: the controller kernel's
        ``step`` result (``(0, thrust, force, torque, scale)``: allocated and the thrusts
        applied; otherwise the code and what the numpy code needs to finish, as
        :meth:`~payload.sim.vehicle_c.CompiledControl.step` gives them)."""
        control = self.control
        return control.step(command, None, None, dt, self._vehicle)


CHECK_STATES = 120
"""Random states of the period's full self-check (:func:`compiled_period`)."""


@native.reported("control period")
def compiled_period(
    make: Callable[[ctypes.CDLL, int], CompiledPeriod],
    check: Callable[[CompiledPeriod, int], bool],
) -> CompiledPeriod | None:
    """``make(lib, gemv)``'s period, or None to run the driver's Python: no compiler, no
    numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or ``check(kernel, probes)`` (the
    driver's comparison with its Python on ``probes`` random states: :data:`CHECK_STATES`,
    or their first tenth once a period of the same shape passed, here or in an earlier
    process) False."""
    return native.checked_blas_kernel(
        "period", SOURCE, "control period", log, make, check, _shape, CHECK_STATES,
        native.NUMPY_DGEMV,
    )  # fmt: skip


def _shape(kernel: CompiledPeriod) -> tuple[int, bool]:
    """What shapes the period's code paths (its check stamp's key): the servos, a CTB."""
    return (len(kernel.goal), kernel.has_ctb)


__all__ = ["CHECK_STATES", "SOURCE", "CompiledPeriod", "compiled_period"]
