"""The nozzle controller's step and the thrusts into MuJoCo as compiled C, with numpy's bits.

:meth:`VehicleController.update <payload.sim.vehicle.VehicleController.update>` with
nozzles (the twist clamp, the jerk-limited profile, the wrench, then the allocation up to
its searches) is one C call (:class:`CompiledControl`) that calls the allocation's
compiled searches (:mod:`payload.sim.allocation_c`, whose C this library includes) on
their own state; its norms go through numpy's ``ddot`` and Python's ``min``/``max`` tie
rules are kept. :meth:`SimDriver.apply_thrusts <payload.sim.driver.SimDriver.apply_thrusts>`
is one C call per control step (:class:`CompiledThrusts`) making the same two ``dgemv``
products per open nozzle and the same ``mj_applyFT`` calls of MuJoCo's own library. Each
checks itself against the numpy code when it is built; without the searches, a compiler,
numpy's OpenBLAS, MuJoCo's symbol, or with ``PAYLOAD_NATIVE=0``, the numpy code runs.

The two classes that call the library's entry points are
:mod:`payload.sim.vehicle_bindings` (re-exported here).
"""

from __future__ import annotations

import ctypes
import functools
import logging
from typing import Any

import numpy as np

from payload import native
from payload.schema import CONTROL_DT
from payload.sim.allocation_c import load_with_searches
from payload.sim.errors import SimError
from payload.sim.vehicle_bindings import CompiledControl, CompiledThrusts

log = logging.getLogger(__name__)

ENTRY_TYPES = r"""
typedef int (*control_fn)(void *, double);
typedef void (*thrusts_fn)(void *, void *, const void *, void *, const double *, const double *,
                           const double *, const double *, const double *, int, double *);
"""
"""The types of the controller's step and the thrusts' entry points
(:mod:`payload.sim.period_c` calls them through their addresses; this library's C is
compiled against them, so a change of either signature fails the build)."""

CONTROL_SOURCE = (
    ENTRY_TYPES
    + r"""
/* ---- the vehicle controller's step (payload.sim.vehicle.VehicleController.update) ---- */

typedef struct {
    searches *s;
    ddot_fn dot;
    const double *matrix;                   /* (6, 12) nozzle wrench per newton */
    int matrix_order; int64_t matrix_ld;    /* its layout, as numpy hands it to dgemv */
    const double *inertia, *com;            /* (3, 3), (3) */
    int inertia_order; int64_t inertia_ld;
    double mass, gain_lin, gain_ang, speed, omega;
    const double *budget;                   /* (3) reference_share * accel_max */
    const double *jerk, *amax;              /* (6) each: the profile's bounds */
    double *vel, *acc;                      /* (6) each: the profile's state, in place */
    const double *in;                       /* (12): command lin, ang; measured lin, ang */
    double *res;                            /* (14): w (6), delivered (6), lam, scale */
    int64_t *facet;
} control;

void *payload_control_new(void *searches_state, void *dot, const double *matrix,
    int matrix_order, int64_t matrix_ld, const double *inertia, int inertia_order,
    int64_t inertia_ld, const double *com, double mass, double gain_lin, double gain_ang,
    double speed, double omega, const double *budget, const double *jerk, const double *amax,
    const double *in, double *res, int64_t *facet)
{
    control *c = malloc(sizeof *c);
    if (!c) return NULL;
    c->s = searches_state; c->dot = (ddot_fn)dot;
    c->matrix = matrix; c->matrix_order = matrix_order; c->matrix_ld = matrix_ld;
    c->inertia = inertia; c->inertia_order = inertia_order; c->inertia_ld = inertia_ld;
    c->com = com; c->mass = mass;
    c->gain_lin = gain_lin; c->gain_ang = gain_ang; c->speed = speed; c->omega = omega;
    c->budget = budget; c->jerk = jerk; c->amax = amax; c->vel = NULL; c->acc = NULL;
    c->in = in; c->res = res; c->facet = facet;
    return c;
}

void payload_control_free(void *p) { free(p); }

/* the profile's state arrays (JerkLimitedProfile.velocity, .acceleration), updated in place */
void payload_control_state(void *p, double *vel, double *acc)
{
    control *c = p;
    c->vel = vel; c->acc = acc;
}

/* vecmath.cross / vehicle._cross: the same products and differences */
static void cross3(const double *a, const double *b, double *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Python's min(a, b) and max(a, b) of floats: the first unless the second is less/greater */
static double py_min(double a, double b) { return (b < a) ? b : a; }
static double py_max(double a, double b) { return (b > a) ? b : a; }

/* JerkLimitedProfile.step on Python floats, axis by axis */
static void profile_step(control *c, const double *target, double dt)
{
    const double lin = 0.5 * dt;
    for (int i = 0; i < NB; i++) {
        double tg = target[i], v = c->vel[i], a0 = c->acc[i], j = c->jerk[i], a_max = c->amax[i];
        double e = tg - v;
        double s = e >= 0.0 ? 1.0 : -1.0;
        double a = s * a0;
        double dist = fabs(e);
        double quad = 1.0 / (2.0 * j);
        double cst = a * lin - dist;
        double x;
        if (cst <= 0.0)
            x = (-lin + sqrt(lin * lin - 4.0 * quad * py_min(cst, 0.0))) / (2.0 * quad);
        else
            x = (lin - sqrt(lin * lin + 4.0 * quad * py_max(cst, 0.0))) / (2.0 * quad);
        x = py_min(py_max(x, a - j * dt), a + j * dt);
        x = py_min(py_max(x, -a_max), a_max);
        double v_new = v + s * 0.5 * (a + x) * dt;
        double a_new = s * x;
        int arrived = fabs(tg - v_new) <= 1e-12 + 1e-9 * fabs(tg) && fabs(a_new) <= j * dt;
        c->vel[i] = arrived ? tg : v_new;
        c->acc[i] = arrived ? 0.0 : a_new;
    }
}

/* VehicleController.update with nozzles, up to the allocation:
   0 allocated (thrusts in the searches' buffer, delivered wrench in res[6:12], scale res[13]);
   1 zero wrench; 2 outside the polytope (lam res[12], facet); 3 no basic solution (lam,
   facet, scale); 4 a non-finite wrench. In 2 to 4 the requested wrench is in res[0:6]. */
int payload_control_step(void *p, double dt)
{
    control *c = p;
    searches *s = c->s;
    const double *in = c->in;
    double *res = c->res;
    double lin[3] = {in[0], in[1], in[2]}, ang[3] = {in[3], in[4], in[5]};
    const double *v = in + 6, *w = in + 9;
    /* clamp */
    double sp = sqrt(c->dot(3, lin, 1, lin, 1)), om = sqrt(c->dot(3, ang, 1, ang, 1));
    if (sp > c->speed) {
        double f = c->speed / sp;
        for (int i = 0; i < 3; i++) lin[i] = lin[i] * f;
    }
    if (om > c->omega) {
        double f = c->omega / om;
        for (int i = 0; i < 3; i++) ang[i] = ang[i] * f;
    }
    double cen[3];
    cross3(ang, lin, cen);
    int any = 0; double least = 0.0;
    for (int i = 0; i < 3; i++) {
        cen[i] = fabs(cen[i]);
        if (cen[i] > c->budget[i]) {
            double r = c->budget[i] / cen[i];
            if (!any || r < least) least = r;
            any = 1;
        }
    }
    if (any) for (int i = 0; i < 3; i++) ang[i] = ang[i] * least;
    double target[NB] = {lin[0], lin[1], lin[2], ang[0], ang[1], ang[2]};
    profile_step(c, target, dt);
    const double *ref = c->vel, *acc = c->acc;
    /* the wrench */
    double cwv[3], force[3], alpha[3], ia[3], iw[3], ciw[3], ccf[3], torque[3];
    cross3(w, v, cwv);
    for (int i = 0; i < 3; i++)
        force[i] = c->mass * ((acc[i] + c->gain_lin * (ref[i] - v[i])) + cwv[i]);
    for (int i = 0; i < 3; i++) alpha[i] = acc[3 + i] + c->gain_ang * (ref[3 + i] - w[i]);
    s->gemv(c->inertia_order, NO_TRANS, 3, 3, 1.0, c->inertia, c->inertia_ld, alpha, 1, 0.0,
            ia, 1);
    s->gemv(c->inertia_order, NO_TRANS, 3, 3, 1.0, c->inertia, c->inertia_ld, w, 1, 0.0, iw, 1);
    cross3(w, iw, ciw);
    cross3(c->com, force, ccf);
    for (int i = 0; i < 3; i++) torque[i] = (ia[i] + ciw[i]) + ccf[i];
    /* Propulsion.allocate */
    int finite = 1, nonzero = 0;
    for (int i = 0; i < 3; i++) { res[i] = force[i]; res[3 + i] = torque[i]; }
    for (int i = 0; i < NB; i++) { finite &= isfinite(res[i]) != 0; nonzero |= res[i] != 0.0; }
    if (!finite) return 4;
    if (!nonzero) return 1;
    double *ws = (double *)s->wrench;
    for (int i = 0; i < NB; i++) ws[i] = res[i];
    int64_t k = payload_extent(s);
    double lam = *s->ratio;
    res[12] = lam; *c->facet = k;
    if (lam < 1.0) return 2;
    double scale = py_min(1.0, lam * (1.0 - 1e-9));
    res[13] = scale;
    for (int i = 0; i < NB; i++) ws[i] = scale * res[i];
    if (!payload_least_thrust(s)) return 3;
    s->gemv(c->matrix_order, NO_TRANS, NB, NZ, 1.0, c->matrix, c->matrix_ld, s->thrust, 1, 0.0,
            res + 6, 1);
    return 0;
}

_Static_assert(__builtin_types_compatible_p(__typeof__(&payload_control_step), control_fn),
               "payload_control_step is not a control_fn (ENTRY_TYPES)");

/* ---- thrusts into MuJoCo (payload.sim.driver.SimDriver.apply_thrusts) ---- */
typedef void (*applyft_fn)(const void *, void *, const double *, const double *, const double *,
                           int, double *);

void payload_apply_thrusts(void *gemv, void *apply, const void *m, void *d, const double *rot,
    const double *origin, const double *dirs, const double *pos, const double *thrust, int body,
    double *qfrc)
{
    dgemv_fn mv = (dgemv_fn)gemv;
    applyft_fn ft = (applyft_fn)apply;
    const double zero[3] = {0.0, 0.0, 0.0};
    for (int k = 0; k < NZ; k++) {
        if (!(thrust[k] > 0.0)) continue;
        double fd[3], f[3], rp[3], pt[3];
        for (int i = 0; i < 3; i++) fd[i] = dirs[3 * k + i] * thrust[k];
        mv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, rot, 3, fd, 1, 0.0, f, 1);
        mv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, rot, 3, pos + 3 * k, 1, 0.0, rp, 1);
        for (int i = 0; i < 3; i++) pt[i] = origin[i] + rp[i];
        ft(m, d, f, zero, pt, body, qfrc);
    }
}

_Static_assert(__builtin_types_compatible_p(__typeof__(&payload_apply_thrusts), thrusts_fn),
               "payload_apply_thrusts is not a thrusts_fn (ENTRY_TYPES)");
"""
)
"""The controller's and the thrusts' C, compiled after :data:`payload.sim.allocation_c.SOURCE`."""


def _load(what: str, nozzles: int) -> tuple[ctypes.CDLL, int] | None:
    return load_with_searches(what, nozzles, "vehicle", CONTROL_SOURCE)


def _same_update(a: tuple, b: tuple) -> bool:
    """Two (wrench, allocation, velocity, acceleration) results alike in every bit."""
    (wa, aa, va, ca), (wb, ab, vb, cb) = a, b
    arrays = [
        (wa.force, wb.force),
        (wa.torque, wb.torque),
        (aa.thrust, ab.thrust),
        (aa.force, ab.force),
        (aa.torque, ab.torque),
        (va, vb),
        (ca, cb),
    ]
    return aa.scale == ab.scale and all(x.tobytes() == y.tobytes() for x, y in arrays)


CHECK_STEPS = 160
"""Control steps of the controller kernel's full self-check (:func:`check_control`)."""

COMMAND_STEPS = 10
"""Steps each of the self-check's commands is held: a shorter check is the start of the
full one and still sees several commands."""


def check_control(controller: Any, kernel: CompiledControl, steps: int) -> bool:
    """Run ``steps`` control steps of piecewise-constant random commands (a new one every
    :data:`COMMAND_STEPS`: moving and turning, at rest, within or beyond the mode's speed)
    from the same states through the numpy code and the kernel; True if every wrench,
    allocation and profile state has the same bits. The controller's profile state and
    allocation are restored afterwards."""
    from payload.schema import VehicleTwist

    profile = controller.profile
    saved = (profile.velocity.copy(), profile.acceleration.copy(), controller.allocation)
    rng = np.random.default_rng(2)
    mode = controller.mode
    command = VehicleTwist.zero()
    try:
        for i in range(steps):
            if i % COMMAND_STEPS == 0:
                scale = rng.choice((0.0, 0.5, 1.0, 2.0))
                command = VehicleTwist(
                    rng.normal(size=3) * mode.speed * scale,
                    rng.normal(size=3) * mode.omega * scale,
                    0.0,
                )
            lin = profile.velocity[:3] + rng.normal(scale=1e-3, size=3)
            ang = profile.velocity[3:] + rng.normal(scale=1e-3, size=3)
            start = (profile.velocity.copy(), profile.acceleration.copy())
            wrench = controller._update_numpy(command, lin, ang, CONTROL_DT)
            want = (wrench, controller.allocation, profile.velocity, profile.acceleration)
            after = (profile.velocity, profile.acceleration)
            profile.velocity, profile.acceleration = start[0].copy(), start[1].copy()
            wrench = controller._update_kernel(kernel, command, lin, ang, CONTROL_DT)
            got = (wrench, controller.allocation, profile.velocity, profile.acceleration)
            if not _same_update(want, got):
                return False
            profile.velocity, profile.acceleration = after
        return True
    finally:
        profile.velocity, profile.acceleration, controller.allocation = saved


@native.reported("vehicle controller")
def compiled_control(controller: Any) -> CompiledControl | None:
    """The compiled control step for a nozzle ``controller``, or None to run the numpy
    code (no kernels, no numpy ``ddot``, or a self-check (:func:`check_control`) that
    differs in a single bit: :data:`CHECK_STEPS` steps, or their first quarter once a build
    for as many nozzles passed, here or in an earlier process: :func:`payload.native.probes`)."""
    searches = controller.nozzles._kernels if controller.nozzles is not None else None
    loaded = nozzles = None
    if searches is not None:
        nozzles = len(controller.nozzles.thrust_max)
        loaded = _load("controller kernel", nozzles)
    ddot = native.numpy_blas(native.NUMPY_DDOT)
    if loaded is None or ddot is None:
        return None
    try:
        kernel = CompiledControl(controller, searches, loaded[0], ddot)
    except SimError as exc:
        log.warning("controller kernel: numpy (%s)", exc)
        return None
    check = functools.partial(check_control, controller, kernel)
    if not native.self_checked(loaded[0], nozzles, CHECK_STEPS, check, CHECK_STEPS // 4):
        log.warning("controller kernel: numpy (the compiled step differs)")
        return None
    return kernel


@native.reported("thrusts")
def compiled_thrusts(
    model: Any, data: Any, body: int, nozzles: Any, python: Any
) -> CompiledThrusts | None:
    """The compiled thrust application, or None to run ``python`` (the numpy loop,
    ``python(thrust, qfrc)``): no kernels, no MuJoCo symbol, or a self-check on random
    thrusts in this data's state that differs from ``python`` in a single bit."""
    n = len(nozzles.thrust_max)
    loaded = _load("thrust kernel", n)
    apply_ft = native.mujoco_function("mj_applyFT")
    if loaded is None or apply_ft is None:
        return None
    kernel = CompiledThrusts(model, data, body, nozzles, loaded[0], loaded[1], apply_ft)
    rng = np.random.default_rng(3)
    for _ in range(50):
        thrust = rng.uniform(0.0, 1.0, size=n) * (rng.random(n) < 0.6)
        mine, theirs = np.zeros(model.nv), np.zeros(model.nv)
        kernel(thrust, mine)
        python(thrust, theirs)
        if mine.tobytes() != theirs.tobytes():
            log.warning("thrust kernel: numpy (the compiled thrusts differ)")
            return None
    return kernel


__all__ = [
    "CONTROL_SOURCE",
    "ENTRY_TYPES",
    "CompiledControl",
    "CompiledThrusts",
    "check_control",
    "compiled_control",
    "compiled_thrusts",
]
