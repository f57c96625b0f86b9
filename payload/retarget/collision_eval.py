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

from payload.retarget.collision import _TINY, _segment_distance_ca
from payload.retarget.features import PairKinematics
from payload.retarget.objective import RetargetConfig
from payload.retarget.symbolic import PointChain, chain_point


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
        self._shared: dict[object, ca.Function] = {}

    def __len__(self) -> int:
        return len(self.terms)

    def keys(self) -> list[tuple[int, bool, int]]:
        """Per group ``(capsule, box, other)``: the capsule, whether the other is a box,
        and the other capsule's or box's index."""
        col = self.pk.collision
        return [
            (col.terms[t[0]].capsule, col.terms[t[0]].box, col.terms[t[0]].other)
            for t in self.terms
        ]

    def ends_function(self) -> ca.Function:
        """``q -> ends (6 per capsule)``: every capsule's axis ends in the base frame."""
        q = ca.SX.sym("q", self.pk.n)
        ends = [chain_point(c, q) for pair in self.pk.collision._chains for c in pair]
        return ca.Function("capsule_ends", [q], [ca.vertcat(*ends)], {"cse": True})

    def vjp_function(self) -> ca.Function:
        """``(q, v) -> (d ends / d q)^T v``: a gradient with respect to the ends, in q."""
        q, v = ca.SX.sym("q", self.pk.n), ca.SX.sym("v", 6 * len(self.pk.collision.capsules))
        ends = self.ends_function()(q)
        return ca.Function("capsule_vjp", [q, v], [ca.jtimes(ends, q, v, True)], {"cse": True})

    def branch(self, g: int, config: RetargetConfig, name: str) -> ca.Function:
        """``(ends_1 (6), ends_2 (6 or 0), bound) -> (S_g, dS_g/d ends_1, dS_g/d ends_2,
        smallest clearance)`` of group g, evaluated; ``S_g`` is the sum of
        ``(band - clearance)_+^2`` over its terms.

        The arithmetic is one shared function per kind of group (a capsule against two
        to k sample points on one box, or a capsule pair), called with the group's
        geometry as constants: one copy of the code for every group, so the generated
        solver stays small enough to stay in the instruction cache."""
        col = self.pk.collision
        cap, box, other = self.keys()[g]
        e1, e2 = ca.MX.sym("e1", 6), ca.MX.sym("e2", 0 if box else 6)
        bound = ca.MX.sym("bound")
        if box:
            bx = col.boxes[other]
            fractions = [col.terms[k].fraction for k in self.terms[g]]
            fn = self._shared_box(len(fractions), config)
            s, d1, m = fn(
                e1,
                ca.DM(bx.centre),
                ca.DM(bx.rotation),
                ca.DM(bx.half),
                col.capsules[cap].radius,
                ca.DM(fractions),
            )
            d2 = ca.MX(0, 1)
        else:
            fn = self._shared_pair(config)
            radii = col.capsules[cap].radius + col.capsules[other].radius
            s, d1, d2, m = fn(e1, e2, radii)
        return ca.Function(name, [e1, e2, bound], [s, d1, d2, m])

    def _shared_box(self, k: int, config: RetargetConfig) -> ca.Function:
        """The group function of a capsule against k points on one box (see :meth:`branch`)."""
        key = ("box", k)
        if key not in self._shared:
            e1, centre = ca.SX.sym("e1", 6), ca.SX.sym("centre", 3)
            rot, half = ca.SX.sym("rotation", 3, 3), ca.SX.sym("half", 3)
            radius, fr = ca.SX.sym("radius"), ca.SX.sym("fractions", k)
            a, b = e1[:3], e1[3:]
            dist = []
            for i in range(k):
                local = ca.mtimes(rot.T, a + fr[i] * (b - a) - centre)
                qv = ca.fabs(local) - half
                out = ca.fmax(qv, 0)
                dist.append(ca.sqrt(ca.dot(out, out) + _TINY) + ca.fmin(ca.mmax(qv), 0) - radius)
            c = ca.vertcat(*dist) - self.pk.collision.margin
            over = ca.fmax(config.collision_band - c, 0.0)
            s = ca.dot(over, over)
            self._shared[key] = ca.Function(
                f"group_box_{k}",
                [e1, centre, rot, half, radius, fr],
                [s, ca.gradient(s, e1), ca.mmin(c)],
                {"cse": True},
            )
        return self._shared[key]

    def _shared_pair(self, config: RetargetConfig) -> ca.Function:
        """The group function of a capsule pair (see :meth:`branch`)."""
        if "pair" not in self._shared:
            e1, e2, radii = ca.SX.sym("e1", 6), ca.SX.sym("e2", 6), ca.SX.sym("radii")
            dist = _segment_distance_ca(e1[:3], e1[3:], e2[:3], e2[3:]) - radii
            c = dist - self.pk.collision.margin
            over = ca.fmax(config.collision_band - c, 0.0)
            s = over * over
            self._shared["pair"] = ca.Function(
                "group_pair",
                [e1, e2, radii],
                [s, ca.gradient(s, e1), ca.gradient(s, e2), c],
                {"cse": True},
            )
        return self._shared["pair"]

    def skip(self, name: str, box: bool) -> ca.Function:
        """``(ends_1, ends_2, bound) -> (0, 0, 0, bound)``: a group proven beyond the band."""
        e1, e2 = ca.SX.sym("e1", 6), ca.SX.sym("e2", 0 if box else 6)
        bound = ca.SX.sym("bound")
        zero = ca.SX.zeros
        return ca.Function(name, [e1, e2, bound], [ca.SX(0.0), zero(6), zero(e2.shape[0]), bound])

    def penalty_function(self, config: RetargetConfig) -> ca.Function:
        """``(q, pre-bounds) -> (S, dS/dq, group minima)``: the groups whose bound is below
        the band evaluated on the capsule ends computed once, the others skipped."""
        n, ng = self.pk.n, len(self)
        ncap = len(self.pk.collision.capsules)
        q, pre = ca.MX.sym("q", n), ca.MX.sym("pre", ng)
        e = self.ends_function()(q)
        caps = [e[6 * i : 6 * i + 6] for i in range(ncap)]
        grads: list = [0.0] * ncap
        skips = {box: self.skip(f"group_skip_{int(box)}", box) for box in (False, True)}
        total, mins = 0.0, []
        for g, (cap, box, other) in enumerate(self.keys()):
            branch = self.branch(g, config, f"group_branch_{g}")
            cond = ca.Function.conditional(f"group_{g}", [branch], skips[box])
            e2 = ca.MX(0, 1) if box else caps[other]
            s_g, d1, d2, m_g = cond(pre[g] >= config.collision_band, caps[cap], e2, pre[g])
            total = total + s_g
            mins.append(m_g)
            grads[cap] = grads[cap] + d1
            if not box:
                grads[other] = grads[other] + d2
        v = ca.vertcat(*[gr if isinstance(gr, ca.MX) else ca.MX.zeros(6) for gr in grads])
        dq = self.vjp_function()(q, v)
        return ca.Function("collision_penalty", [q, pre], [total, dq, ca.vertcat(*mins)])


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
    unknown), and the output ``bounds`` are valid at ``q``. When every group's bound
    is beyond the band, the collision part is not evaluated at all.
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
    far = ca.mmin(pre) >= config.collision_band
    base = ca.Function("evaluate_base", [q, par, qa, lba], [r, jac, pre, far], {"cse": True})
    rs, js = ca.SX.sym("r", r.sparsity()), ca.SX.sym("J", jac.sparsity())
    ss, ds, ms = ca.SX.sym("s"), ca.SX.sym("ds", n), ca.SX.sym("mins", ng)
    scale = config.w_c / config.collision_band**2
    rc, jc = scale * ss, scale * ds
    cost, grad, hess = _cost_terms(ca.vertcat(rs, rc), ca.vertcat(js, jc.T))
    combine = ca.Function(
        "evaluate_combine", [rs, js, ss, ds, ms], [cost, grad, hess, ca.mmin(ms)], {"cse": True}
    )
    qs, pres = ca.SX.sym("q", n), ca.SX.sym("pre", ng)
    none_near = ca.Function("collision_far", [qs, pres], [ca.SX(0.0), ca.SX.zeros(n), pres])
    penalty = ca.Function.conditional(
        "collision_part", [groups.penalty_function(config)], none_near
    )
    sym = ca.MX.sym
    qm, pm, qam, lbm = sym("q", n), sym("p", par.shape[0]), sym("q_anchor", n), sym("bounds", ng)
    rm, jm, prem, farm = base(qm, pm, qam, lbm)
    total, dtotal, mins = penalty(farm, qm, prem)
    cost_m, grad_m, hess_m, clear_m = combine(rm, jm, total, dtotal, mins)
    fn = ca.Function("evaluate", [qm, pm, qam, lbm], [cost_m, grad_m, hess_m, clear_m, mins])
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
