"""CasADi expression graphs of a pair's kinematics and of eq. 3.

pip's Pinocchio has no CasADi bindings, so the forward kinematics is rebuilt here
from the Pinocchio model's data: for every joint between the pair's base frame and a
fingertip or distal frame, its placement in the parent joint frame
(``model.jointPlacements``), its kind and its axis (from the joint's motion subspace),
then the frame's placement on its joint (``model.frames[i].placement``). Any URDF whose
pair joints are one-coordinate revolute or prismatic joints is supported.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from payload.retarget.features import N_FEATURES, PairKinematics
from payload.retarget.objective import RetargetConfig


@dataclass(frozen=True)
class ChainJoint:
    """One joint of a kinematic chain, as the symbolic forward kinematics uses it.

    Attributes:
        rotation: Joint placement rotation in the parent joint frame, shape (3, 3).
        translation: Joint placement translation [m], shape (3,).
        kind: ``revolute`` or ``prismatic``.
        axis: Unit axis in the joint frame, shape (3,).
        index: Index of the joint in the pair's q vector.
    """

    rotation: np.ndarray
    translation: np.ndarray
    kind: str
    axis: np.ndarray
    index: int


@dataclass(frozen=True)
class PointChain:
    """The chain from a pair's base frame to one point (a fingertip or a distal joint).

    The point in the base frame is ``base_inv * J_1(q) * ... * J_k(q) * point``.

    Attributes:
        base_rotation: Rotation of the inverse base-frame placement, shape (3, 3).
        base_translation: Translation of the inverse base-frame placement [m], shape (3,).
        joints: The joints, from the base outward.
        point: The frame's origin in its parent joint frame [m], shape (3,).
    """

    base_rotation: np.ndarray
    base_translation: np.ndarray
    joints: tuple[ChainJoint, ...]
    point: np.ndarray


def point_chains(pk: PairKinematics) -> tuple[PointChain, ...]:
    """The four chains ``p1, p2, a1, a2`` of a pair, read from its Pinocchio model."""
    kin, d = pk.kin, pk.desc
    model = kin.model
    index = {name: i for i, name in enumerate(d.joints)}
    base = model.frames[kin.frame_id(d.base)].placement.inverse()
    chains = []
    for frame in (*d.tips, *d.distals):
        joints = []
        for j in kin.chain(d.base, frame):
            kind, axis = kin.joint_motion(j)
            pl = model.jointPlacements[j]
            joints.append(
                ChainJoint(
                    np.array(pl.rotation),
                    np.array(pl.translation),
                    kind,
                    axis,
                    index[model.names[j]],
                )
            )
        fr = model.frames[kin.frame_id(frame)]
        chains.append(
            PointChain(
                np.array(base.rotation),
                np.array(base.translation),
                tuple(joints),
                np.array(fr.placement.translation),
            )
        )
    return tuple(chains)


def frame_point_chain(pk: PairKinematics, frame: str, point: np.ndarray) -> PointChain:
    """The chain from the pair's base frame to a point fixed in ``frame`` (a link)."""
    kin, d = pk.kin, pk.desc
    model = kin.model
    index = {name: i for i, name in enumerate(d.joints)}
    base = model.frames[kin.frame_id(d.base)].placement.inverse()
    joints = []
    for j in kin.chain(d.base, frame):
        kind, axis = kin.joint_motion(j)
        pl = model.jointPlacements[j]
        name = model.names[j]
        if name not in index:
            raise ValueError(f"joint {name!r} above {frame!r} is not a joint of pair {d.name!r}")
        joints.append(
            ChainJoint(np.array(pl.rotation), np.array(pl.translation), kind, axis, index[name])
        )
    fr = model.frames[kin.frame_id(frame)]
    return PointChain(
        np.array(base.rotation),
        np.array(base.translation),
        tuple(joints),
        np.array(fr.placement.act(np.asarray(point, dtype=float))),
    )


def _skew(k: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])


def _lin(m: np.ndarray, x: list, offset: np.ndarray | None = None) -> list:
    """m @ x (+ offset) for a numeric matrix m and symbolic 3-vector x, skipping zeros."""
    out = []
    for i in range(3):
        acc = None
        for j in range(3):
            c = float(m[i, j])
            if c == 0.0:
                continue
            term = x[j] if c == 1.0 else (-x[j] if c == -1.0 else c * x[j])
            acc = term if acc is None else acc + term
        if offset is not None and float(offset[i]) != 0.0:
            acc = float(offset[i]) if acc is None else acc + float(offset[i])
        out.append(0.0 if acc is None else acc)
    return out


def chain_point(chain: PointChain, q: ca.SX | ca.MX) -> ca.SX | ca.MX:
    """Symbolic position of a chain's point in the base frame, shape (3, 1) [m]."""
    x: list = [float(v) for v in chain.point]
    for jt in reversed(chain.joints):
        qi = q[jt.index]
        if jt.kind == "revolute":
            k = _skew(jt.axis)
            k2 = k @ k
            s, omc = ca.sin(qi), 1.0 - ca.cos(qi)
            kx, k2x = _lin(k, x), _lin(k2, x)
            x = [x[i] + s * kx[i] + omc * k2x[i] for i in range(3)]
        else:
            x = [x[i] + float(jt.axis[i]) * qi for i in range(3)]
        x = _lin(jt.rotation, x, jt.translation)
    x = _lin(chain.base_rotation, x, chain.base_translation)
    return ca.vertcat(*x)


def pair_points(pk: PairKinematics, q: ca.SX | ca.MX) -> list:
    """Symbolic ``[p1, p2, a1, a2]`` in the pair's base frame, each (3, 1) [m]."""
    return [chain_point(c, q) for c in point_chains(pk)]


def points_function(pk: PairKinematics) -> ca.Function:
    """CasADi function ``q (n) -> points (3, 4)``: columns p1, p2, a1, a2 [m]."""
    q = ca.SX.sym("q", pk.n)
    return ca.Function(
        "pair_points", [q], [ca.horzcat(*pair_points(pk, q))], ["q"], ["points"], {"cse": True}
    )


def features_expr(points: list) -> ca.SX:
    """Eq. 2 as a symbolic stacked vector ``[l, d_hat, c, u]``, shape (13, 1)."""
    p1, p2, a1, a2 = points
    d = p2 - p1
    span = ca.norm_2(d)
    e1, e2 = p1 - a1, p2 - a2
    return ca.vertcat(span, d / span, 0.5 * (p1 + p2), e1 / ca.norm_2(e1), e2 / ca.norm_2(e2))


def features_function(pk: PairKinematics) -> ca.Function:
    """CasADi function ``q (n) -> features (13)``."""
    q = ca.SX.sym("q", pk.n)
    return ca.Function(
        "pair_features", [q], [features_expr(pair_points(pk, q))], ["q"], ["f"], {"cse": True}
    )


def uses_collisions(pk: PairKinematics, config: RetargetConfig) -> bool:
    """True when the solve keeps a self-collision margin (config on, geometry present)."""
    return bool(config.collisions) and pk.collision.available


def clearance_and_penalty(
    pk: PairKinematics, config: RetargetConfig, q: ca.SX | ca.MX
) -> tuple[ca.SX | ca.MX, ca.SX | ca.MX] | None:
    """The clearances (k, 1) [m] and the collision penalty residual (1, 1), or ``None``.

    The residual is ``w_c sum((band - clearance)_+^2) / band^2``: it and its gradient
    vanish continuously as every clearance reaches the band (no kink at the band's edge,
    where the constrained optimum tends to lie), and it is ``w_c`` per term at the margin.
    """
    if not uses_collisions(pk, config):
        return None
    c = pk.collision.clearance_expr(q)
    over = ca.fmax(config.collision_band - c, 0.0)
    return c, (config.w_c / config.collision_band**2) * ca.dot(over, over)


def residuals_expr(
    pk: PairKinematics,
    config: RetargetConfig,
    q: ca.SX,
    targets: ca.SX,
    q_ref: ca.SX,
    q_prev: ca.SX,
) -> ca.SX:
    """Eq. 3's residual vector, shape (13 + 2n, 1), as a CasADi expression; with the
    collision penalty residual appended (shape (14 + 2n, 1)) when :func:`uses_collisions`."""
    r = paper_residuals_expr(pk, config, q, targets, q_ref, q_prev)
    cp = clearance_and_penalty(pk, config, q)
    return r if cp is None else ca.vertcat(r, cp[1])


def paper_residuals_expr(
    pk: PairKinematics,
    config: RetargetConfig,
    q: ca.SX,
    targets: ca.SX,
    q_ref: ca.SX,
    q_prev: ca.SX,
) -> ca.SX:
    """Eq. 3's own residual vector, shape (13 + 2n, 1)."""
    f = features_expr(pair_points(pk, q))
    scales = config.feature_scales()
    inv_range = 1.0 / pk.range
    geo = [float(scales[k]) * (f[k] - targets[k]) for k in range(N_FEATURES)]
    post = [config.w_p * float(inv_range[i]) * (q[i] - q_ref[i]) for i in range(pk.n)]
    temp = [config.w_t * float(inv_range[i]) * (q[i] - q_prev[i]) for i in range(pk.n)]
    return ca.vertcat(*geo, *post, *temp)


def objective_function(pk: PairKinematics, config: RetargetConfig) -> ca.Function:
    """CasADi function ``(q, targets, q_ref, q_prev) -> (cost, residuals, jacobian)``.

    ``cost`` is eq. 3's value, ``residuals`` shape (13 + 2n,), ``jacobian`` shape
    (13 + 2n, n) by algorithmic differentiation of the expression graph.
    """
    n = pk.n
    q, t = ca.SX.sym("q", n), ca.SX.sym("targets", N_FEATURES)
    qr, qp = ca.SX.sym("q_ref", n), ca.SX.sym("q_prev", n)
    r = residuals_expr(pk, config, q, t, qr, qp)
    cost = ca.sum1(ca.sqrt(1.0 + r**2) - 1.0)
    return ca.Function(
        "pair_objective",
        [q, t, qr, qp],
        [cost, r, ca.jacobian(r, q)],
        ["q", "targets", "q_ref", "q_prev"],
        ["cost", "r", "J"],
        {"cse": True},
    )
