"""Pinch-to-open calibration: human thumb-index features -> robot pair targets.

Two steps:

1. :func:`pair_range` finds, once per hand and pair, what the robot pair can do:
   its minimum and maximum fingertip span and a one-parameter family of postures
   ``q_ref(l)`` (the posture reference) whose span is ``l``:

   * maximum span: ``max l(q)`` over the joint box, with each fingertip kept in front
     of its finger's first joint along the finger's rest direction (so a finger
     cannot curl back through the structure), solved by SLSQP with analytic
     gradients from 16 deterministic starts (the rest posture, the all-lower-limits
     corner of the box, halfway between the two, and seeded random postures);
   * minimum span: ``max(2 * tip_radius, min l(q))``: the pads touch before the
     points can meet (the kinematic minimum is found the same way);
   * with ``collisions`` (off by default), every posture above also keeps the hand's
     self-collision margin (:mod:`payload.retarget.collision`, plus 0.1 mm), so the
     range ends at the largest collision-free span and starts at the smallest;
   * postures: for 65 spans evenly spaced between the two, the posture closest to the
     rest posture in range-normalised joints with exactly that span (SLSQP,
     continuation from the rest span outward). ``q_ref(l)`` interpolates linearly.

2. :func:`calibrate` takes the operator's pinch and open features (thumb = finger 1,
   index = finger 2, in the calibrated wrist frame) and returns a
   :class:`PairCalibration`: the opening ``alpha = (l_h - l_pinch) / (l_open - l_pinch)``
   (clipped to [0, 1]) maps to the span ``l_min + alpha (l_max - l_min)``, so the
   calibrated pinch and open poses give the robot's minimum and maximum span exactly;
   directions are rotated by the rotation that best aligns the human's direction
   features at the two poses with the robot's at ``q_ref(l_min)`` and ``q_ref(l_max)``
   (Wahba's problem, SVD); the centre follows the robot's centre along the same
   opening plus the human's deviation from the calibrated centre, rotated and scaled.
"""

from __future__ import annotations

import functools
import os
import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from payload.numerics import single_threaded_numerics
from payload.retarget.errors import RetargetError
from payload.retarget.features import PairFeatures, PairKinematics, as_feature_vector

__all__ = ["PairCalibration", "PairRange", "calibrate", "pair_range", "wahba_rotation"]

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

    def posture(self, span: float) -> np.ndarray:
        """Posture reference ``q_ref`` for a commanded span [m] (clipped to the range), (n,)."""
        s = float(np.clip(span, self.spans[0], self.spans[-1]))
        i = int(np.clip(np.searchsorted(self.spans, s) - 1, 0, len(self.spans) - 2))
        w = (s - self.spans[i]) / (self.spans[i + 1] - self.spans[i])
        return (1.0 - w) * self.postures[i] + w * self.postures[i + 1]


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

        from payload.retarget.casadi_solver import _compiled_or_none

        q = ca.SX.sym("q", pk.n)
        c = pk.collision.clearance_expr(q) - _TABLE_BUFFER
        name = "payload_clearance_" + "".join(ch if ch.isalnum() else "_" for ch in pk.name)
        self.function = ca.Function(name, [q], [c, ca.densify(ca.jacobian(c, q))], {"cse": True})
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
    return _load_or_compute(pk, seed, collisions)


def _compute_pair_range(pk: PairKinematics, seed: int, collisions: bool) -> PairRange:
    # single-threaded BLAS: the same range, to the last bit, whoever computes it first
    # (a trial, a report or a bench; the disk cache keeps the first)
    with single_threaded_numerics():
        return _compute_pair_range_here(pk, seed, collisions)


def _compute_pair_range_here(pk: PairKinematics, seed: int, collisions: bool) -> PairRange:
    bounds = list(zip(pk.lower, pk.upper))
    origins, dirs = _front_constraints(pk)
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


_CACHE_VERSION = "pair-range-1"


def _disk_key(pk: PairKinematics, seed: int, collisions: bool) -> str:
    import hashlib
    import inspect
    import sys

    from payload.retarget import collision

    parts = [
        _CACHE_VERSION,
        Path(pk.kin.urdf).read_text(),
        repr(pk.desc),
        repr(seed),
        repr(collisions),
        repr(pk.hand.collision_margin),
        # the code that computes it: a change of it or of the collision model is a new key
        inspect.getsource(sys.modules[__name__]),
        inspect.getsource(collision),
    ]
    if pk.hand.design is not None:
        parts.append(Path(pk.hand.design).read_text())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:24]


def _load_or_compute(pk: PairKinematics, seed: int, collisions: bool) -> PairRange:
    """The range from the on-disk cache (next to the compiled solvers), else computed."""
    from payload.retarget.casadi_solver import cache_dir

    try:
        key = _disk_key(pk, seed, collisions)
    except OSError:  # the model's files are gone (a temporary URDF): no key, no cache
        return _compute_pair_range(pk, seed, collisions)
    path = cache_dir() / f"pair_range_{key}.npz"
    try:
        with np.load(path) as z:
            spans, postures = z["spans"], z["postures"]
            lo, hi, kmin = (float(v) for v in z["scalars"])
        return PairRange(
            pk.name,
            lo,
            hi,
            kmin,
            spans,
            postures,
            pk.features(postures[0]),
            pk.features(postures[-1]),
        )
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        pass  # missing or unreadable (a torn write): computed again and rewritten
    rg = _compute_pair_range(pk, seed, collisions)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # one writer per process and thread (campaign workers run a retargeter per thread)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp.npz")
        np.savez(
            tmp,
            spans=rg.spans,
            postures=rg.postures,
            scalars=np.array([rg.span_min, rg.span_max, rg.span_min_kinematic]),
        )
        os.replace(tmp, path)
    except OSError:  # pragma: no cover - a read-only cache only costs the recomputation
        pass
    return rg


def wahba_rotation(human: np.ndarray, robot: np.ndarray) -> np.ndarray:
    """Rotation R minimising ``sum |robot_i - R human_i|^2`` over unit vectors, (3, 3).

    Args:
        human: Vectors in the human wrist frame, shape (k, 3).
        robot: Matching vectors in the robot pair frame, shape (k, 3).
    """
    b = np.asarray(robot).T @ np.asarray(human)
    u, _, vt = np.linalg.svd(b)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    return u @ s @ vt


@dataclass(frozen=True)
class PairCalibration:
    """The mapping from human thumb-index features to one robot pair's targets.

    Attributes:
        range: The robot pair's span range and posture family.
        human_pinch: The operator's calibrated pinch features (wrist frame).
        human_open: The operator's calibrated open features (wrist frame).
        rotation: Rotation from the wrist frame to the pair's base frame, (3, 3).
        centre_gain: Scale of the operator's centre motion onto the robot [-].
    """

    range: PairRange
    human_pinch: PairFeatures
    human_open: PairFeatures
    rotation: np.ndarray
    centre_gain: float

    def opening(self, human_span: float) -> float:
        """Calibrated opening in [0, 1] of a human span [m] (0 = pinch, 1 = open)."""
        lo, hi = self.human_pinch.span, self.human_open.span
        return float(np.clip((human_span - lo) / (hi - lo), 0.0, 1.0))

    def to_targets(self, human: PairFeatures | np.ndarray) -> PairFeatures:
        """Robot targets ``(l_bar, d_bar, c_bar, u_bar)`` for human features (wrist frame).

        Raises:
            RetargetError: A NaN or infinite or malformed feature.
        """
        h = PairFeatures.from_vector(as_feature_vector(human, "human features"))
        rg, rot = self.range, self.rotation
        alpha = self.opening(h.span)
        span = rg.span_min + alpha * (rg.span_max - rg.span_min)
        c_robot = (1.0 - alpha) * rg.pinch.centre + alpha * rg.open.centre
        c_human = (1.0 - alpha) * self.human_pinch.centre + alpha * self.human_open.centre
        centre = c_robot + self.centre_gain * rot @ (h.centre - c_human)
        distal = np.concatenate([rot @ h.distal[:3], rot @ h.distal[3:]])
        return PairFeatures(float(span), rot @ h.direction, centre, distal)

    def posture_reference(self, span: float) -> np.ndarray:
        """Posture reference ``q_ref`` consistent with a commanded span [m], shape (n,)."""
        return self.range.posture(span)

    def command(self, human: PairFeatures | np.ndarray) -> tuple[PairFeatures, np.ndarray]:
        """Targets and the matching posture reference for human features."""
        targets = self.to_targets(human)
        return targets, self.posture_reference(targets.span)


def calibrate(
    pinch: PairFeatures | np.ndarray,
    open_: PairFeatures | np.ndarray,
    robot: PairRange,
    rotation: np.ndarray | None = None,
    centre_gain: float | None = None,
) -> PairCalibration:
    """Calibrate one pair from the operator's pinch and open poses.

    Args:
        pinch: Human thumb-index features at the calibration pinch (wrist frame).
        open_: Human features at the calibration full opening (wrist frame).
        robot: The robot pair's range (:func:`pair_range`).
        rotation: Wrist-to-pair-frame rotation (3, 3); ``None``: the Wahba alignment of
            the human's direction features (d, u_1, u_2) at the two poses with the
            robot's at its minimum- and maximum-span postures.
        centre_gain: Scale of the human centre motion; ``None``: the span ratio
            ``(l_max - l_min) / (l_open - l_pinch)``.

    Raises:
        RetargetError: Non-finite features, an open span not larger than the pinch
            span by 1 mm, or a rotation that is not a rotation matrix.
    """
    hp = PairFeatures.from_vector(as_feature_vector(pinch, "pinch features"))
    ho = PairFeatures.from_vector(as_feature_vector(open_, "open features"))
    if ho.span < hp.span + 1e-3:
        raise RetargetError(
            f"calibration: the open span ({ho.span * 1e3:.1f} mm) must exceed the pinch span "
            f"({hp.span * 1e3:.1f} mm) by at least 1 mm"
        )
    if rotation is None:
        human = np.vstack(
            [v.reshape(-1, 3) for v in (hp.direction, hp.distal, ho.direction, ho.distal)]
        )
        rb = robot
        rob = np.vstack(
            [
                v.reshape(-1, 3)
                for v in (rb.pinch.direction, rb.pinch.distal, rb.open.direction, rb.open.distal)
            ]
        )
        rotation = wahba_rotation(human, rob)
    rotation = np.asarray(rotation, dtype=float)
    if (
        rotation.shape != (3, 3)
        or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
        or np.linalg.det(rotation) < 0
    ):
        raise RetargetError("calibration: rotation must be a 3x3 rotation matrix")
    if centre_gain is None:
        centre_gain = (robot.span_max - robot.span_min) / (ho.span - hp.span)
    if not np.isfinite(centre_gain) or centre_gain < 0:
        raise RetargetError("calibration: centre_gain must be finite and non-negative")
    return PairCalibration(robot, hp, ho, rotation, float(centre_gain))
