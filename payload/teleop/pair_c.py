"""A pair's finger channel as one compiled call, with the numpy code's bits.

Each control step, for each finger pair with a tracked hand, the teleoperation pipeline
maps the hand to the pair's command: the hand's eq. 2 features
(:func:`~payload.teleop.pipeline.human_feature_vector`, compiled in
:mod:`payload.teleop.hand_c`), the calibrated targets
(:meth:`~payload.retarget.calibration.PairCalibration.to_targets`, compiled in
:mod:`payload.retarget.targets_c`), the posture reference
(:meth:`~payload.retarget.span_range.PairRange.posture`) and the eq. 3 solve (the
retargeter's compiled step). Each is one compiled call already; what remains between them
is Python: the features' copy, the targets' ``PairFeatures`` and their stacking again,
the posture's table lookup, the solver's input checks and copies.

Here one C call runs the chain: the hand features kernel, the targets kernel writing
into the solver's target input, the posture reference (Python's ``min``/``max`` tie rules
and ``bisect_left`` on the same table, the same products and sum as numpy's) into its
posture input, and the solver's step entry (the finiteness check and the anchor update
in C). The kernels are the very functions the Python path calls, reached through their
addresses, so the chain adds only the posture's arithmetic. It is checked against the
Python path when built: random hands (degenerate and non-finite ones among them) give the
same command, report, held command and solver anchor in every bit, or fail alike. A hand
any part refuses goes to the Python path, which raises its error (the pipeline's safety
event); without a compiler, a compiled part, or with ``PAYLOAD_NATIVE=0``, the Python path
runs.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from payload import native
from payload.retarget.features import N_FEATURES
from payload.teleop.hands import JOINTS_SHAPE

log = logging.getLogger(__name__)

SOURCE = r"""
#include <stdint.h>

typedef int (*features_fn)(void *, void *, const double *, const int64_t *, double, double *);
typedef int (*targets_fn)(void *, const double *, const double *, int, int64_t,
                          const double *, int, int64_t, const double *, double *);
typedef int (*step_fn)(const double **, double **, long long *, double *, int);

/* every field 8 bytes: the ctypes structure _Chain, in this order */
struct chain {
    void *features, *f_gemv, *f_ddot; const int64_t *idx; double eps; double *human;
    void *targets, *t_gemv; const double *consts, *rot; int64_t r_order, r_ld;
    const double *grot; int64_t g_order, g_ld;
    const double *spans, *postures; int64_t n_spans, n;
    double *q_in, *t_in, *r_in;
    void *step; const double **arg; double **res; long long *iw; double *w; int64_t mem;
};

/* 0: solved (the solver's outputs and anchor updated); 1: the hand's features (not finite
   or degenerate), 2: the targets, 3: the solver's inputs not finite; 4: the solver failed.
   Before a code other than 0 the held command and the solver's anchor are as they were:
   only the chain's own features, the solver's command, target and posture inputs (the
   next solve writes them anew) and, with 4, its outputs and work are written. */
int payload_pair_chain(const struct chain *c, const double *joints)
{
    if (((features_fn)c->features)(c->f_gemv, c->f_ddot, joints, c->idx, c->eps, c->human))
        return 1;
    if (((targets_fn)c->targets)(c->t_gemv, c->consts, c->rot, (int)c->r_order, c->r_ld,
                                 c->grot, (int)c->g_order, c->g_ld, c->human, c->t_in))
        return 2;
    /* PairRange.posture(span): s = min(max(span, spans[0]), spans[-1]) */
    const double *sp = c->spans;
    int64_t k = c->n_spans, n = c->n;
    double s = c->t_in[0];
    s = (sp[0] > s) ? sp[0] : s;
    s = (sp[k - 1] < s) ? sp[k - 1] : s;
    int64_t lo = 0, hi = k; /* bisect_left(spans, s) */
    while (lo < hi) {
        int64_t mid = (lo + hi) / 2;
        if (sp[mid] < s) lo = mid + 1; else hi = mid;
    }
    int64_t i = lo - 1;
    i = (i < 0) ? 0 : i;
    i = (i > k - 2) ? k - 2 : i;
    double w = (s - sp[i]) / (sp[i + 1] - sp[i]);
    const double *p0 = c->postures + i * n, *p1 = p0 + n;
    for (int64_t j = 0; j < n; j++) c->r_in[j] = (1.0 - w) * p0[j] + w * p1[j];
    int code = ((step_fn)c->step)(c->arg, c->res, c->iw, c->w, (int)c->mem);
    return code == 0 ? 0 : (code == 2 ? 3 : 4);
}
"""
"""The chain's C (:func:`payload.native.build_library` compiles it)."""

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double


class _Chain(ctypes.Structure):
    """``struct chain`` of :data:`SOURCE`."""

    _fields_ = [
        *((name, _P) for name in ("features", "f_gemv", "f_ddot", "idx")),
        ("eps", _D),
        *((name, _P) for name in ("human", "targets", "t_gemv", "consts", "rot")),
        ("r_order", _I),
        ("r_ld", _I),
        ("grot", _P),
        ("g_order", _I),
        ("g_ld", _I),
        ("spans", _P),
        ("postures", _P),
        ("n_spans", _I),
        ("n", _I),
        *((name, _P) for name in ("q_in", "t_in", "r_in", "step", "arg", "res", "iw", "w")),
        ("mem", _I),
    ]


class FingerChain:
    """One pair's finger channel (hand features, targets, posture reference, solve) as
    one C call.

    Args:
        lib: The chain's library (:data:`SOURCE`).
        features: The compiled hand features (:mod:`payload.teleop.hand_c`).
        targets: The pair calibration's compiled targets (:mod:`payload.retarget.targets_c`).
        pair_range: The pair's span range (its posture table).
        retargeter: The pair's retargeter, with a compiled step entry.

    Raises:
        ValueError: The retargeter has no compiled step entry, or the posture table is
            not what the solver's posture input takes.
    """

    def __init__(
        self, lib: ctypes.CDLL, features: Any, targets: Any, pair_range: Any, retargeter: Any
    ) -> None:
        stepping = retargeter.step_entry()
        if stepping is None:
            raise ValueError("the retargeter has no compiled step entry")
        entry, inputs = stepping
        q_in, t_in, r_in = inputs[:3]
        spans = np.ascontiguousarray(pair_range.spans, dtype=np.float64)
        postures = np.ascontiguousarray(pair_range.postures, dtype=np.float64)
        if postures.shape != (spans.size, r_in.size) or spans.size < 2:
            raise ValueError(f"posture table {postures.shape} for {r_in.size} joints")
        if t_in.size != N_FEATURES:  # what the features and targets kernels write
            raise ValueError(f"the solver takes {t_in.size} targets, not {N_FEATURES}")
        self.retargeter = retargeter
        self._q_in = q_in
        self._human = np.zeros(N_FEATURES)
        self._keep = (spans, postures, inputs, features, targets)
        self._chain = _Chain(
            *features.entry, self._human.ctypes.data, *targets.entry, spans.ctypes.data,
            postures.ctypes.data, spans.size, r_in.size, q_in.ctypes.data, t_in.ctypes.data,
            r_in.ctypes.data, *entry,
        )  # fmt: skip
        fn = lib.payload_pair_chain
        fn.restype = ctypes.c_int
        fn.argtypes = [_P, _P]
        self._call = functools.partial(fn, ctypes.addressof(self._chain))
        self.entry = (ctypes.cast(fn, _P).value, ctypes.addressof(self._chain))
        """For a caller that runs the chain from its own C (after :meth:`load_held`): the
        function and its chain's address; a hand's joints (25, 3) are its other argument."""

    def load_held(self) -> None:
        """Write the retargeter's held command into the solver's command input (the warm
        start), as a chain's call does first."""
        self._q_in[:] = self.retargeter.held_command

    def __call__(self, joints: np.ndarray) -> tuple[np.ndarray, Any] | None:
        """The pair's command and the solve's report for a hand's joints (25, 3), as
        ``PairRetargeter.solve`` returns them (the command now held), or None: nothing
        held or anchored changed, and the Python path is to run (it raises the error of a
        hand it refuses)."""
        j = joints
        if not (type(j) is np.ndarray and j.dtype == np.float64 and j.shape == JOINTS_SHAPE):
            return None
        if not j.flags.c_contiguous:
            return None
        self.load_held()
        if self._call(j.ctypes.data):
            return None
        return self.retargeter.finish_step()


CHECK_HANDS = 40
"""Random hands of the chain's full self-check (:func:`compiled_finger_chain`)."""


def _outcome(
    run: Callable[[np.ndarray], Any], joints: np.ndarray, retargeter: Any, inputs: list
) -> list[bytes] | None:
    """``run(joints)``'s command and report, the held command and the solver's inputs
    (its anchor among them) it leaves, as bytes; None if it refused the hand."""
    out = run(joints)
    if out is None:
        return None
    q, info = out
    held = retargeter.held_command
    return [q.tobytes(), repr(tuple(info)).encode(), held.tobytes(), *(a.tobytes() for a in inputs)]


@native.reported("finger chain")
def compiled_finger_chain(
    features: Any,
    targets: Any,
    pair_range: Any,
    retargeter: Any,
    reference: Callable[[np.ndarray], tuple[np.ndarray, Any] | None],
) -> FingerChain | None:
    """The compiled finger channel of one pair, or None to run ``reference`` (the Python
    path: features, targets, posture, solve; None for a hand it refuses): no compiled
    part (``features`` or ``targets`` None, no step entry), no compiler,
    ``PAYLOAD_NATIVE=0``, a failed build, or a self-check on random hands
    (:func:`payload.teleop.hand_c.random_hands`: :data:`CHECK_HANDS`, or their first tenth
    once a full check passed, here or in an earlier process: :func:`payload.native.probes`)
    whose command, report, held command or solver inputs differ from ``reference``'s in a
    single bit, or that one refuses and the other not. The retargeter's held command and
    solver inputs are as they were after the check."""
    if features is None or targets is None or retargeter.step_entry() is None:
        return None  # a part runs in numpy or CasADi's virtual machine: the Python path
    lib = native.load_kernel("pair_chain", SOURCE, "the finger chain", log)
    if lib is None:
        return None
    try:
        chain = FingerChain(lib, features, targets, pair_range, retargeter)
    except ValueError as exc:
        log.warning("finger chain: Python (%s)", exc)
        return None
    from payload.teleop.hand_c import random_hands

    inputs = chain._keep[2]
    restore = retargeter.checkpoint()

    def check(n: int) -> bool:
        with np.errstate(all="ignore"):
            for joints in random_hands(n, seed=1):
                want = _outcome(reference, joints, retargeter, inputs)
                restore()
                got = _outcome(chain, joints, retargeter, inputs)
                restore()
                if got != want:
                    return False
        return True

    try:
        same = native.self_checked(lib, "finger chain", CHECK_HANDS, check)
    finally:
        restore()
    if not same:
        log.warning("finger chain: Python (the compiled chain differs)")
        return None
    return chain


__all__ = ["CHECK_HANDS", "SOURCE", "FingerChain", "compiled_finger_chain"]
