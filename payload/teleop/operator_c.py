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

import functools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from payload import native
from payload.teleop import handmodel_c
from payload.teleop.handmodel import MODEL_TABLES, held_hand_kernel
from payload.teleop.operator_layout import (
    ARGS,
    CONFIG,
    FLIGHT_PHASES,
    HANDS,
    INPUT,
    OUTPUT,
    STATE,
    _layout,
)
from payload.teleop.operator_stepper import CompiledAct

log = logging.getLogger(__name__)

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
