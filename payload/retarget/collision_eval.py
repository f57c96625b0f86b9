"""One residual evaluation of the production solver, with the collision terms skipped
when a bound proves them far.

Eq. 3's residuals and their Jacobian are always evaluated. The clearance terms of
:class:`~payload.retarget.collision.PairCollision` are split into **groups**: the terms
of one capsule against one structure box, and each capsule pair of the two fingers. A
group is evaluated only when a lower bound of its clearance is below the penalty band;
otherwise it contributes nothing to the penalty residual (its terms are all beyond the
band, where the penalty and its gradient vanish) and keeps its bound. The bound is
carried from a point where it is known (the **anchor**: the solve's input, then every
accepted iterate): a group's clearance cannot fall faster than ``L_g . |q - q_anchor|``,
with ``L_g`` (shape (n,)) a configuration-independent bound on how far a joint moves a
point of the group's capsules: for a revolute joint, the sum of the link offsets from
the joint to the capsule end (and of the travel of prismatic joints between them), so
it bounds the point's distance from the joint axis; for a prismatic joint, 1. Signed
distances to a box and segment distances are 1-Lipschitz in the points, so
``clearance(q) >= bound(q_anchor) - L_g . |q - q_anchor|``. An exact evaluation resets
the bound to the group's smallest clearance.

The result is the dense computation's (the same penalty and gradient, the same sign of
the smallest clearance, so the same accepted steps); the reported smallest clearance is
exact whenever it is below the band, and otherwise a lower bound that is itself at least
the band.
"""

from __future__ import annotations

from collections import defaultdict

import casadi as ca
import numpy as np

from payload.retarget.features import PairKinematics
from payload.retarget.objective import RetargetConfig
from payload.retarget.symbolic import PointChain


def chain_lipschitz(chain: PointChain, pk: PairKinematics) -> np.ndarray:
    """Per pair joint, a bound on how far the chain's point moves per unit of that joint
    [m/rad or m/m], valid in every configuration, shape (n,)."""
    out = np.zeros(pk.n)
    reach = float(np.linalg.norm(chain.point))  # from the last joint's origin to the point
    for jt in reversed(chain.joints):
        if jt.kind == "revolute":
            out[jt.index] = max(out[jt.index], reach)
        else:
            out[jt.index] = max(out[jt.index], 1.0)
            reach += float(max(abs(pk.lower[jt.index]), abs(pk.upper[jt.index])))
        reach += float(np.linalg.norm(jt.translation))
    return out


class CollisionGroups:
    """The clearance terms of a pair in groups, each with its motion bound.

    Attributes:
        terms: Per group, the indices of its terms in ``pk.collision.terms``.
        lipschitz: Per group, ``L_g``, shape (groups, n).
    """

    def __init__(self, pk: PairKinematics) -> None:
        col = pk.collision
        self.pk = pk
        caps = [np.maximum(chain_lipschitz(a, pk), chain_lipschitz(b, pk)) for a, b in col._chains]
        by_key: dict[tuple, list[int]] = defaultdict(list)
        for k, t in enumerate(col.terms):
            by_key[(t.capsule, t.box, t.other)].append(k)
        keys = sorted(by_key)
        self.terms: tuple[tuple[int, ...], ...] = tuple(tuple(by_key[k]) for k in keys)
        rows = [caps[c] if box else caps[c] + caps[o] for c, box, o in keys]
        self.lipschitz = np.array(rows).reshape(len(keys), pk.n)

    def __len__(self) -> int:
        return len(self.terms)

    def branch(self, g: int, config: RetargetConfig, name: str) -> ca.Function:
        """``(q, bound) -> (S_g, dS_g/dq (n), smallest clearance)`` of group g, evaluated;
        ``S_g`` is the sum of ``(band - clearance)_+^2`` over its terms."""
        col = self.pk.collision
        q = ca.SX.sym("q", self.pk.n)
        bound = ca.SX.sym("bound")
        terms = tuple(col.terms[k] for k in self.terms[g])
        c = col.distances_expr(q, terms) - col.margin
        over = ca.fmax(config.collision_band - c, 0.0)
        s = ca.dot(over, over)
        return ca.Function(name, [q, bound], [s, ca.gradient(s, q), ca.mmin(c)], {"cse": True})

    def skip(self, name: str) -> ca.Function:
        """``(q, bound) -> (0, 0, bound)``: a group proven beyond the band."""
        q = ca.SX.sym("q", self.pk.n)
        bound = ca.SX.sym("bound")
        return ca.Function(name, [q, bound], [ca.SX(0.0), ca.SX.zeros(self.pk.n), bound])


def evaluate_function(
    pk: PairKinematics,
    config: RetargetConfig,
    r: ca.SX,
    jac: ca.SX,
    q: ca.SX,
    par: ca.SX,
) -> tuple[ca.Function, int]:
    """``evaluate(q, par, q_anchor, bounds) -> (cost, g, H, clearance, bounds)`` and the
    number of groups (0 without collision terms: ``bounds`` is then empty).

    ``r``/``jac`` are eq. 3's residuals and Jacobian in ``q`` and ``par``; ``bounds``
    (groups,) are lower bounds of the groups' clearances valid at ``q_anchor`` (``-inf``:
    unknown), and the output ``bounds`` are valid at ``q``.
    """
    n = pk.n
    groups = CollisionGroups(pk) if config.collisions and pk.collision.available else None
    ng = 0 if groups is None else len(groups)
    qa, lba = ca.SX.sym("q_anchor", n), ca.SX.sym("bounds", ng)
    if groups is None:
        cost, grad, hess = _cost_terms(r, jac)
        fn = ca.Function(
            "evaluate", [q, par, qa, lba], [cost, grad, hess, ca.SX(1.0), lba], {"cse": True}
        )
        return fn, 0
    pre = lba - ca.mtimes(ca.DM(groups.lipschitz), ca.fabs(q - qa))
    base = ca.Function("evaluate_base", [q, par, qa, lba], [r, jac, pre], {"cse": True})
    rs, js = ca.SX.sym("r", r.sparsity()), ca.SX.sym("J", jac.sparsity())
    ss, ds, ms = ca.SX.sym("s"), ca.SX.sym("ds", n), ca.SX.sym("mins", ng)
    scale = config.w_c / config.collision_band
    root = ca.sqrt(ss + 1e-12)
    rc = scale * (root - 1e-6)
    jc = (scale * 0.5 / root) * ds
    cost, grad, hess = _cost_terms(ca.vertcat(rs, rc), ca.vertcat(js, jc.T))
    combine = ca.Function(
        "evaluate_combine", [rs, js, ss, ds, ms], [cost, grad, hess, ca.mmin(ms)], {"cse": True}
    )
    sym = ca.MX.sym
    qm, pm, qam, lbm = sym("q", n), sym("p", par.shape[0]), sym("q_anchor", n), sym("bounds", ng)
    rm, jm, prem = base(qm, pm, qam, lbm)
    skip = groups.skip("group_skip")
    total, dtotal, mins = 0.0, 0.0, []
    for g in range(ng):
        cond = ca.Function.conditional(
            f"group_{g}", [groups.branch(g, config, f"branch_{g}")], skip
        )
        s_g, d_g, m_g = cond(prem[g] >= config.collision_band, qm, prem[g])
        total, dtotal = total + s_g, dtotal + d_g
        mins.append(m_g)
    mins_mx = ca.vertcat(*mins)
    cost_m, grad_m, hess_m, clear_m = combine(rm, jm, total, dtotal, mins_mx)
    fn = ca.Function("evaluate", [qm, pm, qam, lbm], [cost_m, grad_m, hess_m, clear_m, mins_mx])
    return fn, ng


def _cost_terms(r: ca.SX, jac: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
    """Soft-L1 cost, its gradient and the IRLS curvature ``J^T diag(1/sqrt(1+r^2)) J``."""
    s1 = ca.sqrt(1.0 + r * r)
    w1 = 1.0 / s1  # rho'(r^2), the IRLS weight
    cost = ca.sum1(s1 - 1.0)
    grad = ca.mtimes(jac.T, w1 * r)
    jw = ca.mtimes(ca.diag(ca.sqrt(w1)), jac)
    hess = ca.vec(ca.densify(ca.mtimes(jw.T, jw)))
    return cost, grad, hess
