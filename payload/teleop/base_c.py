"""The base channel's step as compiled C, with numpy's bits.

:meth:`payload.teleop.channels.BaseChannel.step` turns the wrists into the vehicle's twist
every control step: the virtual sphere's request, the hold by the right wrist, the
jerk-limited velocity, the heading's yaw request and its jerk-limited rate, the twist in
the body frame. In numpy that is about sixty small-array calls. Here it is one C call
with the same operations in the same order (see :mod:`payload.sim.allocation_c` for the
method):

* norms through numpy's own CBLAS ``ddot`` (:func:`payload.vecmath.norm`), the rotations'
  products through its ``dgemv`` with the layouts numpy's ``matmul`` passes (the yaw
  matrix row-major, the transposed vehicle rotation column-major);
* ``cos``, ``sin``, ``atan2`` and ``fmod`` of the C library Python's ``math`` calls,
  Python's ``%`` (:func:`pymod`) and its ``min``/``max`` tie rules;
* both jerk limiters by the C of :mod:`payload.teleop.limiter_c` (the yaw one as a
  vector of one, which is what :meth:`JerkLimiter._step_scalar
  <payload.teleop.channels.JerkLimiter._step_scalar>` computes), their state updated in
  place.

It is checked against the numpy step on random wrists when it is built; a wrist that is
not three finite numbers, or inputs of other types, go to the numpy step (which raises
its error). Without a compiler, numpy's OpenBLAS or with ``PAYLOAD_NATIVE=0`` the numpy
step runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.rotations import quat_to_matrix, yaw_matrix
from payload.schema import VehicleTwist
from payload.teleop import limiter_c
from payload.vecmath import read_only

log = logging.getLogger(__name__)

SOURCE = r"""
static dgemv_fn mv;
void payload_base_init(void *ddot, void *gemv) { payload_limiter_init(ddot); mv = (dgemv_fn)gemv; }



static int finite3(const double *v) { return isfinite(v[0]) && isfinite(v[1]) && isfinite(v[2]); }

/* BaseChannel.step. cfg: sphere radius, full-speed offset, max speed, turn min speed, yaw
   gain, the yaw request's cap (BaseChannel.yaw_cap), yaw_matrix(heading0) (9, row-major).
   flags: 1 left wrist, 2 right wrist, 4 vehicle rotation (row-major 3x3), 8 right
   neutral, 16 linear cap (a capped yaw limiter is left to numpy). lin/yaw: each
   limiter's value, rate and parameters (payload_limiter_step's). out: v_req (3), v (3),
   yaw rate, twist linear (3), twist angular (3). Returns the mode (0 brake, 1 drive: the
   left wrist outside its sphere, 2 hold), or -1, nothing changed, for a wrist that is not
   finite. */
int payload_base_step(const double *cfg, const double *neutral, const double *neutral_right,
    const double *left, const double *right, const double *rot, int flags,
    double *lin_value, double *lin_rate, const double *lin_p,
    double *yaw_value, double *yaw_rate, const double *yaw_p, double dt, double *out)
{
    const double sphere = cfg[0], full = cfg[1], max_speed = cfg[2], turn_min = cfg[3];
    const double gain = cfg[4], cap = cfg[5];
    double v_req[3] = {0.0, 0.0, 0.0};
    int outside = 0;
    if (flags & 1) {                                   /* request() */
        if (!finite3(left)) return -1;
        double disp[3], u[3];
        for (int k = 0; k < 3; k++) disp[k] = left[k] - neutral[k];
        const double dist = sqrt(dot(3, disp, 1, disp, 1));
        const double beyond = dist - sphere;
        if (!(beyond <= 0)) {
            const double x = beyond / full;
            const double speed = max_speed * ((x < 1.0) ? x : 1.0);  /* min(1.0, x) */
            for (int k = 0; k < 3; k++) u[k] = disp[k] / dist;
            /* yaw_matrix(heading0), row-major in cfg */
            mv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, cfg + 6, 3, u, 1, 0.0, v_req, 1);
            for (int k = 0; k < 3; k++) v_req[k] = v_req[k] * speed;
            outside = 1;
        }
    }
    int mode = outside ? 1 : 0;
    if (!outside && (flags & 1) && (flags & 8) && (flags & 2)) {  /* right_outside() */
        if (!finite3(right)) return -1;
        double d[3];
        for (int k = 0; k < 3; k++) d[k] = right[k] - neutral_right[k];
        if (sqrt(dot(3, d, 1, d, 1)) > sphere) {
            for (int k = 0; k < 3; k++) v_req[k] = lin_value[k];
            mode = 2;
        }
    }
    for (int k = 0; k < 3; k++) out[k] = v_req[k];
    payload_limiter_step(v_req, lin_value, lin_rate, 3, dt, lin_p, (flags & 16) != 0);
    for (int k = 0; k < 3; k++) out[3 + k] = lin_value[k];
    static const double eye[9] = {1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0};
    const double *r = (flags & 4) ? rot : eye;
    double yaw_req = 0.0;
    if (sqrt(dot(2, v_req, 1, v_req, 1)) > turn_min) {
        const double heading = atan2(r[3], r[0]);
        const double desired = atan2(v_req[1], v_req[0]);
        const double err = pymod(desired - heading + M_PI, 2 * M_PI) - M_PI;
        const double g = gain * err;
        const double lo = (g < cap) ? g : cap;           /* min(cap, g) */
        yaw_req = (lo > -cap) ? lo : -cap;               /* max(-cap, lo) */
    }
    payload_limiter_step(&yaw_req, yaw_value, yaw_rate, 1, dt, yaw_p, 0);
    out[6] = yaw_value[0];
    const double z[3] = {0.0, 0.0, out[6]};
    /* rot.T @ v: the transposed row-major matrix is a column-major one, as numpy passes it */
    mv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, r, 3, out + 3, 1, 0.0, out + 7, 1);
    mv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, r, 3, z, 1, 0.0, out + 10, 1);
    return mode;
}

/* payload_base_step with its arguments in one array (one argument for ctypes to pass):
   a: the pointers cfg .. rot, the flags, the pointers lin_value .. yaw_p, out; s: dt */
int payload_base_packed(const int64_t *a, const double *s)
{
    typedef double *P;
    return payload_base_step((P)a[0], (P)a[1], (P)a[2], (P)a[3], (P)a[4], (P)a[5], (int)a[6],
                             (P)a[7], (P)a[8], (P)a[9], (P)a[10], (P)a[11], (P)a[12], s[0],
                             (P)a[13]);
}
"""
"""The base step's C, compiled after :data:`payload.teleop.limiter_c.SOURCE`."""

MODES = ("brake", "drive", "hold")
"""The kernel's mode codes, in order."""


def _real(a: Any, shape: tuple[int, ...]) -> bool:
    """A numpy array of real numbers (what ``np.asarray(a, float)`` takes as it is) of
    ``shape``."""
    return type(a) is np.ndarray and a.shape == shape and a.dtype.kind in "biuf"


class CompiledBase:
    """The base step, compiled (:data:`SOURCE`), bound to channels by :meth:`stepper`."""

    def __init__(self, lib: ctypes.CDLL, ddot: int, gemv: int) -> None:
        init = lib.payload_base_init
        init.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        init(ddot, gemv)
        fn = lib.payload_base_packed
        fn.restype = ctypes.c_int
        fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._fn = fn

    def stepper(self, channel: Any) -> Callable[..., Any] | None:
        """``step(left, rotation, right)`` of ``channel`` (a :class:`BaseChannel
        <payload.teleop.channels.BaseChannel>`), returning the fields of what its numpy
        step returns (``v_request, v_world, yaw_rate, twist, outside, mode``, a
        :class:`BaseCommand <payload.teleop.channels.BaseCommand>`'s), or None where the
        numpy step is to run (other input types, a non-finite wrist); or None for a
        channel the kernel does not take."""
        c = channel.config
        lin, yaw = channel.linear, channel.yaw
        if lin.value.shape != (3,) or yaw.value.shape != (1,) or yaw.max_value is not None:
            return None  # the channel's own limiters only (its yaw limiter has no cap)
        for limiter in (lin, yaw):
            if not (limiter.max_jerk > 0 and limiter.max_rate >= 0):
                return None  # numpy's step says what is wrong
        neutrals = (channel.neutral, channel.neutral_right)
        has_right = neutrals[1] is not None
        for a in neutrals[: 1 + has_right]:  # read in place: a change to them counts
            if not (type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (3,)):
                return None
            if not a.flags.c_contiguous:
                return None
        cfg = np.array(
            [
                c.sphere_radius,
                c.full_speed_offset,
                c.max_speed,
                c.turn_min_speed,
                c.yaw_gain,
                channel.yaw_cap,
                *yaw_matrix(channel.heading0).ravel(),
            ],
            dtype=np.float64,
        )
        neutral_right = neutrals[1] if has_right else np.zeros(3)
        lin_p, yaw_p = limiter_c.limiter_params(lin), limiter_c.limiter_params(yaw)
        left, right, rot, out = np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros(13)
        fixed = 8 * has_right + 16 * (lin.max_value is not None)
        args = np.zeros(14, dtype=np.int64)  # payload_base_packed's pointers and flags
        args[:6] = [a.ctypes.data for a in (cfg, neutrals[0], neutral_right, left, right, rot)]
        args[9], args[12], args[13] = lin_p.ctypes.data, yaw_p.ctypes.data, out.ctypes.data
        scalars = np.array([channel.dt])
        call = functools.partial(self._fn, args.ctypes.data, scalars.ctypes.data)
        bound: list[Any] = [None, None, None, None]
        # what the step was made for: another setting, neutral, limiter or limit -> numpy
        n0, n1, h0, dt0 = neutrals[0], neutrals[1], channel.heading0, channel.dt
        made_for = (lin.settings(), yaw.settings())

        def state() -> bool:
            """Bind the limiters' arrays (made the limiters' own first); False for arrays
            of other shapes (the numpy step says what is wrong)."""
            for m, n in ((lin, 3), (yaw, 1)):
                if np.shape(m.value) != (n,) or np.shape(m.rate) != (n,):
                    return False
            if not (bound[0] is lin.value and bound[1] is lin.rate):
                lin.value, lin.rate = np.array(lin.value, float), np.array(lin.rate, float)
            if not (bound[2] is yaw.value and bound[3] is yaw.rate):
                yaw.value, yaw.rate = np.array(yaw.value, float), np.array(yaw.rate, float)
            bound[:] = lin.value, lin.rate, yaw.value, yaw.rate
            args[7], args[8] = lin.value.ctypes.data, lin.rate.ctypes.data
            args[10], args[11] = yaw.value.ctypes.data, yaw.rate.ctypes.data
            return True

        def unchanged() -> bool:
            """The channel's settings, neutrals, limiters and limits as the step was made
            for."""
            return not (
                channel.config is not c
                or channel.neutral is not n0
                or channel.neutral_right is not n1
                or channel.linear is not lin
                or channel.yaw is not yaw
                or channel.heading0 != h0
                or channel.dt != dt0
                or (lin.settings(), yaw.settings()) != made_for
            )

        def ready(rotation: Any, flags: int) -> bool:
            """The rotation copied in (flag 4) and the limiters' arrays bound, the flags
            set: the kernel may run; False where the numpy step is to run."""
            if rotation is not None:
                # numpy's rot.T @ v takes its BLAS layout from the memory: row-major only
                if not (_real(rotation, (3, 3)) and rotation.flags.c_contiguous):
                    return False
                np.copyto(rot, rotation)
                flags |= 4
            if (
                not (
                    bound[0] is lin.value
                    and bound[1] is lin.rate
                    and bound[2] is yaw.value
                    and bound[3] is yaw.rate
                )
                and not state()
            ):
                return False
            args[6] = flags
            return True

        def finish(mode: int, stamp: float) -> tuple:
            """The fields of the step's command from what the kernel wrote."""
            vel = read_only(out[7:13])  # the twist's own, frozen: taken as it is
            twist = VehicleTwist.of_frozen(vel[:3], vel[3:], stamp)
            return (  # outside: the drive mode (the left wrist outside its sphere)
                out[0:3].copy(), out[3:6].copy(), float(out[6]), twist, MODES[mode] == "drive",
                MODES[mode],
            )  # fmt: skip

        def step(left_wrist: Any, rotation: Any, right_wrist: Any, stamp: float = 0.0) -> Any:
            if not unchanged():
                return None
            flags = fixed
            if left_wrist is not None:
                if not _real(left_wrist, (3,)):
                    return None
                np.copyto(left, left_wrist)
                flags |= 1
            if right_wrist is not None:
                if not _real(right_wrist, (3,)):
                    return None
                np.copyto(right, right_wrist)
                flags |= 2
            if not ready(rotation, flags):
                return None
            mode = call()
            if mode < 0:
                return None
            return finish(mode, stamp)

        def prepare(rotation: Any) -> bool:
            """For a caller that writes both wrists into :attr:`entry`'s buffers and runs
            the kernel itself (:mod:`payload.teleop.intake_c`): what :func:`step` does
            before its call with both wrists given; False where the numpy step is to run.
            A kernel's mode >= 0 then goes to ``finish(mode, stamp)``, a mode < 0 changed
            nothing."""
            return unchanged() and ready(rotation, fixed | 3)

        if not state():
            return None
        keep = (cfg, *neutrals, neutral_right, lin_p, yaw_p, left, right, rot, out, args, scalars)
        step.keep = keep  # type: ignore[attr-defined]
        step.prepare = prepare  # type: ignore[attr-defined]
        step.finish = finish  # type: ignore[attr-defined]
        # the packed step, its two arguments, and the wrists' buffers it reads
        step.entry = (  # type: ignore[attr-defined]
            ctypes.cast(self._fn, ctypes.c_void_p).value,
            args.ctypes.data,
            scalars.ctypes.data,
            left.ctypes.data,
            right.ctypes.data,
        )
        return step


def _load() -> tuple[Any, ...] | None:
    return native.load_blas_kernel(
        "base",
        limiter_c.SOURCE + native.PYMOD_C + SOURCE,
        "the base channel kernel",
        log,
        native.NUMPY_DDOT,
        native.NUMPY_DGEMV,
    )


@functools.cache
@native.reported("base channel")
def compiled_base(factory: Callable[..., Any]) -> CompiledBase | None:
    """The process's compiled base step, or None to run the numpy step (no compiler, no
    numpy OpenBLAS, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that differs in a
    single bit from the numpy step of channels made by ``factory(neutral_left, heading0,
    neutral_right)``, on random wrists in every mode: :data:`CHECK_STEPS` steps of three
    channels, or their first third once a full check passed, :func:`payload.native.probes`)."""
    loaded = _load()
    if loaded is None:
        return None
    kernel = CompiledBase(*loaded)

    # each channel's steps, or its first third (every kind of leg) once a full check passed
    def check(steps: int) -> bool:
        for c, (heading, with_right) in enumerate(CHECK_CHANNELS):
            rng = np.random.default_rng(c)  # each channel's own draws: the short check a prefix
            neutral = rng.normal(scale=0.1, size=3)
            right_neutral = neutral + np.array([0.0, -0.3, 0.0])
            mine = factory(neutral, heading, right_neutral if with_right else None)
            theirs = factory(neutral, heading, right_neutral if with_right else None)
            step = kernel.stepper(mine)
            if step is None:
                return False
            left, right = neutral.copy(), right_neutral.copy()
            q = rng.normal(size=4)
            for k in range(steps):
                if k % 50 == 0:  # a new leg: push, hold with the right hand, let go, lose
                    aim = rng.normal(scale=(0.0, 0.03, 0.1, 0.3)[(k // 50) % 4], size=3)
                    q = rng.normal(size=4)
                left = left + 0.1 * (neutral + aim - left)
                right = right_neutral + (rng.normal(scale=0.08, size=3) if k % 100 > 70 else 0.0)
                q = q + rng.normal(scale=0.01, size=4)
                rot = quat_to_matrix(q / np.linalg.norm(q))
                args = (
                    None if k % 173 == 7 else left.copy(),
                    None if k % 61 == 3 else rot,
                    None if k % 89 == 5 else right.copy(),
                )
                a, b = step(*args), theirs._step_numpy(*args)
                if a is None or not _same(a, b) or not _same_state(mine, theirs):
                    log.warning("base channel: numpy (the compiled step differs)")
                    return False
        return True

    if not native.self_checked(loaded[0], _CHECK_KEY, CHECK_STEPS, check, SHORT_STEPS):
        return None
    return kernel


CHECK_STEPS = 600
"""Steps of each channel (:data:`CHECK_CHANNELS`) of the base kernel's full self-check;
its first third (:data:`SHORT_STEPS`) already holds the four kinds of leg (aims of 0 to
0.3 m), the right hand's holds and lost hands and rotations."""

SHORT_STEPS = CHECK_STEPS // 3
"""Steps of each channel in the short check (every kind of leg)."""

CHECK_CHANNELS: tuple[tuple[float, bool], ...] = ((0.0, True), (2.3, True), (-1.1, False))
"""The self-check's channels: heading [rad], and whether a right-hand neutral is set."""

_CHECK_KEY = "base channel"  # the check stamp's key


def _fields(command: Any) -> tuple:
    """A base command's fields (a command, or the kernel's tuple of them)."""
    if isinstance(command, tuple):
        return command
    c = command
    return (c.v_request, c.v_world, c.yaw_rate, c.twist, c.outside, c.mode)


def _same(a: Any, b: Any) -> bool:
    """Two base commands (or the kernel's tuples of their fields) alike to the bit."""
    (ra, va, ya, ta, oa, ma), (rb, vb, yb, tb, ob, mb) = _fields(a), _fields(b)
    return (
        ra.tobytes() == rb.tobytes()
        and va.tobytes() == vb.tobytes()
        and np.float64(ya).tobytes() == np.float64(yb).tobytes()
        and ta.linear.tobytes() == tb.linear.tobytes()
        and ta.angular.tobytes() == tb.angular.tobytes()
        and (oa, ma, ta.stamp) == (ob, mb, tb.stamp)
    )


def _same_state(a: Any, b: Any) -> bool:
    """Two channels' limiters in the same state, to the bit."""
    return all(
        np.asarray(getattr(getattr(a, lim), part), float).tobytes()
        == np.asarray(getattr(getattr(b, lim), part), float).tobytes()
        for lim in ("linear", "yaw")
        for part in ("value", "rate")
    )


__all__ = ["CHECK_STEPS", "MODES", "SOURCE", "CompiledBase", "compiled_base"]
