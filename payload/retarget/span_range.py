"""The robot side of the pinch-to-open calibration: what a finger pair can do.

:func:`pair_range` finds, once per hand and pair, the pair's minimum and maximum
fingertip span and a one-parameter family of postures ``q_ref(l)`` (the posture
reference) whose span is ``l``:

* maximum span: ``max l(q)`` over the joint box, with each fingertip kept in front
  of its finger's first joint along the finger's rest direction (so a finger
  cannot curl back through the structure), solved by SLSQP with analytic
  gradients from 16 deterministic starts (the rest posture, the all-lower-limits
  corner of the box, halfway between the two, and seeded random postures);
* minimum span: ``max(2 * tip_radius, min l(q))``: the pads touch before the
  points can meet (the kinematic minimum is found the same way);
* with ``collisions`` (off by default), every posture above also keeps the hand's
  self-collision margin (:mod:`payload.retarget.collision`, plus 0.1 mm), so the
  range ends at the largest collision-free span and starts at the smallest (the two
  pad links of the pair keep no margin, so with our hand that is still the pads
  touching, 2 * tip_radius);
* postures: for 65 spans evenly spaced between the two, the posture closest to the
  rest posture in range-normalised joints with exactly that span (SLSQP,
  continuation from the rest span outward). ``q_ref(l)`` interpolates linearly.

The result is kept on disk (:mod:`payload.retarget.range_cache`).
"""

from __future__ import annotations

import bisect
import functools
import sys
from dataclasses import dataclass

import numpy as np

from payload.numerics import single_threaded_numerics
from payload.retarget.collision import register as register_collision_model
from payload.retarget.errors import RetargetError
from payload.retarget.features import PairFeatures, PairKinematics
from payload.retarget.range_cache import load_or_compute
from payload.vecmath import read_only

__all__ = ["PairRange", "pair_range"]

_N_POSTURES = 65
_N_STARTS = 16


@dataclass(frozen=True)
class PairRange:
    """What a robot pair can do: its span range and the posture reference family.

    Attributes:
        pair: Pair name.
        span_min: Minimum usable span [m]: ``max(2 * tip_radius, span_min_kinematic)``.
        span_max: Maximum span [m].
        span_min_kinematic: Smallest fingertip-point distance over the box [m].
        spans: Spans of the posture table, shape (k,) [m], increasing.
        postures: Postures of the table, shape (k, n): ``span(postures[i]) = spans[i]``.
        pinch: Robot features at the minimum-span posture.
        open: Robot features at the maximum-span posture.
    """

    pair: str
    span_min: float
    span_max: float
    span_min_kinematic: float
    spans: np.ndarray
    postures: np.ndarray
    pinch: PairFeatures
    open: PairFeatures

    def __post_init__(self) -> None:
        # read-only copies: the compiled finger chain reads the table in place and the
        # targets kernel copies the features when built, while the Python path caches the
        # spans; a change afterwards would reach one and not the other
        for name in ("spans", "postures"):
            object.__setattr__(self, name, read_only(getattr(self, name)))
        for name in ("pinch", "open"):
            object.__setattr__(self, name, getattr(self, name).frozen())

    def posture(self, span: float) -> np.ndarray:
        """Posture reference ``q_ref`` for a commanded span [m] (clipped to the range), (n,)."""
        # on Python floats (twice a control step): the same IEEE operations as
        # np.clip / np.searchsorted on the table, without their call overhead
        spans = self._span_list
        s = min(max(float(span), spans[0]), spans[-1])
        i = min(max(bisect.bisect_left(spans, s) - 1, 0), len(spans) - 2)
        w = (s - spans[i]) / (spans[i + 1] - spans[i])
        return (1.0 - w) * self.postures[i] + w * self.postures[i + 1]

    @functools.cached_property
    def _span_list(self) -> list[float]:
        return [float(s) for s in self.spans]


def _front_constraints(pk: PairKinematics) -> tuple[np.ndarray, np.ndarray]:
    """Origins of each finger's first joint and its unit rest direction, both (2, 3)."""
    kin, d = pk.kin, pk.desc
    origins, dirs = [], []
    pts = pk.points(pk.rest)
    base = kin.frame_placement(kin.neutral(), d.base)
    for i in range(2):
        first = kin.chain(d.base, d.tips[i])[0]
        world = kin.frame_placement(
            pk.full_configuration(pk.rest), kin.model.names[first]
        ).translation
        o = base.rotation.T @ (world - base.translation)
        v = pts[i] - o
        origins.append(o)
        dirs.append(v / np.linalg.norm(v))
    return np.array(origins), np.array(dirs)


def _starts(pk: PairKinematics, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    fixed = [pk.rest, pk.lower.copy(), np.clip(0.5 * (pk.lower + pk.rest), pk.lower, pk.upper)]
    rand = pk.lower + rng.random((_N_STARTS - len(fixed), pk.n)) * pk.range
    return np.vstack([*fixed, rand])


class _Clearance:
    """The pair's self-collision clearances and their Jacobian, compiled once."""

    def __init__(self, pk: PairKinematics) -> None:
        import casadi as ca

        from payload.retarget.compiled import _compiled_or_none

        q = ca.MX.sym("q", pk.n)  # shared functions per kind of term: small C
        c = pk.collision.clearance_expr(q) - _TABLE_BUFFER
        name = "payload_clearance_" + "".join(ch if ch.isalnum() else "_" for ch in pk.name)
        self.function = ca.Function(name, [q], [c, ca.densify(ca.jacobian(c, q))])
        self.k = c.shape[0]
        self._c = _compiled_or_none(self.function)

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._c is None:
            c, j = self.function(q)
            return np.array(c).reshape(-1), np.array(j)
        self._c.inputs[0][:] = q
        self._c()
        out = self._c.outputs
        return out[0].copy(), out[1].reshape((self.k, -1), order="F").copy()


_TABLE_BUFFER = 1e-4
"""Clearance [m] the calibration's postures keep beyond the margin (interpolation slack)."""


@functools.lru_cache(maxsize=16)
def _pair_range_cached(pk: PairKinematics, seed: int, collisions: bool = False) -> PairRange:
    return load_or_compute(
        pk, seed, collisions, _compute_pair_range, PairRange, [sys.modules[__name__]]
    )


def _compute_pair_range(pk: PairKinematics, seed: int, collisions: bool) -> PairRange:
    # single-threaded BLAS: the same range, to the last bit, whoever computes it first
    # (a trial, a report or a bench; the disk cache keeps the first)
    with single_threaded_numerics():
        return _compute_pair_range_here(pk, seed, collisions)


def _compute_pair_range_here(pk: PairKinematics, seed: int, collisions: bool) -> PairRange:
    from scipy.optimize import minimize  # ~0.4 s of imports, only on a cache miss

    bounds = list(zip(pk.lower, pk.upper))
    origins, dirs = _front_constraints(pk)
    register_collision_model()
    clear = _Clearance(pk) if collisions and pk.collision.available else None
    extra = (
        []
        if clear is None
        else [{"type": "ineq", "fun": lambda q: clear(q)[0], "jac": lambda q: clear(q)[1]}]
    )

    def free(q: np.ndarray) -> bool:
        return clear is None or bool(clear(q)[0].min() >= -1e-7)

    def span_and_grad(q: np.ndarray) -> tuple[float, np.ndarray]:
        f, jac = pk.features_jacobian(q)
        return float(f[0]), jac[0]

    def front(q: np.ndarray) -> np.ndarray:
        p = pk.points(q)
        return np.einsum("ij,ij->i", p[:2] - origins, dirs)

    def front_jac(q: np.ndarray) -> np.ndarray:
        _, jac = pk.points_jacobian(q)
        return np.einsum("ij,ijn->in", dirs, jac[:2])

    front_c = {"type": "ineq", "fun": front, "jac": front_jac}
    starts = _starts(pk, seed)

    # Maximum span (workspace-constrained), multi-start SLSQP.
    best_q, best = None, -np.inf
    for q0 in starts:
        if np.any(front(q0) < 0) or not free(q0):
            continue
        res = minimize(
            lambda q: tuple(-v for v in span_and_grad(q)),
            q0,
            jac=True,
            bounds=bounds,
            constraints=[front_c, *extra],
            method="SLSQP",
            options={"maxiter": 200, "ftol": 1e-12},
        )
        q = np.clip(res.x, pk.lower, pk.upper)
        if np.all(front(q) >= -1e-9) and free(q) and pk.features(q).span > best:
            best_q, best = q, pk.features(q).span
    if best_q is None:  # pragma: no cover - the rest posture always satisfies the constraint
        raise RetargetError(f"pair {pk.name}: no start posture keeps the fingers in front")
    span_max, q_open = best, best_q

    # Kinematic minimum span: the squared distance is smooth where the span is not.
    def sq(q: np.ndarray) -> tuple[float, np.ndarray]:
        p, jac = pk.points_jacobian(q)
        d = p[1] - p[0]
        return float(d @ d), 2.0 * d @ (jac[1] - jac[0])

    if clear is None:
        kin_min = min(
            float(np.sqrt(max(minimize(sq, q0, jac=True, bounds=bounds, method="L-BFGS-B").fun, 0)))
            for q0 in starts
        )
    else:  # the smallest span among collision-free postures
        kin_min = np.inf
        for q0 in starts:
            if not free(q0):
                continue
            res = minimize(
                sq,
                q0,
                jac=True,
                bounds=bounds,
                constraints=extra,
                method="SLSQP",
                options={"maxiter": 300, "ftol": 1e-14},
            )
            q = np.clip(res.x, pk.lower, pk.upper)
            if free(q):
                kin_min = min(kin_min, pk.features(q).span)
    span_min = max(kin_min, 2.0 * pk.desc.tip_radius)
    if span_max <= span_min + 1e-3:
        raise RetargetError(
            f"pair {pk.name}: the span range [{span_min:.4f}, {span_max:.4f}] m is too small"
        )

    # Posture table: closest posture to rest (range-normalised) with each span.
    inv = 1.0 / pk.range
    spans = np.linspace(span_min, span_max, _N_POSTURES)
    postures = np.empty((_N_POSTURES, pk.n))
    rest_span = pk.features(pk.rest).span

    def solve_at(span: float, q0: np.ndarray) -> np.ndarray:
        # without the clearance constraints first; with them only if that answer needs them.
        # SLSQP can stall from the neighbouring posture on a very different design: then
        # from the rest and the widest posture too (the check below judges the result)
        for start in (q0, pk.rest, q_open):
            q = _solve_at(span, start, [])
            if not free(q):
                q = _solve_at(span, start, extra)
            if abs(span_and_grad(q)[0] - span) <= 1e-5:
                break
        return q

    def _solve_at(span: float, q0: np.ndarray, more: list) -> np.ndarray:
        res = minimize(
            lambda q: (float(np.sum(((q - pk.rest) * inv) ** 2)), 2.0 * (q - pk.rest) * inv**2),
            q0,
            jac=True,
            bounds=bounds,
            constraints=[
                {
                    "type": "eq",
                    "fun": lambda q: np.array([span_and_grad(q)[0] - span]),
                    "jac": lambda q: span_and_grad(q)[1][None, :],
                },
                front_c,
                *more,
            ],
            method="SLSQP",
            options={"maxiter": 300, "ftol": 1e-12},
        )
        return np.clip(res.x, pk.lower, pk.upper)

    order_up = [i for i in range(_N_POSTURES) if spans[i] >= rest_span]
    order_down = [i for i in reversed(range(_N_POSTURES)) if spans[i] < rest_span]
    for order in (order_up, order_down):
        q_prev = pk.rest
        for i in order:
            q_prev = q_open if i == _N_POSTURES - 1 else solve_at(spans[i], q_prev)
            postures[i] = q_prev
    if clear is not None:
        spans, postures = _refine(spans, postures, clear, solve_at)
        worst = min(float(clear(q)[0].min()) for q in postures)
        if worst < -1e-6:
            raise RetargetError(
                f"pair {pk.name}: a calibration posture is {-worst * 1e3:.2f} mm inside the "
                "self-collision margin"
            )
    errors = np.abs(pk.features_batch(postures)[:, 0] - spans)
    if errors.max() > 1e-5:
        bad = int(errors.argmax())
        raise RetargetError(
            f"pair {pk.name}: no posture found with span {spans[bad]:.4f} m "
            f"(off by {errors[bad] * 1e3:.2f} mm)"
        )
    return PairRange(
        pair=pk.name,
        span_min=float(span_min),
        span_max=float(span_max),
        span_min_kinematic=float(kin_min),
        spans=spans,
        postures=postures,
        pinch=pk.features(postures[0]),
        open=pk.features(postures[-1]),
    )


def _refine(
    spans: np.ndarray, postures: np.ndarray, clear: _Clearance, solve_at: object
) -> tuple[np.ndarray, np.ndarray]:
    """Insert postures where interpolating between neighbours would leave the margin."""
    spans, postures = list(spans), list(postures)
    i = 0
    while i < len(spans) - 1 and len(spans) < 4 * _N_POSTURES:
        ws = np.linspace(0.0, 1.0, 9)[1:-1]
        mids = [(1 - w) * postures[i] + w * postures[i + 1] for w in ws]
        if min(float(clear(q)[0].min()) for q in mids) >= -_TABLE_BUFFER:
            i += 1
            continue
        span = 0.5 * (spans[i] + spans[i + 1])
        if spans[i + 1] - spans[i] < 1e-5:
            i += 1
            continue
        spans.insert(i + 1, span)
        postures.insert(i + 1, solve_at(span, 0.5 * (postures[i] + postures[i + 1])))  # type: ignore[operator]
    return np.array(spans), np.array(postures)


def pair_range(pk: PairKinematics, seed: int = 0, *, collisions: bool = False) -> PairRange:
    """The pair's span range and posture family (computed once per pair object and seed,
    and kept on disk beside the compiled solvers, keyed by the URDF, the pair, the margin,
    the design and this code).

    Args:
        pk: The pair's kinematics.
        seed: Seed of the random starts.
        collisions: Restrict the range and the postures to configurations that keep the
            hand's self-collision margin (:mod:`payload.retarget.collision`), so the
            operator's full opening maps to the largest collision-free span; no effect
            on a hand without collision geometry. Off by default, like
            ``RetargetConfig.collisions``.

    Raises:
        RetargetError: The optimisation finds no usable range or posture.
    """
    return _pair_range_cached(pk, seed, bool(collisions))
