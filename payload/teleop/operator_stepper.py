"""The compiled flight step bound to one synthetic operator (:class:`CompiledAct`).

The library (:data:`payload.teleop.operator_c.SOURCE`, built and checked by
:func:`payload.teleop.operator_c.compiled_act`) takes its constants, state, inputs and
outputs in arrays laid out by :mod:`payload.teleop.operator_layout`;
:meth:`CompiledAct.stepper` fills them from an operator and its view, calls the step, and
writes the step's state back into the operator as its Python does.
"""

from __future__ import annotations

import ctypes
import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from payload.teleop import handmodel_c
from payload.teleop.hands import JOINTS_SHAPE
from payload.teleop.operator_layout import (
    AIMLESS_M,
    ARGS,
    ARRIVAL_M,
    CONFIG,
    DROPOUT_S,
    FLIGHT_PHASES,
    HANDS,
    INPUT,
    OUTPUT,
    PINCH_LAG_S,
    REACH_MARGIN_M,
    REST_S,
    REST_SPEED,
    STATE,
    STOP_SHORT_M,
    TURN_ABOVE_RAD,
    _offsets,
)


class CompiledAct:
    """The flight step, compiled (:data:`~payload.teleop.operator_c.SOURCE`), bound to
    operators by :meth:`stepper`.

    Args:
        lib: The kernel's library.
        ddot, gemv: The addresses of numpy's CBLAS functions.
        tables: The hand model's tables by name
            (:data:`payload.teleop.handmodel.MODEL_TABLES`).
    """

    def __init__(self, lib: ctypes.CDLL, ddot: int, gemv: int, tables: Any) -> None:
        init = lib.payload_operator_init
        init.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        init(ddot, gemv)
        fn = lib.payload_operator_act
        fn.restype = ctypes.c_int
        fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._fn = fn
        self._hand = handmodel_c.CompiledHeldHand(lib, tables)  # its tables' struct

    def stepper(self, operator: Any) -> Callable[..., Any] | None:
        """``step(t, dt, seen, grid)`` of ``operator`` (a :class:`SyntheticOperator
        <payload.teleop.operator.SyntheticOperator>`) after its perception, its state
        updated as its Python (``_act_numpy``) updates it: ``(left, right)``, each hand's
        joints (a (25, 3) array of its own, rounded to ``grid`` unless it is None) or None
        for a lost hand; or None, nothing changed and nothing drawn, where the Python is to
        run (another phase, a view, wrists, phases or state of other types, a held hand
        numpy draws). None for an operator the kernel does not take: a route not of (n, 3)
        floats, hands of another size than its traits', or settings the Python refuses
        (a wrist lag that is not positive, no top speed, a negative braking, a negative
        noise)."""
        plan, traits, rng = operator.plan, operator.traits, operator.rng
        route = plan.route
        if not (
            type(route) is np.ndarray
            and route.dtype == np.float64
            and route.ndim == 2
            and route.shape[1] == 3
            and len(route) >= 1
        ):
            return None
        base = plan.base
        if not (traits.wrist_lag > 0.0 and base.max_speed != 0.0 and plan.brake_accel >= 0.0):
            return None  # the Python divides by zero, or takes a negative square root
        if math.copysign(1.0, traits.noise) < 0.0:
            return None  # numpy's normal refuses a negative scale
        models = (operator.models["left"], operator.models["right"])
        if any(m.size != traits.hand_size for m in models):
            return None
        route = np.array(route)  # read at every step: a copy of the plan's
        left = np.array(operator._route_left, dtype=np.float64)
        to_operator = operator._to_operator
        if not (to_operator.flags.f_contiguous and not to_operator.flags.c_contiguous):
            return None  # numpy's matmul passes this layout's transpose as column-major
        yaw = np.ascontiguousarray(to_operator.T)
        centre, half = (np.ascontiguousarray(a, dtype=np.float64) for a in operator._posture)
        constants = {
            "waypoint_radius": plan.waypoint_radius,
            "brake_accel": plan.brake_accel,
            "max_speed": base.max_speed,
            "speed_pref": traits.speed_pref,
            "corner_speed_squared": plan.corner_speed**2,  # Python's power, not the C's
            "sphere_radius": base.sphere_radius,
            "full_speed_offset": base.full_speed_offset,
            "wrist_lag": traits.wrist_lag,
            "turn_above": TURN_ABOVE_RAD,
            "stop_short": STOP_SHORT_M,
            "arrival": ARRIVAL_M,
            "aimless": AIMLESS_M,
            "reach_margin": REACH_MARGIN_M,
            "rest_speed": REST_SPEED,
            "rest_time": REST_S,
            "pinch_lag": PINCH_LAG_S,
            "dropout_low": DROPOUT_S[0],
            "dropout_range": DROPOUT_S[1] - DROPOUT_S[0],  # numpy's uniform: low + range u
        }
        cfg = np.array([constants[name] for name in CONFIG], dtype=np.float64)
        hand = {
            "hand_size": float(traits.hand_size),
            "tremor_amp": traits.tremor_amp,
            "tremor_freq": traits.tremor_freq,
            "noise": traits.noise,
            "dropout_rate": traits.dropout_rate,
            "curl": handmodel_c.DEFAULT_CURL,
        }
        scalars = np.array([hand.get(name, 0.0) for name in HANDS], dtype=np.float64)
        t_at, dt_at, grid_at = (HANDS.index(name) for name in ("t", "dt", "grid"))
        inp = np.zeros(sum(size for _, size in INPUT))
        at = _offsets(INPUT)
        pos, rot, vel, wl_in, wr_in, ph_l, ph_r = (
            inp[at[name] : at[name] + size] for name, size in INPUT
        )
        rot = rot.reshape(3, 3)
        state = np.zeros(len(STATE))
        out = np.zeros(sum(size for _, size in OUTPUT))
        at = _offsets(OUTPUT)
        new_l, new_r = (out[at[name] : at[name] + 3] for name in ("wrist_left", "wrist_right"))
        hands = out[at["hands"] :].reshape(2, *JOINTS_SHAPE)
        pointers = {
            "cfg": cfg.ctypes.data,
            "route": route.ctypes.data,
            "left": left.ctypes.data,
            "n": len(route),
            "yaw": yaw.ctypes.data,
            "centre": centre.ctypes.data,
            "half": half.ctypes.data,
            "in": inp.ctypes.data,
            "state": state.ctypes.data,
            "tables": self._hand.tables_address,
            "bitgen": rng.bit_generator.ctypes.bit_generator.value,
            "out": out.ctypes.data,
        }
        args = np.array([pointers[name] for name in ARGS], dtype=np.int64)
        call = functools.partial(self._fn, args.ctypes.data, scalars.ctypes.data)
        codes = {name: float(i) for i, name in enumerate(FLIGHT_PHASES)}
        n = len(route)
        synced: list[Any] = [None]  # the attributes as the kernel last left them

        def load(op: Any) -> bool:
            """The operator's attributes into the kernel's state; False for values the
            kernel does not take."""
            waypoint, stopped, grip = op.waypoint, op.stopped_since, op.grip_aperture
            drop = op._dropout_until
            if type(waypoint) is not int or not 0 <= waypoint < n:
                return False
            for value in (stopped, grip):  # None is the kernel's NaN
                if value is not None and not (type(value) is float and value == value):
                    return False
            if not all(type(drop[s]) is float for s in ("left", "right")):
                return False
            values = {
                "phase": codes[op.phase],
                "waypoint": waypoint,
                "stopped_since": math.nan if stopped is None else stopped,
                "finished": 0.0,
                "aperture": op.aperture,
                "grip_aperture": math.nan if grip is None else grip,
                "dropout_left": drop["left"],
                "dropout_right": drop["right"],
            }
            state[:] = [values[name] for name in STATE]
            return True

        def step(t: float, dt: float, seen: Any, grid: float | None) -> tuple[Any, Any] | None:
            op = operator
            if op.plan is not plan or op.traits is not traits or op.rng is not rng:
                return None
            if op.phase not in codes or (
                grid is not None and not (type(grid) is float and grid > 0.0)
            ):
                return None
            m, ph, wrist = op.models, op.phases, op.wrist
            if m["left"] is not models[0] or m["right"] is not models[1]:
                return None
            p, r, v = seen.astrobee_pos, seen.astrobee_rot, seen.astrobee_vel
            wl, wr, pl, pr = wrist["left"], wrist["right"], ph["left"], ph["right"]
            if not (_real(p, (3,)) and _real(r, (3, 3)) and _real(v, (3,))):
                return None
            if not all(map(handmodel_c.takes_vector, (wl, wr, pl, pr))):
                return None  # the held hand's Python would go to numpy
            drop = op._dropout_until
            now = (op.phase, op.waypoint, op.stopped_since, op.aperture, op.grip_aperture,
                   drop["left"], drop["right"])  # fmt: skip
            if now != synced[0] and not load(op):
                return None
            pos[:], rot[:], vel[:], wl_in[:], wr_in[:], ph_l[:], ph_r[:] = p, r, v, wl, wr, pl, pr
            scalars[t_at], scalars[dt_at], scalars[grid_at] = t, dt, 0.0 if grid is None else grid
            tracked = call()
            if tracked < 0:
                return None
            phase, waypoint, stopped, finished, aperture, _, dl, dr = state.tolist()  # STATE
            op.phase = FLIGHT_PHASES[int(phase)]
            op.waypoint = int(waypoint)
            op.stopped_since = None if stopped != stopped else stopped
            if finished:
                op.finished = True
            op.aperture = aperture
            drop["left"], drop["right"] = dl, dr
            wrist["left"], wrist["right"] = new_l.copy(), new_r.copy()  # new arrays, as numpy
            synced[0] = (op.phase, op.waypoint, op.stopped_since, aperture, op.grip_aperture,
                         dl, dr)  # fmt: skip
            return (
                hands[0].copy() if tracked & 1 else None,
                hands[1].copy() if tracked & 2 else None,
            )

        keep = (cfg, route, left, yaw, centre, half, scalars, inp, state, out, args)
        step.keep = keep  # type: ignore[attr-defined]
        return step


def _real(a: Any, shape: tuple[int, ...]) -> bool:
    """A float64 numpy array of ``shape`` (copied into the kernel's input)."""
    return type(a) is np.ndarray and a.dtype == np.float64 and a.shape == shape


__all__ = ["CompiledAct"]
