"""The synthetic operator's flight steps as one compiled call, with numpy's bits.

From the end of the acquisition to the trial's end (most of a trial's steps) the synthetic
operator (:class:`payload.teleop.operator.SyntheticOperator`) does the same thing every
control step (:meth:`~payload.teleop.operator.SyntheticOperator.act`): it advances along
the route, works out the speed it wants (its preference, the distance it needs to stop,
the corner ahead), turns or translates, offsets both wrists from their working posture to
fly the vehicle that way, brakes and waits at the end; both wrists and the pinch follow
that intent through the arm's lags; then each hand is lost for a moment or drawn: the
tracker's noise, the hand model at the trembling wrist
(:func:`payload.teleop.handmodel.held_hand`). In Python that is about sixty calls a step
on 3-vectors, floats and numpy's generator; here it is one C call doing the same
operations in the same order:

* norms through numpy's own CBLAS ``ddot`` (:func:`payload.vecmath.norm`), the
  operator-frame rotation through its ``dgemv`` as numpy's ``matmul`` passes the
  transposed yaw matrix (column-major);
* ``sqrt``, ``atan2``, ``exp``, ``sin`` and ``fmod`` of the C library Python's ``math``
  calls (the corner speed's square is Python's, passed in), Python's ``%`` (``pymod``) and
  its ``min``/``max`` tie rules (the first argument unless a later one is strictly
  smaller/greater; a NaN never is), Python's truth of ``stopped_since`` (None or zero is
  false);
* the dropouts and the noise drawn by numpy's own generator functions
  (``random_uniform``, ``random_normal`` of ``numpy/random/lib/libnpyrandom.a``, linked in,
  and the bit generator's ``next_double``) on the operator's own generator, in the order
  numpy draws them;
* the held hand by the C of :mod:`payload.teleop.handmodel_c`, compiled in, and, for a
  headset that reports on a grid, :func:`payload.teleop.hands.round_to_grid` (C's
  ``rint``, numpy's for doubles).

The calibration and the acquisition (their own random draws among them) stay in Python.
A step whose held hand the compiled hand would leave to numpy (a wrist coordinate that is
zero) goes to the Python before anything is drawn. Checked against the Python when built,
on random routes, traits and views in every phase of the flight, hands and generator
states compared to the bit; without a compiler, numpy's OpenBLAS or its ``libnpyrandom``,
or with ``PAYLOAD_NATIVE=0`` the Python runs.
"""

from __future__ import annotations

import ctypes
import functools
import itertools
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from payload import native
from payload.teleop import handmodel_c
from payload.teleop.handmodel import MODEL_TABLES, held_hand_kernel
from payload.teleop.hands import JOINTS_SHAPE

log = logging.getLogger(__name__)

FLIGHT_PHASES: tuple[str, ...] = ("translation", "turn", "arrival", "braking")
"""The operator's phases the kernel steps (its phase codes, in order)."""

STOP_SHORT_M = 0.3
"""The operator brakes to stop this far short of the route's end [m]."""
ARRIVAL_M = 0.45
"""Within this of the route's end (along it) the operator has arrived [m]."""
TURN_ABOVE_RAD = math.radians(12)
"""A heading error above this and the operator turns rather than translates [rad]."""
AIMLESS_M = 1e-6
"""A waypoint nearer than this gives the operator no direction to push [m]."""
REACH_MARGIN_M = 0.01
"""How far beyond the base channel's sphere the operator's wrist reaches at rest [m]."""
REST_SPEED = 0.005
"""The vehicle counts as at rest below this speed [m/s]."""
REST_S = 2.0
"""At rest this long at the end, the operator is done [s]."""
PINCH_LAG_S = 0.15
"""The time constant of the operator's pinch following its intent [s]."""
DROPOUT_S: tuple[float, float] = (0.03, 0.08)
"""How long a hand the tracker loses stays lost: uniform between these [s]."""

CONFIG: tuple[str, ...] = (
    "waypoint_radius",
    "brake_accel",
    "max_speed",
    "speed_pref",
    "corner_speed_squared",
    "sphere_radius",
    "full_speed_offset",
    "wrist_lag",
    "turn_above",
    "stop_short",
    "arrival",
    "aimless",
    "reach_margin",
    "rest_speed",
    "rest_time",
    "pinch_lag",
    "dropout_low",
    "dropout_range",
)
"""The kernel's constants (``cfg`` of :data:`SOURCE`, in this order): the plan's, the base
channel's, the traits' and this module's (numpy's ``uniform`` of :data:`DROPOUT_S` as its
low end and range, ``high - low``)."""

STATE: tuple[str, ...] = (
    "phase",
    "waypoint",
    "stopped_since",
    "finished",
    "aperture",
    "grip_aperture",
    "dropout_left",
    "dropout_right",
)
"""The operator's state the kernel reads and writes (``state`` of :data:`SOURCE`): the
phase's code, the waypoint, ``stopped_since`` and ``grip_aperture`` (NaN: None), whether
it finished at this step, the aperture, and until when each hand is lost."""

HANDS: tuple[str, ...] = (
    "t",
    "dt",
    "hand_size",
    "tremor_amp",
    "tremor_freq",
    "noise",
    "dropout_rate",
    "curl",
    "grid",
)
"""The step's scalars (``s`` of :data:`SOURCE`, in this order): its time and period, the
traits the hands are drawn with, the hand model's curl and the grid the headset reports
the joints on (0: none)."""

INPUT: tuple[tuple[str, int], ...] = (
    ("pos", 3),
    ("rot", 9),
    ("vel", 3),
    ("wrist_left", 3),
    ("wrist_right", 3),
    ("phases_left", 3),
    ("phases_right", 3),
)
"""The step's arrays (``in`` of :data:`SOURCE`, in this order, with their sizes): what the
operator sees (position, rotation row-major, velocity), its wrists and its tremor's
phases."""

OUTPUT: tuple[tuple[str, int], ...] = (
    ("wrist_left", 3),
    ("wrist_right", 3),
    ("hands", 2 * math.prod(JOINTS_SHAPE)),
)
"""What the step writes (``out`` of :data:`SOURCE`, in this order, with their sizes): the
wrists after the lag and both hands' joints (left then right)."""

ARGS: tuple[str, ...] = (
    "cfg",
    "route",
    "left",
    "n",
    "yaw",
    "centre",
    "half",
    "in",
    "state",
    "tables",
    "bitgen",
    "out",
)
"""The step's pointers, and the route's length ``n`` (``a`` of :data:`SOURCE`, in this
order)."""


def _offsets(parts: tuple[tuple[str, int], ...]) -> dict[str, int]:
    """Each part's place in its array (the parts one after the other)."""
    return dict(zip((name for name, _ in parts), itertools.accumulate(
        (size for _, size in parts), initial=0)))  # fmt: skip


def _layout() -> str:
    """The C's names for the places in its arrays, from the tuples above (each fact once):
    ``PH_*`` the phase codes, ``CFG_*``, ``ST_*``, ``H_*`` and ``ARG_*`` the indices of
    :data:`CONFIG`, :data:`STATE`, :data:`HANDS` and :data:`ARGS`, ``IN_*`` and ``OUT_*``
    the offsets of :data:`INPUT` and :data:`OUTPUT`."""
    names = [
        *(f"PH_{name.upper()} = {i}" for i, name in enumerate(FLIGHT_PHASES)),
        *(f"CFG_{name.upper()} = {i}" for i, name in enumerate(CONFIG)),
        *(f"ST_{name.upper()} = {i}" for i, name in enumerate(STATE)),
        *(f"H_{name.upper()} = {i}" for i, name in enumerate(HANDS)),
        *(f"ARG_{name.upper()} = {i}" for i, name in enumerate(ARGS)),
        *(f"IN_{name.upper()} = {i}" for name, i in _offsets(INPUT).items()),
        *(f"OUT_{name.upper()} = {i}" for name, i in _offsets(OUTPUT).items()),
    ]
    return "enum {\n" + "".join(f"    {n},\n" for n in names) + "};\n"


SOURCE = r"""
#include "numpy/random/bitgen.h"

double random_normal(bitgen_t *bitgen_state, double loc, double scale);
double random_uniform(bitgen_t *bitgen_state, double lower, double range);

static ddot_fn dot;
static dgemv_fn mv;
void payload_operator_init(void *ddot, void *gemv) { dot = (ddot_fn)ddot; mv = (dgemv_fn)gemv; }

static double pymax0(double x) { return (x > 0.0) ? x : 0.0; }  /* max(0.0, x) */

/* the places in the arrays (PH_*, CFG_*, ST_*, H_*, ARG_*, IN_*, OUT_*): _layout() */

/* SyntheticOperator._act_numpy in a flight phase: _task_intent, the arm's lags, then each
   hand (lost, or drawn: noise, held hand, the headset's grid). a: the pointers and the
   route's length (ARGS): cfg (CONFIG), route (n, 3), left (n, the route's length from each
   waypoint), yaw (yaw_matrix(heading0), row-major; the operator frame's rotation is its
   transpose), centre, half (the working posture), in (INPUT), state (STATE, updated), the
   held hand's tables, the bit generator, out (OUTPUT: the new wrists, then the hands'
   joints). s: HANDS. Returns -1, nothing written and nothing drawn, for a step whose
   held hand numpy draws; else 1 if the left hand is tracked plus 2 if the right one is. */
int payload_operator_act(const int64_t *a, const double *s)
{
    const double *cfg = (const double *)a[ARG_CFG], *route = (const double *)a[ARG_ROUTE];
    const double *left = (const double *)a[ARG_LEFT], *yaw = (const double *)a[ARG_YAW];
    const double *centre = (const double *)a[ARG_CENTRE], *half = (const double *)a[ARG_HALF];
    const double *in = (const double *)a[ARG_IN];
    const double *pos = in + IN_POS, *rot = in + IN_ROT, *vel = in + IN_VEL;
    const double *wrists[2] = {in + IN_WRIST_LEFT, in + IN_WRIST_RIGHT};
    double *state = (double *)a[ARG_STATE], *out = (double *)a[ARG_OUT];
    const int64_t n = a[ARG_N];
    const double t = s[H_T], dt = s[H_DT];
    const double radius = cfg[CFG_WAYPOINT_RADIUS], brake = cfg[CFG_BRAKE_ACCEL];
    const double max_speed = cfg[CFG_MAX_SPEED];
    int phase = (int)state[ST_PHASE];
    int64_t w = (int64_t)state[ST_WAYPOINT];
    double stopped = state[ST_STOPPED_SINCE];
    int finished = 0;
    const double grip = state[ST_GRIP_APERTURE];
    double ap_now = state[ST_APERTURE];
    const double aperture = isnan(grip) ? ap_now : grip;  /* grip_aperture, unless None */
    double d[3];
    for (;;) {  /* advance along the route */
        if (!(w < n - 1)) break;
        for (int k = 0; k < 3; k++) d[k] = route[3 * w + k] - pos[k];
        if (!(sqrt(dot(3, d, 1, d, 1)) < radius)) break;
        w += 1;
    }
    double to_target[3];
    for (int k = 0; k < 3; k++) to_target[k] = route[3 * w + k] - pos[k];
    const double dist = sqrt(dot(3, to_target, 1, to_target, 1));
    const int last = (w == n - 1);
    double offset[3] = {0.0, 0.0, 0.0};
    if (phase == PH_TRANSLATION || phase == PH_TURN) {
        const double remaining = dist + left[w];
        const double stop_speed = sqrt(2 * brake * pymax0(remaining - cfg[CFG_STOP_SHORT]));
        const double corner = last ? max_speed
            : sqrt(cfg[CFG_CORNER_SPEED_SQUARED] + 2 * brake * pymax0(dist - radius));
        double speed = max_speed * cfg[CFG_SPEED_PREF];  /* min(..., stop_speed, corner) */
        if (stop_speed < speed) speed = stop_speed;
        if (corner < speed) speed = corner;
        const double heading = atan2(rot[3], rot[0]);
        const double desired = atan2(to_target[1], to_target[0]);
        const double err = fabs(pymod(desired - heading + M_PI, 2 * M_PI) - M_PI);
        phase = (err > cfg[CFG_TURN_ABOVE]) ? PH_TURN : PH_TRANSLATION;
        if (last && remaining < cfg[CFG_ARRIVAL]) phase = PH_ARRIVAL;
        if (dist > cfg[CFG_AIMLESS] && phase != PH_ARRIVAL) {
            double u[3], direction[3];
            for (int k = 0; k < 3; k++) u[k] = to_target[k] / dist;
            /* yaw.T @ u: the transposed row-major matrix is a column-major one */
            mv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, yaw, 3, u, 1, 0.0, direction, 1);
            const double reach = cfg[CFG_SPHERE_RADIUS] + cfg[CFG_REACH_MARGIN]
                + cfg[CFG_FULL_SPEED_OFFSET] * speed / max_speed;
            for (int k = 0; k < 3; k++) offset[k] = direction[k] * reach;
        }
    }
    if (phase == PH_ARRIVAL || phase == PH_BRAKING) {
        const double speed_now = sqrt(dot(3, vel, 1, vel, 1));
        phase = PH_BRAKING;
        if (speed_now < cfg[CFG_REST_SPEED]) {
            if (isnan(stopped) || stopped == 0.0) stopped = t;  /* None or 0.0: false */
            if (t - stopped > cfg[CFG_REST_TIME]) finished = 1;
        } else {
            stopped = NAN;
        }
    }
    const double kw = 1.0 - exp(-dt / cfg[CFG_WRIST_LAG]);
    double *wl = out + OUT_WRIST_LEFT, *wr = out + OUT_WRIST_RIGHT;
    for (int k = 0; k < 3; k++) {
        const double il = centre[k] + half[k] + offset[k];
        const double ir = centre[k] - half[k] + offset[k];
        wl[k] = wrists[0][k] + kw * (il - wrists[0][k]);
        wr[k] = wrists[1][k] + kw * (ir - wrists[1][k]);
    }
    ap_now += (1.0 - exp(-dt / cfg[CFG_PINCH_LAG])) * (aperture - ap_now);
    const double arg = 2 * M_PI * s[H_TREMOR_FREQ] * t;
    const double *phases[2] = {in + IN_PHASES_LEFT, in + IN_PHASES_RIGHT};
    double trembling[3];  /* the held hand's own refusal, tested before anything is drawn */
    for (int side = 0; side < 2; side++)
        if (!payload_held_wrist(s[H_HAND_SIZE], ap_now, s[H_CURL], side ? wr : wl,
                                s[H_TREMOR_AMP], arg, phases[side], trembling))
            return -1;
    state[ST_PHASE] = (double)phase;
    state[ST_WAYPOINT] = (double)w;
    state[ST_STOPPED_SINCE] = stopped;
    state[ST_FINISHED] = finished ? 1.0 : 0.0;
    state[ST_APERTURE] = ap_now;
    bitgen_t *bitgen = (bitgen_t *)a[ARG_BITGEN];
    int tracked = 0;
    for (int side = 0; side < 2; side++) {
        if (t < state[ST_DROPOUT_LEFT + side]) continue;
        if (bitgen->next_double(bitgen->state) < s[H_DROPOUT_RATE] * dt) {
            state[ST_DROPOUT_LEFT + side] =
                t + random_uniform(bitgen, cfg[CFG_DROPOUT_LOW], cfg[CFG_DROPOUT_RANGE]);
            continue;
        }
        double *joints = out + OUT_HANDS + side * 3 * N_JOINTS;
        for (int i = 0; i < 3 * N_JOINTS; i++) joints[i] = random_normal(bitgen, 0.0, s[H_NOISE]);
        payload_held_hand((const struct tables *)a[ARG_TABLES], s[H_HAND_SIZE], side == 0, ap_now,
                          s[H_CURL], side ? wr : wl, s[H_TREMOR_AMP], arg, phases[side], joints);
        const double grid = s[H_GRID];
        if (grid > 0.0)  /* round_to_grid: numpy's rint of the quotient, times the grid */
            for (int i = 0; i < 3 * N_JOINTS; i++) joints[i] = rint(joints[i] / grid) * grid;
        tracked |= 1 << side;
    }
    return tracked;
}
"""
"""The kernel's C (after :data:`payload.native.BLAS_C`, :data:`handmodel_c.SOURCE` and
:data:`payload.native.PYMOD_C`)."""


def _npyrandom() -> tuple[str, str] | None:
    """numpy's headers' folder and its ``libnpyrandom.a`` (the generator's C functions,
    built for extensions to link), or None when this numpy ships no such library."""
    include = Path(np.get_include())
    lib = Path(np.__file__).parent / "random" / "lib" / "libnpyrandom.a"
    if not (include / "numpy" / "random" / "bitgen.h").is_file() or not lib.is_file():
        return None
    return str(include), str(lib)


class CompiledAct:
    """The flight step, compiled (:data:`SOURCE`), bound to operators by :meth:`stepper`.

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


CHECK_OPERATORS = 6
"""Operators (routes, traits) of the kernel's full self-check."""

CHECK_STEPS = 400
"""Flight steps of each operator in the full self-check (a short check: the first tenth
of them, every operator)."""

CHECK_GRIDS: tuple[float | None, ...] = (None, 1e-5, 3e-4)
"""The headset grids of the self-check's steps, in turn (None: the joints as drawn)."""

RESET_EVERY = 25
"""Every so many steps the self-check puts both operators back in flight (translation or
turn, at a random waypoint): a flight ends in braking for good."""


@functools.cache
@native.reported("operator")
def compiled_act(
    factory: Callable[[int], tuple[Any, Any]],
    view: Callable[[Any, np.random.Generator, int, float], Any],
) -> CompiledAct | None:
    """The process's compiled flight step, or None to run the Python (no compiler, no
    numpy OpenBLAS or ``libnpyrandom``, ``PAYLOAD_NATIVE=0``, a failed build, or a
    self-check that differs in a single bit): ``factory(k)`` makes two like operators in
    flight (random route, traits and state, seeded by ``k``), ``view(operator, rng, i,
    t)`` a random view of the vehicle along its route at step ``i`` (at rest for
    stretches); the kernel steps one of each pair and the Python the other
    (``_act_numpy``), on the same views, and every hand, wrist, aperture, state value and
    the generators' states must agree to the bit (:data:`CHECK_OPERATORS` of
    :data:`CHECK_STEPS` steps, or their first tenth once a full check passed)."""
    if held_hand_kernel() is None:
        log.info("operator: numpy (the held hand is numpy's)")
        return None
    npy = _npyrandom()
    if npy is None:
        log.info("operator: numpy (this numpy has no libnpyrandom)")
        return None
    loaded = native.load_blas_kernel(
        "operator_act", handmodel_c.SOURCE + native.PYMOD_C + SOURCE, "the operator's kernel", log,
        native.NUMPY_DDOT, native.NUMPY_DGEMV, prelude=handmodel_c.PRELUDE + _layout(),
        include_dirs=(npy[0],), link=(npy[1],),
    )  # fmt: skip
    if loaded is None:
        return None
    try:
        kernel = CompiledAct(*loaded, MODEL_TABLES)
    except ValueError as exc:
        log.warning("operator: numpy (%s)", exc)
        return None

    def check(steps: int) -> bool:
        for k in range(CHECK_OPERATORS):
            mine, theirs = factory(k)
            step = kernel.stepper(mine)
            if step is None:
                log.warning("operator: numpy (the kernel refused a probe's operator)")
                return False
            rng = np.random.default_rng(1000 + k)
            for i in range(steps):
                if i % RESET_EVERY == 0:  # back in flight (the operators brake for good)
                    phase = FLIGHT_PHASES[int(rng.integers(2))]  # translation or turn
                    waypoint = int(rng.integers(len(mine.plan.route)))
                    for op in (mine, theirs):
                        op.phase, op.waypoint = phase, waypoint
                t = 20.0 + 0.02 * i
                dt = 0.02 if i % 37 else float(rng.uniform(1e-3, 0.1))
                seen = view(mine, rng, i, t)
                grid = CHECK_GRIDS[(k + i) % len(CHECK_GRIDS)]
                hands = step(t, dt, seen, grid)
                if hands is None:
                    log.warning("operator: numpy (the compiled step refused a probe)")
                    return False
                want = theirs._act_numpy(t, dt, seen, grid)
                if not (_same(mine, theirs) and _same_hands(hands, want)):
                    log.warning("operator: numpy (the compiled step differs)")
                    return False
        return True

    if not native.self_checked(loaded[0], "operator", CHECK_STEPS, check):
        return None
    return kernel


def _same_hands(got: tuple[Any, Any], want: tuple[Any, Any]) -> bool:
    """The kernel's hands and the Python's alike to the bit (None: lost)."""
    for a, b in zip(got, want):
        if (a is None) != (b is None):
            return False
        if a is not None and a.tobytes() != b.tobytes():
            return False
    return True


def _same(a: Any, b: Any) -> bool:
    """Two operators' state alike to the bit (their generators' too)."""
    return (
        a.wrist["left"].tobytes() == b.wrist["left"].tobytes()
        and a.wrist["right"].tobytes() == b.wrist["right"].tobytes()
        and np.float64(a.aperture).tobytes() == np.float64(b.aperture).tobytes()
        and (a.phase, a.waypoint, a.finished, a.grip_aperture)
        == (b.phase, b.waypoint, b.finished, b.grip_aperture)
        and (a.stopped_since is None) == (b.stopped_since is None)
        and np.float64(a.stopped_since or 0.0).tobytes()
        == np.float64(b.stopped_since or 0.0).tobytes()
        and np.array(list(a._dropout_until.values())).tobytes()
        == np.array(list(b._dropout_until.values())).tobytes()
        and a.rng.bit_generator.state == b.rng.bit_generator.state
    )


__all__ = [
    "ARGS",
    "CHECK_GRIDS",
    "CHECK_OPERATORS",
    "CHECK_STEPS",
    "CONFIG",
    "FLIGHT_PHASES",
    "HANDS",
    "INPUT",
    "OUTPUT",
    "RESET_EVERY",
    "SOURCE",
    "STATE",
    "CompiledAct",
    "compiled_act",
]
