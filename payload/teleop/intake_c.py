"""The pipeline's hand intake as one compiled call, with the Python path's bits.

Each control step, before its three channels, the teleoperation pipeline takes both hands
in: the tracking supervisor's checks of each hand (:mod:`payload.teleop.safety_c`), the
One Euro filter of each hand's keypoints (:mod:`payload.teleop.filter_c`) and each finger
pair's chain from the filtered hand to its solved command (:mod:`payload.teleop.pair_c`).
Each of those is one compiled call already; what remains between them is Python: the
supervisor's bookkeeping, the filters' clocks and copies, the hands made of them.

On a steady step (both hands tracked and not lost, time going forward, both filters
running) one C call here runs those kernels, reached through their addresses, in the
Python path's order: both hands' checks (nothing changes if one fails: the Python path
runs and words the reason), both filter steps, both chains. Its own arithmetic is the
jump a wrist is allowed since its last valid frame and the filter's period and speed
smoothing factor, the same operations as
:func:`~payload.teleop.safety.allowed_jump` and
:func:`~payload.teleop.filters._alpha`; that arithmetic is checked against them when
built (the kernels it calls check themselves when they are built; the whole intake is
tested against the Python path: ``tests/test_pipeline.py``). Only a stamp that is a
Python float (or numpy's float64) is taken in: another type's arithmetic is the Python
path's. The caller adopts the step as the Python path would (:meth:`TrackingSupervisor.accepted
<payload.teleop.safety.TrackingSupervisor.accepted>`, the filters' clocks) and finishes
each pair whose chain took its hand; a chain that refused its hand leaves that pair to
the Python path, which raises its error (the pipeline's safety event). Without a
compiler, a compiled part, or with ``PAYLOAD_NATIVE=0``, the Python path runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Iterator
from typing import Any

import numpy as np

from payload import native
from payload.teleop.channels import ChannelError, RailConfig, rail_command
from payload.teleop.filters import OneEuroFilter, _alpha
from payload.teleop.hands import JOINTS_SHAPE, HandFrame
from payload.teleop.pair_c import FingerChain
from payload.teleop.safety import SIDES, Supervised, TrackingSupervisor, allowed_jump

log = logging.getLogger(__name__)

SOURCE = r"""
typedef int (*check_fn)(void *, const double *, int64_t, int64_t, const double *,
                        const double *, int, const double *, int);
typedef void (*euro_fn)(const double *, double *, double *, int64_t, double, double, double,
                        double, double);
typedef int (*chain_fn)(const void *, const double *);

/* every field 8 bytes: the ctypes structure _Side, in this order */
struct side {
    void *check, *ddot; int64_t n, wrist; double *params; const double *neutral;
    int64_t has_neutral; double *last; double max_speed;
    void *euro; double *x, *dx; double two_pi, min_cutoff, beta, d_cutoff;
    void *chain; const void *ctx; const double *raw;
};

/* safety.allowed_jump: the jump allowed since the last valid frame, and the filter's
   period and speed smoothing factor (filters._alpha of d_cutoff), for a step at t */
static double allowed(double speed, double t, double tv) { return speed * (t - tv); }
static double alpha(double cutoff, double dt)
{
    return 1.0 / (1.0 + (1.0 / (2.0 * M_PI * cutoff)) / dt);
}

void payload_intake_numbers(double t, double tf, double tv, double speed, double cutoff,
                            double *out)
{
    out[0] = allowed(speed, t, tv);
    out[1] = t - tf;
    out[2] = alpha(cutoff, t - tf);
}

/* Both hands at t. clocks per side: the filter's last time, the last valid frame's time,
   whether there is one. -1: a hand fails a check, -2: a filter's time does not move on
   (nothing changed: the Python path is to run). Else the filters stepped, the last valid
   wrists are these hands', and bit s is set where side s's chain took its hand. */
int payload_intake(const struct side *h, double t, double tf0, double tv0, int has0,
                   double tf1, double tv1, int has1)
{
    const double tf[2] = {tf0, tf1}, tv[2] = {tv0, tv1};
    const int has[2] = {has0, has1};
    for (int s = 0; s < 2; s++) {
        const struct side *e = h + s;
        const int has_last = has[s] && t > tv[s];
        if (has_last) e->params[2] = allowed(e->max_speed, t, tv[s]);
        if (((check_fn)e->check)(e->ddot, e->raw, e->n, e->wrist, e->params, e->neutral,
                                 (int)e->has_neutral, e->last, has_last))
            return -1;
        if (!(t > tf[s])) return -2;
    }
    for (int s = 0; s < 2; s++) {
        const struct side *e = h + s;
        const double dt = t - tf[s];
        ((euro_fn)e->euro)(e->raw, e->x, e->dx, e->n, dt, alpha(e->d_cutoff, dt), e->two_pi,
                           e->min_cutoff, e->beta);
    }
    int taken = 0;
    for (int s = 0; s < 2; s++) {
        const struct side *e = h + s;
        if (((chain_fn)e->chain)(e->ctx, e->x) == 0) taken |= 1 << s;
        for (int k = 0; k < 3; k++) e->last[k] = e->raw[3 * e->wrist + k];
    }
    return taken;
}

typedef int (*base_fn)(const int64_t *, const double *);

/* every field 8 bytes: the ctypes structure _Tail, in this order */
struct tail {
    const double *fresh0, *fresh1; int64_t n; void *ddot;
    void *base; const int64_t *base_args; const double *base_scalars;
    double *base_left, *base_right;
    double d_min, d_max, travel; double *rail;
};

/* channels.rail_command of two wrists: the distance as vecmath.norm of their difference
   (numpy's ddot), then Python's float arithmetic and min/max tie rules. 0, or -1 for a
   distance that is not finite (nothing written). */
int payload_tail_rail(const double *left, const double *right, const struct tail *p,
                      double *rail)
{
    double d3[3];
    for (int k = 0; k < 3; k++) d3[k] = right[k] - left[k];
    const double d = sqrt(((ddot_fn)p->ddot)(3, d3, 1, d3, 1));
    if (!isfinite(d)) return -1;
    const double s = (d - p->d_min) / (p->d_max - p->d_min);
    const double lo = (s > 0.0) ? s : 0.0;                /* max(0.0, s) */
    *rail = p->travel * ((lo < 1.0) ? lo : 1.0);          /* travel * min(1.0, ...) */
    return 0;
}

/* The pipeline's channels after a steady intake (both chains took their hands): both
   solved commands finite, the rail command of the filtered wrists
   and the base channel's step on them. Returns the base's mode, or -1 where the Python
   path is to run (a command or a distance that is not finite, or a base step refused:
   nothing it keeps changed). */
static int tail_step(const struct side *h, const struct tail *p)
{
    for (int64_t k = 0; k < p->n; k++)
        if (!isfinite(p->fresh0[k]) || !isfinite(p->fresh1[k])) return -1;
    const double *wl = h[0].x + 3 * h[0].wrist, *wr = h[1].x + 3 * h[1].wrist;
    if (payload_tail_rail(wl, wr, p, p->rail)) return -1;
    for (int k = 0; k < 3; k++) {
        p->base_left[k] = wl[k];
        p->base_right[k] = wr[k];
    }
    return ((base_fn)p->base)(p->base_args, p->base_scalars);
}

/* payload_intake, then with ``tail`` on a step both chains took, tail_step: bits 0 and 1
   as payload_intake's, bit 2 set where the tail ran, bits 3 and 4 the base's mode. */
int payload_intake_step(const struct side *h, const struct tail *p, int tail, double t,
                        double tf0, double tv0, int has0, double tf1, double tv1, int has1)
{
    const int taken = payload_intake(h, t, tf0, tv0, has0, tf1, tv1, has1);
    if (taken != 3 || !tail) return taken;
    const int mode = tail_step(h, p);
    return mode < 0 ? taken : taken | 4 | mode << 3;
}
"""
"""The intake's C (:func:`payload.native.build_library` compiles it)."""

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double


def _fields(spec: str) -> list[tuple[str, Any]]:
    """A C structure's fields for ctypes from ``name:kind`` words (p: pointer, i: int64,
    d: double), in order."""
    return [
        (name, {"p": _P, "i": _I, "d": _D}[kind])
        for name, kind in (field.split(":") for field in spec.split())
    ]


class _Side(ctypes.Structure):
    """``struct side`` of :data:`SOURCE`."""

    _fields_ = _fields(
        "check:p ddot:p n:i wrist:i params:p neutral:p has_neutral:i last:p max_speed:d "
        "euro:p x:p dx:p two_pi:d min_cutoff:d beta:d d_cutoff:d chain:p ctx:p raw:p"
    )


class _Tail(ctypes.Structure):
    """``struct tail`` of :data:`SOURCE`."""

    _fields_ = _fields(
        "fresh0:p fresh1:p n:i ddot:p base:p base_args:p base_scalars:p base_left:p "
        "base_right:p d_min:d d_max:d travel:d rail:p"
    )


def intake_objects(
    supervisor: TrackingSupervisor,
    filters: dict[str, OneEuroFilter],
    chains: tuple[Any, Any],
) -> tuple:
    """What an intake is made for: the supervisor, its settings and neutral wrists, each
    filter's settings, estimates and compiled step, each side's chain (``chains``: the
    left hand's, the right hand's)."""
    left, right = filters["left"], filters["right"]
    neutral = supervisor.neutral
    return (
        supervisor, supervisor.config, neutral.get("left"), neutral.get("right"),
        left.config, left._x, left._dx, left._bound,
        right.config, right._x, right._dx, right._bound,
        chains[0], chains[1],
    )  # fmt: skip


def intake_parts(objects: tuple) -> tuple[int, ...]:
    """:func:`intake_objects` by identity (their ids: whoever keeps the objects keeps
    their ids theirs), compared at every step."""
    return tuple(map(id, objects))


def ready(filters: dict[str, OneEuroFilter], chains: tuple[Any, Any]) -> bool:
    """Whether the parts an intake runs are there: each side's compiled chain, and each
    filter running (a sample taken) with its compiled step bound to its estimates."""
    for side, chain in zip(SIDES, chains):
        f = filters[side]
        bound = f._bound
        if not isinstance(chain, FingerChain):
            return False
        if f._t is None or bound is None or bound[2] is None:
            return False
        if bound[0] is not f._x or bound[1] is not f._dx or bound[3] is not f.config:
            return False
    return True


class HandIntake:
    """Both hands' checks, filter steps and finger chains as one C call.

    Args:
        lib: The intake's library (:data:`SOURCE`).
        supervisor: The pipeline's tracking supervisor, with a compiled check per side.
        filters: The pipeline's filter per side, each with its compiled step bound.
        chains: The finger chain of each side (the pair that hand drives), the left
            hand's first.

    Raises:
        ValueError: A part the intake needs is not compiled (or not bound).
    """

    def __init__(
        self,
        lib: ctypes.CDLL,
        supervisor: TrackingSupervisor,
        filters: dict[str, OneEuroFilter],
        chains: tuple[Any, Any],
    ) -> None:
        if not ready(filters, chains):
            raise ValueError("a filter or a chain is not compiled and running")
        self.made_for = intake_objects(supervisor, filters, chains)
        """What it is made for (:func:`intake_objects`; kept alive with it)."""
        self._supervisor = supervisor
        self._filters = [filters[side] for side in SIDES]
        self._chains = list(chains)
        self._raw = [np.zeros(JOINTS_SHAPE) for _ in SIDES]
        self._last = [np.zeros(3) for _ in SIDES]
        self._params = []
        self._accepted: list[Any] = [None, None]
        sides = []
        for k, side in enumerate(SIDES):
            check = supervisor._check_kernel(side)
            if check is None or check.shape != JOINTS_SHAPE:
                raise ValueError(f"no compiled hand check for the {side} hand")
            fn, ddot, n, wrist, params, neutral, has_neutral = check.entry
            mine = np.array(params, dtype=np.float64)  # the limits, and the jump's place
            self._params.append(mine)
            f = filters[side]
            c = f.config
            if not all(isinstance(v, float) for v in (c.min_cutoff, c.beta, c.d_cutoff)):
                raise ValueError("the filter's settings are not floats")
            sides.append(
                (
                    fn, ddot, n, wrist, mine.ctypes.data, neutral, has_neutral,
                    self._last[k].ctypes.data, float(supervisor.config.max_wrist_speed),
                    f._bound[2].kernel.address, f._x.ctypes.data, f._dx.ctypes.data,
                    f._bound[2].kernel.two_pi,
                    c.min_cutoff, c.beta, c.d_cutoff, *self._chains[k].entry,
                    self._raw[k].ctypes.data,
                )
            )  # fmt: skip
        self._sides = (_Side * 2)(*(_Side(*s) for s in sides))
        self._ddot = sides[0][1]  # numpy's ddot, as the hand checks call it
        fn = lib.payload_intake_step
        fn.restype = ctypes.c_int
        fn.argtypes = [_P, _P, ctypes.c_int, _D, _D, _D, ctypes.c_int, _D, _D, ctypes.c_int]
        self._fn = fn
        self._tail: _Tail | None = None
        self._tail_kept: tuple | None = None
        self.rail = np.zeros(1)
        """The rail command the last tail wrote (:meth:`bind_tail`)."""
        self._call = functools.partial(fn, ctypes.addressof(self._sides), None, 0)
        self._call_tail = self._call
        numbers = lib.payload_intake_numbers
        numbers.restype = None
        numbers.argtypes = [_D, _D, _D, _D, _D, _P]
        self._numbers = numbers
        rail = lib.payload_tail_rail
        rail.restype = ctypes.c_int
        rail.argtypes = [_P, _P, _P, _P]
        self._rail_fn = rail

    def bind_tail(self, fresh: tuple[np.ndarray, np.ndarray], base: Any, rail: RailConfig) -> None:
        """The channels after a steady intake, run in the same call when :meth:`__call__`
        is asked for them: both pairs' solved commands ``fresh`` (the arrays the chains'
        solves write, the left hand's pair first) checked finite, the rail command of the
        filtered wrists (:func:`~payload.teleop.channels.rail_command` with the settings
        ``rail``, checked against it on :data:`RAIL_CHECKS` random wrists here; the
        result in :attr:`rail`) and the base channel's compiled step ``base`` (its
        ``entry``: the kernel, its arguments and its wrists' buffers) on them.

        Raises:
            ValueError: A part it cannot take (settings that are not floats, arrays of
                other layouts) or a rail command that differs from the Python's.
        """
        # unbound until the new parts pass: a call never runs a tail that failed
        self._tail, self._tail_kept, self._call_tail = None, None, self._call
        numbers = (rail.d_min, rail.d_max, rail.travel)
        if not all(type(v) is float for v in numbers):
            raise ValueError("the rail settings are not floats")
        for a in fresh:
            if not (a.dtype == np.float64 and a.ndim == 1 and a.flags.c_contiguous):
                raise ValueError("a solved command is not a contiguous float64 vector")
        if fresh[0].shape != fresh[1].shape:
            raise ValueError("the pairs' commands differ in length")
        fn, args, scalars, left, right = base.entry
        made = _Tail(
            fresh[0].ctypes.data, fresh[1].ctypes.data, fresh[0].shape[0], self._ddot,
            fn, args, scalars, left, right, *numbers, self.rail.ctypes.data,
        )  # fmt: skip
        for left, right in _rail_probes(rail, RAIL_CHECKS):
            try:
                want: float | None = rail_command(rail, left, right)
            except ChannelError:
                want = None
            got = self._rail(made, left, right)
            if (got is None) != (want is None) or (
                got is not None and np.float64(got).tobytes() != np.float64(want).tobytes()
            ):
                raise ValueError("the compiled rail command differs from the Python's")
        # taken together: the call, the structure it points to and the arrays it addresses
        self._tail, self._tail_kept = made, (fresh, base)
        self._call_tail = functools.partial(
            self._fn, ctypes.addressof(self._sides), ctypes.addressof(made), 1
        )

    def _rail(self, tail: _Tail, left: np.ndarray, right: np.ndarray) -> float | None:
        """``tail``'s rail command of two wrists (None: the distance is not finite)."""
        out = np.zeros(1)
        a, b = np.array(left, dtype=np.float64), np.array(right, dtype=np.float64)
        got = self._rail_fn(a.ctypes.data, b.ctypes.data, ctypes.addressof(tail), out.ctypes.data)
        return None if got else float(out[0])

    def rail_command(self, left: np.ndarray, right: np.ndarray) -> float | None:
        """The bound tail's rail command of two wrists (its check's side; None: the
        distance is not finite).

        Raises:
            ValueError: No tail bound.
        """
        if self._tail is None:
            raise ValueError("no tail bound")
        return self._rail(self._tail, left, right)

    def numbers(self, t: float, tf: float, tv: float, speed: float, cutoff: float) -> bytes:
        """The C's jump allowed, filter period and smoothing factor for these times (its
        self-check's side), as bytes."""
        out = np.zeros(3)
        self._numbers(t, tf, tv, speed, cutoff, out.ctypes.data)
        return out.tobytes()

    def __call__(
        self, frame: HandFrame, t: float, tail: bool = False
    ) -> tuple[Supervised, int] | None:
        """Take both hands of ``frame`` in at ``t`` (its stamp): the supervisor's verdict
        (no events: both hands valid) and which sides' chains took their hand (bit 0 the
        left, bit 1 the right; those pairs' solves wait in their retargeters:
        ``finish_step``); or None, nothing changed, where the Python path is to run.
        With ``tail`` (the caller made the bound base step ready: :meth:`bind_tail`), a
        step both chains took runs the tail as well: bit 2 set where it did (its rail
        command in :attr:`rail`), bits 3 and 4 the base kernel's mode."""
        if not isinstance(t, float):  # another type's arithmetic: the Python path's
            return None
        sup = self._supervisor
        status = sup.status
        st0, st1 = status["left"], status["right"]
        left, right = frame.left, frame.right
        if not (left.tracked and right.tracked) or st0.lost or st1.lost or t < sup.last_stamp:
            return None
        f0, f1 = self._filters
        if f0._t is None or f1._t is None:
            return None
        np.copyto(self._raw[0], left.joints)
        np.copyto(self._raw[1], right.joints)
        accepted = self._accepted
        for k, st in enumerate((st0, st1)):
            if st.last_valid is not accepted[k]:  # the Python path took a hand since
                if st.last_valid is not None:
                    np.copyto(self._last[k], st.last_valid.wrist)
                accepted[k] = st.last_valid
        for chain in self._chains:
            chain.load_held()
        taken = (self._call_tail if tail else self._call)(
            t,
            f0._t,
            st0.last_valid_stamp,
            st0.last_valid is not None,
            f1._t,
            st1.last_valid_stamp,
            st1.last_valid is not None,
        )
        if taken < 0:
            return None
        verdict = sup.accepted(frame)
        f0._t = f1._t = t
        accepted[0], accepted[1] = left, right
        return verdict, taken


CHECK_TIMES = 200
"""Random times of the intake's full self-check (:func:`compiled_hand_intake`)."""

RAIL_CHECKS = 200
"""Random wrist pairs the tail's rail command is checked on when bound
(:meth:`HandIntake.bind_tail`)."""


def _rail_probes(rail: RailConfig, n: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``n`` wrist pairs for the rail's check: apart by distances around and beyond the
    settings' range (both clamps, the ends themselves), one not finite."""
    rng = np.random.default_rng(0)
    lo, hi = rail.d_min, rail.d_max
    for k in range(n):
        left = rng.normal(scale=0.3, size=3)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        d = (lo, hi, 0.0)[k % 3] if k < 9 else float(rng.uniform(lo - 0.2, hi + 0.2))
        right = left + abs(d) * u
        if k == n - 1:
            right[1] = np.nan
        yield left, right


def _times(n: int) -> Iterator[tuple[float, float, float, float, float]]:
    """``n`` random (t, the filter's last time, the last valid frame's time, the wrist
    speed limit, the filter's cutoff) of the self-check, the same ones for the same ``n``."""
    rng = np.random.default_rng(0)
    for k in range(n):
        t = float(rng.uniform(0.0, 300.0))
        tf = t - (0.02, float(rng.uniform(1e-6, 0.5)))[k % 2]
        tv = t - float(rng.uniform(1e-6, 2.0))
        yield t, tf, tv, float(rng.uniform(0.1, 10.0)), float(rng.uniform(0.05, 5.0))


def _numbers(t: float, tf: float, tv: float, speed: float, cutoff: float) -> bytes:
    """:meth:`HandIntake.numbers` by the Python path's own functions."""
    return np.array([allowed_jump(speed, t - tv), t - tf, _alpha(cutoff, t - tf)]).tobytes()


@native.reported("hand intake")
def compiled_hand_intake(
    supervisor: TrackingSupervisor, filters: dict[str, OneEuroFilter], chains: tuple[Any, Any]
) -> HandIntake | None:
    """The pipeline's compiled hand intake, or None to run the Python path: a part not
    compiled or not running yet, no compiler, ``PAYLOAD_NATIVE=0``, a failed build, or a
    self-check whose jump allowed, filter period or smoothing factor differs from the
    Python's in a single bit on random times and settings (:data:`CHECK_TIMES`, or their
    first tenth once a full check passed, here or in an earlier process:
    :func:`payload.native.probes`)."""
    lib = native.load_kernel("hand_intake", SOURCE, "the hand intake", log)
    if lib is None:
        return None
    try:
        intake = HandIntake(lib, supervisor, filters, chains)
    except ValueError as exc:
        log.info("hand intake: Python (%s)", exc)
        return None

    def check(n: int) -> bool:
        return all(intake.numbers(*args) == _numbers(*args) for args in _times(n))

    if not native.self_checked(lib, "hand intake", CHECK_TIMES, check):
        log.warning("hand intake: Python (the compiled numbers differ)")
        return None
    return intake


__all__ = [
    "CHECK_TIMES",
    "SOURCE",
    "HandIntake",
    "compiled_hand_intake",
    "intake_objects",
    "intake_parts",
    "ready",
]
