"""Pair features of the paper's eq. 2 and their analytic Jacobians.

For a finger pair with fingertips p_1, p_2 and distal joints a_1, a_2::

    d = p_2 - p_1,  l = |d|,  d_hat = d / l,  c = (p_1 + p_2) / 2,
    u_i = (p_i - a_i) / |p_i - a_i|,  u = [u_1; u_2]

The same function serves the robot (points from forward kinematics, in the pair's
base frame) and the human (thumb and index points in the calibrated wrist frame).
Stacked as a vector the features are ``[l, d_hat (3), c (3), u (6)]``, shape (13,).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from payload.kinematics import Kinematics
from payload.retarget.errors import RetargetError
from payload.retarget.hand import HandDescription, PairDescription, load_hand
from payload.vecmath import all_finite, read_only
from payload.vecmath import norm as vec_norm

N_FEATURES = 13
"""Length of a stacked feature vector: span 1, direction 3, centre 3, distal directions 6."""

_EPS = 1e-12

COLLISION_MODEL: list[Any] = []
"""The self-collision model class (:class:`payload.retarget.collision.PairCollision`),
named by :func:`payload.retarget.collision.register` (an explicit call: that module
imports this one, so this one cannot import it)."""


class PairFeatures(NamedTuple):
    """Pair geometry of eq. 2 (also used for the mapped robot targets, the overbars).

    Attributes:
        span: Fingertip separation l [m].
        direction: Unit direction d_hat from fingertip 1 to fingertip 2, shape (3,).
        centre: Midpoint c of the fingertips, shape (3,) [m].
        distal: Distal-link directions [u_1; u_2], shape (6,), each a unit vector.
    """

    span: float
    direction: np.ndarray
    centre: np.ndarray
    distal: np.ndarray

    def as_vector(self) -> np.ndarray:
        """The stacked vector ``[l, d_hat, c, u]``, shape (13,)."""
        out = np.empty(N_FEATURES)
        out[0] = self.span
        out[1:4] = self.direction
        out[4:7] = self.centre
        out[7:13] = self.distal
        return out

    @classmethod
    def from_vector(cls, v: np.ndarray) -> PairFeatures:
        """Split a stacked vector of shape (13,) into features."""
        v = np.asarray(v, dtype=float).reshape(-1)
        if v.shape != (N_FEATURES,):
            raise RetargetError(f"pair features: expected {N_FEATURES} values, got {v.size}")
        return cls(float(v[0]), v[1:4].copy(), v[4:7].copy(), v[7:13].copy())

    def frozen(self) -> PairFeatures:
        """These features with read-only float64 copies of the vectors (a calibration's or
        a pair range's, which the compiled targets copy when they are built)."""
        return PairFeatures(
            float(self.span), read_only(self.direction), read_only(self.centre),
            read_only(self.distal),
        )  # fmt: skip


def as_feature_vector(targets: PairFeatures | np.ndarray, what: str = "targets") -> np.ndarray:
    """Targets as a finite stacked vector of shape (13,).

    Raises:
        RetargetError: Wrong size, or a NaN or infinite component (named).
    """
    if isinstance(targets, PairFeatures):
        try:
            v = targets.as_vector()
        except ValueError as exc:
            raise RetargetError(f"{what}: malformed pair features ({exc})") from exc
    else:
        v = np.asarray(targets, dtype=float).reshape(-1)
        if v.shape != (N_FEATURES,):
            raise RetargetError(f"{what}: expected {N_FEATURES} values, got {v.size}")
    if not np.isfinite(v).all():
        raise RetargetError(f"{what}: {_nonfinite_names(v)} not finite")
    return v


_FEATURE_NAMES = (
    "span",
    *(f"direction[{i}]" for i in range(3)),
    *(f"centre[{i}]" for i in range(3)),
    *(f"distal[{i}]" for i in range(6)),
)


def _nonfinite_names(v: np.ndarray) -> str:
    bad = np.flatnonzero(~np.isfinite(v))
    return ", ".join(f"{_FEATURE_NAMES[i]}={v[i]}" for i in bad)


def _unit(v: np.ndarray, what: str) -> tuple[np.ndarray, float]:
    n = vec_norm(v)  # np.linalg.norm's bits, without its overhead
    if not n > _EPS:
        raise RetargetError(f"pair features: {what} has zero length (degenerate geometry)")
    return v / n, n


def features_from_points(
    p1: np.ndarray, p2: np.ndarray, a1: np.ndarray, a2: np.ndarray
) -> PairFeatures:
    """Eq. 2 from fingertip points ``p1, p2`` and distal-joint points ``a1, a2``, each (3,) [m].

    Raises:
        RetargetError: A non-finite point, coincident fingertips, or a fingertip on its
            distal joint.
    """
    pts = np.asarray([p1, p2, a1, a2], dtype=float)
    if pts.shape != (4, 3):
        raise RetargetError(f"pair features: expected four 3-D points, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise RetargetError("pair features: a point is not finite")
    d_hat, span = _unit(pts[1] - pts[0], "the fingertip separation")
    u1, _ = _unit(pts[0] - pts[2], "the distal link of finger 1")
    u2, _ = _unit(pts[1] - pts[3], "the distal link of finger 2")
    return PairFeatures(span, d_hat, 0.5 * (pts[0] + pts[1]), np.concatenate([u1, u2]))


def features_jacobian_from_points(
    points: np.ndarray, jacobians: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stacked features and their Jacobian from points and point Jacobians.

    Args:
        points: ``[p1, p2, a1, a2]``, shape (4, 3) [m].
        jacobians: Their Jacobians with respect to the n joints, shape (4, 3, n).

    Returns:
        ``(f, J)``: features of shape (13,) and ``J = df/dq`` of shape (13, n).
    """
    p1, p2, a1, a2 = points
    jp1, jp2, ja1, ja2 = jacobians
    n = jacobians.shape[2]
    f = np.empty(N_FEATURES)
    jac = np.empty((N_FEATURES, n))
    d = p2 - p1
    d_hat, span = _unit(d, "the fingertip separation")
    jd = jp2 - jp1
    f[0] = span
    jac[0] = d_hat @ jd
    f[1:4] = d_hat
    jac[1:4] = (jd - np.outer(d_hat, d_hat @ jd)) / span
    f[4:7] = 0.5 * (p1 + p2)
    jac[4:7] = 0.5 * (jp1 + jp2)
    for k, (p, a, jp, ja) in enumerate(((p1, a1, jp1, ja1), (p2, a2, jp2, ja2))):
        u, norm = _unit(p - a, f"the distal link of finger {k + 1}")
        je = jp - ja
        f[7 + 3 * k : 10 + 3 * k] = u
        jac[7 + 3 * k : 10 + 3 * k] = (je - np.outer(u, u @ je)) / norm
    return f, jac


class PairKinematics:
    """Forward kinematics of one finger pair with Pinocchio, in the pair's base frame.

    The pair's joint vector ``q`` has shape (n,) (n = 8 for our fingers): finger 1's
    joints, then finger 2's, as the hand description lists them. Joints outside the
    pair sit at their neutral value; they do not change base-frame features.

    Args:
        hand: Hand description, or ``None`` for ours.
        pair: Pair name (``L`` or ``R`` for ours); ``None``: the hand's first pair.
        kin: A :class:`~payload.kinematics.Kinematics` of the hand's URDF to share.

    Attributes:
        hand: The hand description.
        desc: The pair's description.
        kin: The Pinocchio wrapper.
        lower: Lower joint limits, shape (n,) [rad or m].
        upper: Upper joint limits, shape (n,).
        rest: Rest posture, shape (n,).
    """

    def __init__(
        self,
        hand: HandDescription | None = None,
        pair: str | None = None,
        kin: Kinematics | None = None,
    ) -> None:
        self.hand: HandDescription = hand if hand is not None else load_hand()
        self.desc: PairDescription = self.hand.pair(pair or next(iter(self.hand.pairs)))
        self.kin: Kinematics = kin if kin is not None else self.hand.kinematics()
        d = self.desc
        self._qidx = self.kin.q_indices(d.joints)
        self._vidx = self.kin.v_indices(d.joints)
        self._fids = [self.kin.frame_id(f) for f in (*d.tips, *d.distals)]
        self.lower: np.ndarray = self.kin.lower[self._qidx]
        self.upper: np.ndarray = self.kin.upper[self._qidx]
        self._q0 = self.kin.neutral()
        base = self.kin.frame_placement(self._q0, d.base)
        self._rot_t = base.rotation.T.copy()
        self._origin = base.translation.copy()
        rest = np.zeros(self.n) if d.rest is None else np.asarray(d.rest, dtype=float)
        self.rest: np.ndarray = np.clip(rest, self.lower, self.upper)

    @property
    def name(self) -> str:
        """The pair's name."""
        return self.desc.name

    @property
    def collision(self) -> Any:
        """The pair's self-collision model (:class:`payload.retarget.collision.PairCollision`),
        built on first use and kept."""
        model = self.__dict__.get("_collision")
        if model is None:
            if not COLLISION_MODEL:
                raise RetargetError(
                    "no self-collision model registered: call "
                    "payload.retarget.collision.register() first (the retargeters do)"
                )
            model = self.__dict__["_collision"] = COLLISION_MODEL[0](self)
        return model

    @property
    def n(self) -> int:
        """Number of pair joints."""
        return len(self._qidx)

    @property
    def joints(self) -> tuple[str, ...]:
        """The pair's joint names, in the order of ``q``."""
        return self.desc.joints

    @property
    def range(self) -> np.ndarray:
        """Joint ranges ``upper - lower``, shape (n,) (the normalisation of eq. 3)."""
        return self.upper - self.lower

    def check_q(self, q: np.ndarray, what: str = "q") -> np.ndarray:
        """``q`` as a float array of shape (n,), finite.

        Raises:
            RetargetError: Wrong shape or a NaN or infinite value.
        """
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (self.n,):
            raise RetargetError(f"{what}: expected {self.n} joint values, got {q.size}")
        if not all_finite(q):
            bad = [self.joints[i] for i in np.flatnonzero(~np.isfinite(q))]
            raise RetargetError(f"{what}: non-finite value for {', '.join(bad)}")
        return q

    def full_configuration(self, q: np.ndarray) -> np.ndarray:
        """The model configuration with the pair joints set to ``q``, shape (nq,)."""
        full = self._q0.copy()
        full[self._qidx] = q
        return full

    def points(self, q: np.ndarray) -> np.ndarray:
        """``[p1, p2, a1, a2]`` in the base frame, shape (4, 3) [m]."""
        q = self.check_q(q)
        world = self.kin.frame_positions(self.full_configuration(q), self._fids)
        return (world - self._origin) @ self._rot_t.T

    def points_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points, shape (4, 3) [m], and their Jacobians, shape (4, 3, n), in the base frame."""
        q = self.check_q(q)
        world, jac = self.kin.frame_jacobians(self.full_configuration(q), self._fids)
        pts = (world - self._origin) @ self._rot_t.T
        jac = np.einsum("ij,kjn->kin", self._rot_t, jac[:, :, self._vidx])
        return pts, jac

    def points_batch(self, qs: np.ndarray) -> np.ndarray:
        """Points for many pair configurations: qs (m, n) -> (m, 4, 3) [m]."""
        qs = np.asarray(qs, dtype=float)
        if qs.ndim != 2 or qs.shape[1] != self.n:
            raise RetargetError(f"configurations: expected shape (m, {self.n}), got {qs.shape}")
        full = np.tile(self._q0, (qs.shape[0], 1))
        full[:, self._qidx] = qs
        world = self.kin.frame_positions_batch(full, self._fids)
        return (world - self._origin) @ self._rot_t.T

    def features(self, q: np.ndarray) -> PairFeatures:
        """Eq. 2 features of the pair at ``q`` (shape (n,)), in the base frame."""
        p = self.points(q)
        return features_from_points(p[0], p[1], p[2], p[3])

    def features_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stacked features, shape (13,), and their analytic Jacobian, shape (13, n)."""
        pts, jac = self.points_jacobian(q)
        return features_jacobian_from_points(pts, jac)

    def features_batch(self, qs: np.ndarray) -> np.ndarray:
        """Stacked features for many configurations: qs (m, n) -> (m, 13)."""
        pts = self.points_batch(qs)
        return np.array([features_from_points(*p).as_vector() for p in pts])
