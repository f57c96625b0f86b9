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
"""
"""The intake's C (:func:`payload.native.build_library` compiles it)."""

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
_SIDE_FIELDS = (
    "check:p ddot:p n:i wrist:i params:p neutral:p has_neutral:i last:p max_speed:d "
    "euro:p x:p dx:p two_pi:d min_cutoff:d beta:d d_cutoff:d chain:p ctx:p raw:p"
)
"""``struct side`` of :data:`SOURCE`, field by field (p: pointer, i: int64, d: double)."""


class _Side(ctypes.Structure):
    """``struct side`` of :data:`SOURCE`."""

    _fields_ = [
        (name, {"p": _P, "i": _I, "d": _D}[kind])
        for name, kind in (field.split(":") for field in _SIDE_FIELDS.split())
    ]


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
        fn = lib.payload_intake
        fn.restype = ctypes.c_int
        fn.argtypes = [_P, _D, _D, _D, ctypes.c_int, _D, _D, ctypes.c_int]
        self._call = functools.partial(fn, ctypes.addressof(self._sides))
        numbers = lib.payload_intake_numbers
        numbers.restype = None
        numbers.argtypes = [_D, _D, _D, _D, _D, _P]
        self._numbers = numbers

    def numbers(self, t: float, tf: float, tv: float, speed: float, cutoff: float) -> bytes:
        """The C's jump allowed, filter period and smoothing factor for these times (its
        self-check's side), as bytes."""
        out = np.zeros(3)
        self._numbers(t, tf, tv, speed, cutoff, out.ctypes.data)
        return out.tobytes()

    def __call__(self, frame: HandFrame, t: float) -> tuple[Supervised, int] | None:
        """Take both hands of ``frame`` in at ``t`` (its stamp): the supervisor's verdict
        (no events: both hands valid) and which sides' chains took their hand (bit 0 the
        left, bit 1 the right; those pairs' solves wait in their retargeters:
        ``finish_step``); or None, nothing changed, where the Python path is to run."""
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
        taken = self._call(
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
