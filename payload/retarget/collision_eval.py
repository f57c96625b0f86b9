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
the bound to the group's smallest clearance. A group the carried bound does not prove far
is checked next by its **midpoint bound** at the current capsule ends
(:meth:`CollisionGroups.midpoint_bound`), and evaluated exactly only if that is below
the band too.

Besides the penalty and its gradient, the collision part returns the sum of
``grad c grad c^T`` over the terms in the band: the curvature of the penalty's sum of
squares that the single penalty row's Gauss-Newton term does not see
(:func:`evaluate_function` adds it).

This module writes the skipping as nested ``casadi.Function.conditional`` calls
(:meth:`CollisionGroups.penalty_function`, what CasADi's virtual machine runs); with a C
compiler the solver runs the same computation as one C loop
(:mod:`payload.retarget.collision_c`).

The result is the dense computation's (the same penalty and gradient, the same sign of
the smallest clearance, so the same accepted steps); the reported smallest clearance is
exact whenever it is below the band, and otherwise a lower bound that is itself at least
the band.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import casadi as ca
import numpy as np

from payload.retarget.collision_distance import (
    _TINY,
    _point_segment_ca,
    _point_segment_np,
    _segment_distance_ca,
    box_sdf,
    segment_box_distance_expr,
)
from payload.retarget.features import PairKinematics
from payload.retarget.objective import RetargetConfig
from payload.retarget.symbolic import PointChain

_SLACK = 1e-9
"""Added to the midpoint bounds' reach [m]: covers rounding (and the ``1e-18`` under the
distances' square roots)."""


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
        self._shared: dict[object, Any] = {}
        if any(len(t) != 1 for t in self.terms):  # pragma: no cover - a model change
            raise AssertionError("collision groups expect one term per capsule and box or pair")

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
        """``q -> ends (6 per capsule)``: :meth:`PairCollision.ends_function
        <payload.retarget.collision.PairCollision.ends_function>`."""
        return self.pk.collision.ends_function()

    def ends_jacobian_function(self) -> ca.Function:
        """``q -> (ends_0, ..., ends_k, J_0, ..., J_k)``: each capsule's ends (6) and their
        Jacobian in q (dense, shape (6, n)), one output each so callers pass them on
        without slicing."""
        q = ca.SX.sym("q", self.pk.n)
        ends = self.ends_function()(q)
        jac = ca.densify(ca.jacobian(ends, q))
        ncap = len(self.pk.collision.capsules)
        outs = [ends[6 * i : 6 * i + 6] for i in range(ncap)]
        outs += [jac[6 * i : 6 * i + 6, :] for i in range(ncap)]
        return ca.Function("capsule_ends_jacobian", [q], outs, {"cse": True})

    def group_call(self, g: int, config: RetargetConfig) -> tuple[ca.Function, list]:
        """Group g's shared function and the group's constants.

        ``fn(far, ends_1 (6), [ends_2 (6),] J_1 (6, n), [J_2 (6, n),] *constants, bound)
        -> (over, clearance bound, u)``, with ``J`` the ends' Jacobians in q: with
        ``far`` true, ``(0, bound, 0)``; else first the group's **midpoint bound**
        (:meth:`midpoint_bound`), and only if that is below the band the exact term
        (``over``, its clearance and ``u`` of :meth:`kind_functions`), else ``(0,
        max(bound, midpoint bound), 0)``. ``ends_2`` and ``J_2`` are there for a capsule
        pair.

        There is one such function per kind of group (a capsule against a box; a capsule
        pair), the group's geometry passed as constants: one copy of the code for all
        groups, so the generated solver stays small enough to stay in the instruction
        cache.
        """
        kind = "box" if self.keys()[g][1] else "pair"
        return self._shared_group(kind, config), self.group_constants(g)

    def group_constants(self, g: int) -> list:
        """Group g's geometry, the constants of its kind's functions
        (:meth:`kind_functions`)."""
        col = self.pk.collision
        cap, box, other = self.keys()[g]
        if box:
            bx = col.boxes[other]
            consts = [ca.DM(bx.centre), ca.DM(bx.rotation), ca.DM(bx.half)]
            return [*consts, col.capsules[cap].radius, self._half_axis(cap)]
        radii = col.capsules[cap].radius + col.capsules[other].radius
        return [radii, self._half_axis(cap), self._half_axis(other)]

    def _half_axis(self, cap: int) -> float:
        """Half the capsule's axis length [m] (fixed in its link), plus rounding slack:
        no point of the axis is farther from its middle."""
        c = self.pk.collision.capsules[cap]
        return 0.5 * float(np.linalg.norm(c.b - c.a)) + _SLACK

    def midpoint_bound(self, g: int, ends: np.ndarray) -> float:
        """Group g's midpoint bound at capsule ends ``ends`` (6 per capsule) [m], in numpy:
        a lower bound of its smallest clearance, because a box's signed distance and the
        distance between two points are 1-Lipschitz: for a capsule and a box, the box's
        signed distance at the axis middle less half the axis, the radius and the margin;
        for a capsule pair, the larger of each axis's distance to the other's middle less
        half the other axis, less both radii and the margin."""
        col = self.pk.collision
        cap, box, other = self.keys()[g]
        a, b = ends[6 * cap : 6 * cap + 3], ends[6 * cap + 3 : 6 * cap + 6]
        if box:
            d = box_sdf(0.5 * (a + b), col.boxes[other]) - col.capsules[cap].radius
            return float(d - self._half_axis(cap) - col.margin)
        a2, b2 = ends[6 * other : 6 * other + 3], ends[6 * other + 3 : 6 * other + 6]
        radii = col.capsules[cap].radius + col.capsules[other].radius
        gap = max(
            _point_segment_np(0.5 * (a2 + b2), a, b) - self._half_axis(other),
            _point_segment_np(0.5 * (a + b), a2, b2) - self._half_axis(cap),
        )
        return gap - radii - col.margin

    def kind_functions(self, kind: str, config: RetargetConfig) -> tuple[ca.Function, ca.Function]:
        """The two SX functions of one kind of group (``box``: a capsule against a box;
        ``pair``: a capsule pair), the group's geometry passed as constants.

        ``gate(ends_1 (6), [ends_2 (6),] *constants) -> midpoint bound`` (see
        :meth:`midpoint_bound`) and ``exact(ends_1, [ends_2,] *constants) -> (over, c,
        grad)``: the clearance ``c`` less the margin, ``over = (band - c)_+`` and
        ``grad`` (6 per capsule) the clearance's gradient in the ends. Through the ends'
        Jacobians ``J``, ``u = J^T grad`` is its gradient in q: the penalty's term
        ``over^2`` has the gradient ``-2 over u`` and ``u u^T`` is its term of the
        curvature (only while ``over > 0``). Constants: for a box its centre (3),
        rotation (3x3), half sizes (3), the capsule radius and :meth:`_half_axis`; for a
        pair the radii's sum and each capsule's :meth:`_half_axis`.
        """
        margin, band = self.pk.collision.margin, config.collision_band
        key = (kind, band, margin)  # both are built into the functions
        if key in self._shared:
            return self._shared[key]
        e1 = ca.SX.sym("e1", 6)
        a, b = e1[:3], e1[3:]
        if kind == "box":
            centre, rot = ca.SX.sym("centre", 3), ca.SX.sym("rotation", 3, 3)
            half, radius, slack = ca.SX.sym("half", 3), ca.SX.sym("radius"), ca.SX.sym("slack")
            others = [centre, rot, half, radius, slack]
            c = segment_box_distance_expr(a, b, centre, rot, half) - radius - margin
            qv = ca.fabs(ca.mtimes(rot.T, 0.5 * (a + b) - centre)) - half
            out = ca.fmax(qv, 0)
            mid = ca.sqrt(ca.dot(out, out) + _TINY) + ca.fmin(ca.mmax(qv), 0)
            gate = mid - radius - slack - margin
            e2: list = []
        else:
            e2s, radii = ca.SX.sym("e2", 6), ca.SX.sym("radii")
            half1, half2 = ca.SX.sym("half1"), ca.SX.sym("half2")
            others = [radii, half1, half2]
            a2, b2 = e2s[:3], e2s[3:]
            c = _segment_distance_ca(a, b, a2, b2) - radii - margin
            gap = ca.fmax(
                _point_segment_ca(0.5 * (a2 + b2), a, b) - half2,
                _point_segment_ca(0.5 * (a + b), a2, b2) - half1,
            )
            gate = gap - radii - margin
            e2 = [e2s]
        over = ca.fmax(band - c, 0.0)
        grad = ca.gradient(c, ca.vertcat(e1, *e2))
        gate_fn = ca.Function(f"group_{kind}_gate", [e1, *e2, *others], [gate], {"cse": True})
        exact = ca.Function(
            f"group_{kind}_exact", [e1, *e2, *others], [over, c, grad], {"cse": True}
        )
        self._shared[key] = (gate_fn, exact)
        return gate_fn, exact

    def _project(self, ne: int) -> ca.Function:
        """``(over, grad (6 ne), J_1 (6, n), ...) -> u``: the clearance's gradient in q
        (``J^T grad``) where ``over > 0``, else 0."""
        key = ("project", ne)
        if key not in self._shared:
            n = self.pk.n
            over, grad = ca.SX.sym("over"), ca.SX.sym("grad", 6 * ne)
            jacs = [ca.SX.sym(f"J{i + 1}", 6, n) for i in range(ne)]
            u = ca.if_else(over > 0, 1.0, 0.0) * ca.mtimes(ca.vertcat(*jacs).T, grad)
            self._shared[key] = ca.Function(f"project{ne}", [over, grad, *jacs], [u])
        return self._shared[key]

    def _shared_group(self, kind: str, config: RetargetConfig) -> ca.Function:
        """The shared MX function of one kind of group (see :meth:`group_call`)."""
        key = ("group", kind, config.collision_band, self.pk.collision.margin)
        if key in self._shared:
            return self._shared[key]
        gate_fn, exact = self.kind_functions(kind, config)
        band, n = config.collision_band, self.pk.n
        ne = 1 if kind == "box" else 2
        ends = [ca.MX.sym(f"e{i + 1}", 6) for i in range(ne)]
        jacs = [ca.MX.sym(f"J{i + 1}", 6, n) for i in range(ne)]
        others = [ca.MX.sym(f"k{i}", exact.sparsity_in(i)) for i in range(ne, exact.n_in())]
        bound = ca.MX.sym("bound")
        ins = [*ends, *jacs, *others, bound]
        sx_ins = [ca.SX.sym(x.name(), x.sparsity()) for x in ins]
        skip = ca.Function(f"group_{kind}_skip", sx_ins, [ca.SX(0.0), sx_ins[-1], ca.SX.zeros(n)])
        over, c, grad = exact(*ends, *others)
        u = self._project(ne)(over, grad, *jacs)
        exact_mx = ca.Function(f"group_{kind}_exact_b", ins, [over, c, u])
        g_mx = gate_fn(*ends, *others)
        inner = ca.Function.conditional(f"group_{kind}_near", [exact_mx], skip)
        gated = ca.Function(
            f"group_{kind}_gated", ins, inner(g_mx >= band, *ins[:-1], ca.fmax(bound, g_mx))
        )
        self._shared[key] = ca.Function.conditional(f"group_{kind}", [gated], skip)
        return self._shared[key]

    def penalty_function(self, config: RetargetConfig) -> ca.Function:
        """``(q, pre-bounds) -> (S, dS/dq, group minima, A)``: the groups whose bound is
        below the band evaluated on the capsule ends (and their Jacobian) computed once,
        the others skipped; ``A`` (n*n, column-major) is the sum over the terms in the
        band of ``grad c grad c^T``, the curvature of ``S`` bar the terms' own."""
        n, ng = self.pk.n, len(self)
        q, pre = ca.MX.sym("q", n), ca.MX.sym("pre", ng)
        ncap = len(self.pk.collision.capsules)
        outs = self.ends_jacobian_function()(q)
        ends, jacs = outs[:ncap], outs[ncap:]
        band = config.collision_band
        overs, mins, us = [], [], []
        for g, (cap, box, other) in enumerate(self.keys()):
            fn, consts = self.group_call(g, config)
            two = [cap] if box else [cap, other]
            out = fn(
                pre[g] >= band, *[ends[i] for i in two], *[jacs[i] for i in two], *consts, pre[g]
            )
            overs.append(out[0])
            mins.append(out[1])
            us.append(out[2])
        over, u = ca.vertcat(*overs), ca.horzcat(*us)  # u is 0 outside the band
        result = [ca.dot(over, over), ca.mtimes(u, -2.0 * over), ca.vertcat(*mins)]
        result.append(ca.vec(ca.mtimes(u, u.T)))
        return ca.Function("collision_penalty", [q, pre], result)


def evaluate_function(
    pk: PairKinematics,
    config: RetargetConfig,
    r: ca.SX,
    jac: ca.SX,
    q: ca.SX,
    par: ca.SX,
    penalty: ca.Function | None = None,
    name: str = "evaluate",
) -> tuple[ca.Function, int]:
    """``evaluate(q, par, q_anchor, bounds) -> (cost, g, H, clearance, bounds)`` (named
    ``name``) and the number of groups (0 without collision terms: ``bounds`` is then
    empty).

    ``penalty`` replaces :meth:`CollisionGroups.penalty_function` (same contract), e.g.
    by the C loop of :class:`payload.retarget.collision_c.NativeCollision`.

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
            name, [q, par, qa, lba], [cost, grad, hess, ca.SX(1.0), lba], {"cse": True}
        )
        return fn, 0
    pre = lba - ca.mtimes(ca.DM(groups.lipschitz), ca.fabs(q - qa))
    far = ca.mmin(pre) >= config.collision_band
    base = ca.Function("evaluate_base", [q, par, qa, lba], [r, jac, pre, far], {"cse": True})
    rs, js = ca.SX.sym("r", r.sparsity()), ca.SX.sym("J", jac.sparsity())
    ss, ds, ms = ca.SX.sym("s"), ca.SX.sym("ds", n), ca.SX.sym("mins", ng)
    curv = ca.SX.sym("A", n * n)
    scale = config.w_c / config.collision_band**2
    rc, jc = scale * ss, scale * ds
    cost, grad, hess = _cost_terms(ca.vertcat(rs, rc), ca.vertcat(js, jc.T))
    # The penalty row's own curvature, w r_c d2 r_c / dq2 (w = 1 / sqrt(1 + r_c^2), the
    # row's IRLS weight) with d2 S / dq2 taken as
    # 2 sum(grad c grad c^T) over the terms in the band: Gauss-Newton of the single row
    # sees only the direction of dS/dq, so without it the iterates zigzag along the band.
    hess = hess + 2.0 * scale * rc / ca.sqrt(1.0 + rc * rc) * curv
    combine = ca.Function(
        "evaluate_combine",
        [rs, js, ss, ds, ms, curv],
        [cost, grad, hess, ca.mmin(ms)],
        {"cse": True},
    )
    qs, pres = ca.SX.sym("q", n), ca.SX.sym("pre", ng)
    none_near = ca.Function(
        "collision_far", [qs, pres], [ca.SX(0.0), ca.SX.zeros(n), pres, ca.SX.zeros(n * n)]
    )
    penalty = ca.Function.conditional(
        "collision_part", [penalty or groups.penalty_function(config)], none_near
    )
    sym = ca.MX.sym
    qm, pm, qam, lbm = sym("q", n), sym("p", par.shape[0]), sym("q_anchor", n), sym("bounds", ng)
    rm, jm, prem, farm = base(qm, pm, qam, lbm)
    total, dtotal, mins, curv_m = penalty(farm, qm, prem)
    cost_m, grad_m, hess_m, clear_m = combine(rm, jm, total, dtotal, mins, curv_m)
    fn = ca.Function(name, [qm, pm, qam, lbm], [cost_m, grad_m, hess_m, clear_m, mins])
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
