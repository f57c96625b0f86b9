"""The vehicle library's entry points bound to a controller and to a driver's data: the
controller's step (:class:`CompiledControl`) and the thrusts into MuJoCo
(:class:`CompiledThrusts`).

The library is :data:`payload.sim.vehicle_c.CONTROL_SOURCE` (after the allocation's
searches); :func:`payload.sim.vehicle_c.compiled_control` and
:func:`payload.sim.vehicle_c.compiled_thrusts` build it, bind it with these classes and
check the result against the numpy code.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.sim.allocation_c import CompiledSearches
from payload.sim.errors import SimError


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

    def step(
        self,
        command: Any,
        linear: np.ndarray | None,
        angular: np.ndarray | None,
        dt: float,
        call: Callable[[float], int] | None = None,
    ) -> tuple:
        """One control step (the arguments of ``VehicleController.update``), the profile's
        state updated in place: ``(0, thrust, force, torque, scale)`` allocated; ``(1,)``
        a zero wrench; ``(2, w, lam, facet)`` outside the polytope and ``(3, w, lam,
        facet)`` without a basic solution (the numpy code finishes those); ``(4, w)`` a
        non-finite wrench ``w`` (6,).

        ``call(dt)``, if given, makes the step instead of the kernel's own call: it writes
        the measured twist into the inputs itself (``linear`` and ``angular`` unused) and
        returns the step's code (:class:`~payload.sim.period_c.CompiledPeriod`)."""
        profile = self.controller.profile
        if profile.velocity is not self._bound[0] or profile.acceleration is not self._bound[1]:
            self._bind(profile)
        inp, res = self._in, self._res
        with self.searches._lock:
            inp[0:3] = command.linear
            inp[3:6] = command.angular
            if call is None:
                inp[6:9] = linear
                inp[9:12] = angular
                code = self._step(dt)
            else:
                code = call(dt)
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
        self.apply_ft = apply_ft
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


__all__ = ["CompiledControl", "CompiledThrusts"]
