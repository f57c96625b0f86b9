"""The pair solve as one CasADi graph: guarded projected Levenberg-Marquardt iterations.

The forward kinematics rebuilt from the Pinocchio model (:mod:`payload.retarget.symbolic`),
the residuals of eq. 3, their Jacobian by algorithmic differentiation, and a capped
sequence of guarded iterations of a projected Levenberg-Marquardt method on the soft-L1
cost ``sum(sqrt(1 + r^2) - 1)`` (the same value scipy's ``loss="soft_l1"`` minimises).
See :mod:`payload.retarget.casadi_solver` for the method; :func:`build_solve_function`
returns the whole solve (every start of the budget, :mod:`payload.retarget.budget`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from payload.retarget.budget import RESUME, budget_plan, table_seeds
from payload.retarget.collision import register as register_collision_model
from payload.retarget.collision_eval import evaluate_function
from payload.retarget.errors import RetargetError
from payload.retarget.features import N_FEATURES, PairKinematics
from payload.retarget.objective import RetargetConfig
from payload.retarget.symbolic import paper_residuals_expr, uses_collisions

_MU0 = 1e-4
_MU_MAX = 1e12
_BOUND_EPS = 1e-12
_CURVATURE_FLOOR = 1e-9
_DAMPING_EPS = 1e-14
_MAX_STEP = 0.1


def _cholesky_solve(a: ca.SX, b: ca.SX) -> ca.SX:
    """Solve ``a x = b`` for a symmetric positive definite symbolic matrix (n, n)."""
    n = a.shape[0]
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s = s - low[j][k] * low[j][k]
        low[j][j] = ca.sqrt(s)
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i][j] = s / low[j][j]
    y = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - low[i][k] * y[k]
        y[i] = s / low[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - low[k][i] * x[k]
        x[i] = s / low[i][i]
    return ca.vertcat(*x)


def _step_functions(
    pk: PairKinematics,
    config: RetargetConfig,
    wrap: Callable[[ca.Function], Any] | None = None,
    penalty: ca.Function | None = None,
) -> tuple[Any, ca.Function]:
    """``evaluate(q, par, q_anchor, bounds) -> (cost, g, H, clearance, bounds)`` and one
    guarded iteration ``iterate(x, par) -> x`` (:func:`solve_parts`; ``wrap`` replaces
    ``evaluate``, e.g. by a counting callback). The iteration is an MX graph that calls
    ``propose``, ``evaluate`` and ``accept``."""
    parts = solve_parts(pk, config, penalty=penalty)
    evaluate = parts.evaluate if wrap is None else wrap(parts.evaluate)
    return evaluate, _iterate_function(parts, evaluate)


def _iterate_function(parts: SolveParts, evaluate: Any) -> ca.Function:
    """One guarded iteration as an MX graph: ``propose``, one residual evaluation at the
    candidate, ``accept``."""
    lay, ng = parts.layout, parts.groups
    xm, pm = ca.MX.sym("x", lay["size"]), ca.MX.sym("p", parts.npar)
    qm, prm = parts.propose(xm)
    anchor_q, anchor_b = xm[: parts.n], xm[lay["bounds"] : lay["bounds"] + ng]
    ev = evaluate(qm, pm, anchor_q, anchor_b)  # the iteration's one residual evaluation
    return ca.Function("iterate", [xm, pm], [parts.accept(xm, qm, prm, *ev)])


@dataclass(frozen=True)
class SolveParts:
    """The pieces of one pair solve, each a CasADi function; :func:`build_solve_function`
    composes them into one graph, :mod:`payload.retarget.lm_c` drives them from a C loop.

    The state is ``x = [q (n), cost, g (n), H (n*n), clearance, bounds (groups), free
    record, mu, done, iterations, evaluations]`` (:func:`_layout`; ``bounds``: the collision
    groups' clearance bounds at q, :mod:`payload.retarget.collision_eval`; the free record:
    the best collision-free point met).

    Attributes:
        evaluate: ``(q, par, q_anchor, bounds) -> (cost, g, H, clearance, bounds)``: one
            residual evaluation (the residuals and their Jacobian).
        propose: ``x -> (q_candidate, predicted decrease)``: one iteration's step.
        accept: ``(x, q_candidate, predicted, cost, g, H, clearance, bounds) -> x``: the
            candidate kept if it lowers the cost; ``done`` set by the convergence tests or
            by a damping that ran away; iterations and evaluations counted.
        decide: ``(x, q_candidate, predicted, cost, g, clearance) -> (lower, free, mu,
            done)``: ``accept``'s choices, for a caller that moves the state itself.
        prep: ``(q_prev, targets, q_ref) -> (par, starts (n, k))``: the parameters and the
            start points in the budget's order (:func:`payload.retarget.budget.budget_plan`).
        init: ``(q_start, cost, g, H, clearance, bounds, best) -> x``: a start's first state
            from its evaluation (counted on ``best``'s count).
        finish: ``(x, best) -> best``: a start's result (:func:`_collapse`) kept if better.
        outputs: ``best -> (q, info, bounds)``: the solve's outputs.
        starts: ``(cumulative evaluation cap, iteration levels)`` per start.
        tags: Each start's tag (:func:`payload.retarget.budget.budget_plan`).
        initial: The ``best`` state before any start (cost ``inf``).
        layout: :func:`_layout`.
        n: Joints.
        groups: Collision groups (0 without collision terms).
        npar: Length of ``par``.
        lower: Lower joint limits, shape (n,) [rad, m].
        upper: Upper joint limits, shape (n,) [rad, m].
        gtol: The projected-gradient convergence threshold of ``init`` and ``accept``.
    """

    evaluate: ca.Function
    propose: ca.Function
    accept: ca.Function
    decide: ca.Function
    prep: ca.Function
    init: ca.Function
    finish: ca.Function
    outputs: ca.Function
    starts: tuple[tuple[int, int], ...]
    tags: tuple[str, ...]
    initial: np.ndarray
    layout: dict[str, int]
    n: int
    groups: int
    npar: int
    lower: np.ndarray
    upper: np.ndarray
    gtol: float


def solve_parts(
    pk: PairKinematics,
    config: RetargetConfig,
    penalty: ca.Function | None = None,
    prefix: str = "",
) -> SolveParts:
    """The pieces of one pair solve (:class:`SolveParts`); ``penalty``: see
    :func:`build_solve_function`; ``prefix`` starts each piece's name (its C symbol)."""
    register_collision_model()  # pk.collision, when the config models it
    n = pk.n
    npar = N_FEATURES + 2 * n
    q = ca.SX.sym("q", n)
    par = ca.SX.sym("p", npar)
    t, qr, qp = par[:N_FEATURES], par[N_FEATURES : N_FEATURES + n], par[N_FEATURES + n :]
    r = paper_residuals_expr(pk, config, q, t, qr, qp)
    evaluate, ng = evaluate_function(
        pk, config, r, ca.jacobian(r, q), q, par, penalty, prefix + "evaluate"
    )
    lay = _layout(n, ng)
    nx = lay["size"]
    x = ca.SX.sym("x", nx)
    qc, predicted = _proposal(pk, x, lay)
    propose = ca.Function(prefix + "propose", [x], [qc, predicted], {"cse": True})
    cc, gc, hc = ca.SX.sym("c"), ca.SX.sym("g", n), ca.SX.sym("h", n * n)
    clc, bc, qs, pr = ca.SX.sym("cl"), ca.SX.sym("b", ng), ca.SX.sym("qc", n), ca.SX.sym("pr")
    ck, mu = x[lay["cost"]], x[lay["mu"]]
    lbv, ubv = ca.DM(pk.lower), ca.DM(pk.upper)
    gain = (ck - cc) / ca.fmax(pr, 1e-300)
    mu_ok = ca.fmax(mu * ca.fmax(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-12)
    pg = qs - ca.fmin(ca.fmax(qs - gc, lbv), ubv)
    conv = ca.logic_or(ca.mmax(ca.fabs(pg)) <= config.gtol, ck - cc <= config.ftol * ck)
    mu_up = 4.0 * mu
    # The iterates follow the cost (the penalty keeps them near the free region but may
    # pass through the margin); the best collision-free point met is recorded apart.
    lower = cc < ck
    i_f = lay["free"]
    free_ok = ca.logic_and(clc >= 0, cc < x[lay["rec_cost"]])
    record = ca.if_else(free_ok, ca.vertcat(qs, cc, clc, bc), x[i_f : lay["mu"]])
    main = ca.if_else(lower, ca.vertcat(qs, cc, gc, hc, clc, bc), x[:i_f])
    mu_new = ca.if_else(lower, mu_ok, mu_up)
    done_new = ca.if_else(lower, conv, mu_up >= _MU_MAX)
    out = ca.vertcat(main, record, mu_new, done_new, x[lay["it"]] + 1.0, x[lay["ev"]] + 1.0)
    accept = ca.Function(prefix + "accept", [x, qs, pr, cc, gc, hc, clc, bc], [out], {"cse": True})
    decide = ca.Function(
        prefix + "decide",
        [x, qs, pr, cc, gc, clc],
        [lower, free_ok, mu_new, done_new],
        {"cse": True},
    )
    # A start's first state from its evaluation at the start point.
    best = ca.SX.sym("best", nx)
    done0 = ca.mmax(ca.fabs(pg)) <= config.gtol  # pg: the projected gradient at qs
    rec0 = ca.if_else(clc >= 0, ca.vertcat(qs, cc, clc, bc), ca.vertcat(qs, np.inf, -np.inf, bc))
    x0 = ca.vertcat(
        qs, cc, gc, hc, clc, bc, rec0, _MU0, done0, best[lay["it"]], best[lay["ev"]] + 1.0
    )
    init = ca.Function(prefix + "init", [qs, cc, gc, hc, clc, bc, best], [x0], {"cse": True})
    st = _collapse(x, lay)
    kept = ca.if_else(
        _better(st[lay["cost"]], st[lay["clear"]], best[lay["cost"]], best[lay["clear"]]), st, best
    )
    kept = ca.vertcat(kept[: lay["it"]], st[lay["it"]], st[lay["ev"]])
    finish = ca.Function(prefix + "finish", [x, best], [kept], {"cse": True})
    outputs = ca.Function(prefix + "outputs", [best], list(_outputs(pk, config, best, lay, ng)))
    # The parameters and the start points.
    q_prev, targets, q_ref = (
        ca.MX.sym("q_prev", n),
        ca.MX.sym("targets", N_FEATURES),
        ca.MX.sym("q_ref", n),
    )
    q0 = ca.fmin(ca.fmax(q_prev, lbv), ubv)
    # RESUME's column is a placeholder: that start continues from the best point met
    seeds = {"prev": q0, "ref": ca.fmin(ca.fmax(q_ref, lbv), ubv), RESUME: q0}
    plan = budget_plan(config)
    tags = [tag for tag, _ in plan if tag.startswith("seed")]
    for tag, q_seed in zip(tags, table_seeds(pk, config, targets, q_ref, q0, len(tags))):
        seeds[tag] = q_seed
    prep = ca.Function(
        prefix + "prep",
        [q_prev, targets, q_ref],
        [ca.vertcat(targets, q_ref, q0), ca.horzcat(*(seeds[tag] for tag, _ in plan))],
    )
    initial = np.zeros(nx)
    initial[lay["cost"]] = np.inf
    initial[lay["clear"]] = -np.inf
    initial[lay["bounds"] : lay["bounds"] + ng] = -np.inf
    starts = tuple((cap, max(0, min(config.max_iterations, cap - 1))) for _, cap in plan)
    return SolveParts(
        evaluate,
        propose,
        accept,
        decide,
        prep,
        init,
        finish,
        outputs,
        starts,
        tuple(tag for tag, _ in plan),
        initial,
        lay,
        n,
        ng,
        npar,
        np.asarray(pk.lower, dtype=float).copy(),
        np.asarray(pk.upper, dtype=float).copy(),
        float(config.gtol),
    )


def _proposal(pk: PairKinematics, x: ca.SX, lay: dict[str, int]) -> tuple[ca.SX, ca.SX]:
    """The candidate of one iteration from state x, and its predicted decrease."""
    n, nn = pk.n, pk.n * pk.n
    lbv, ubv, rng = ca.DM(pk.lower), ca.DM(pk.upper), ca.DM(pk.range)
    qk, gk, mu = x[:n], x[lay["g"] : lay["g"] + n], x[lay["mu"]]
    hk = ca.reshape(x[lay["h"] : lay["h"] + nn], n, n)
    active = ca.logic_or(
        ca.logic_and(qk <= lbv + _BOUND_EPS, gk > 0), ca.logic_and(qk >= ubv - _BOUND_EPS, gk < 0)
    )
    free = 1.0 - active
    damping = mu * ca.fmax(ca.diag(hk), _CURVATURE_FLOOR) + _DAMPING_EPS
    # First pass: the damped step over the free joints.
    delta = -_cholesky_solve(
        hk * ca.mtimes(free, free.T) + ca.diag(active + free * damping), free * gk
    )
    # Second pass: joints the step would push through a bound stop on it, and the others
    # are solved again with that displacement fixed.
    hit_lo = free * (qk + delta < lbv)
    hit_hi = free * (qk + delta > ubv)
    fixed = ca.fmax(active, hit_lo + hit_hi)
    free2 = 1.0 - fixed
    d_fixed = hit_lo * (lbv - qk) + hit_hi * (ubv - qk)
    rhs = -free2 * (gk + ca.mtimes(hk, d_fixed))
    delta = d_fixed + free2 * _cholesky_solve(
        hk * ca.mtimes(free2, free2.T) + ca.diag(fixed + free2 * damping), rhs
    )
    # Step cap: no joint moves more than _MAX_STEP of its range per iteration.
    delta = delta / ca.fmax(1.0, ca.mmax(ca.fabs(delta) / rng) / _MAX_STEP)
    qc = ca.fmin(ca.fmax(qk + delta, lbv), ubv)
    step = qc - qk
    predicted = -(ca.dot(gk, step) + 0.5 * ca.dot(step, ca.mtimes(hk, step)))
    return qc, predicted


def _collapse(st: ca.MX, lay: dict[str, int]) -> ca.MX:
    """A start's result: its best collision-free point when it met one (converged only
    if that is where the iterates stopped), else where the iterates stopped."""
    i_f, i_cost, i_cl = lay["free"], lay["cost"], lay["clear"]
    fq, fc = st[i_f : lay["rec_cost"]], st[lay["rec_cost"]]
    fcl, fb = st[lay["rec_clear"]], st[lay["rec_bounds"] : lay["mu"]]
    done = ca.logic_and(st[lay["done"]], fc == st[i_cost])
    moved = ca.vertcat(
        fq, fc, st[i_cost + 1 : i_cl], fcl, fb, st[i_f : lay["done"]], done, st[lay["it"] :]
    )
    return ca.if_else(fc < np.inf, moved, st)


def _better(c_new: Any, cl_new: Any, c_old: Any, cl_old: Any) -> Any:
    """A point beats another: both collision-free (clearance >= 0) and a lower cost, or
    it is collision-free and the other is not, or neither is and it is less deep."""
    free_new, free_old = cl_new >= 0, cl_old >= 0
    return ca.logic_or(
        ca.logic_and(free_new, ca.logic_or(c_new < c_old, ca.logic_not(free_old))),
        ca.logic_and(ca.logic_not(free_old), ca.logic_and(ca.logic_not(free_new), cl_new > cl_old)),
    )


def _layout(n: int, groups: int) -> dict[str, int]:
    """Offsets in the state ``[q (n), cost, g (n), H (n*n), clearance, bounds (groups),
    free record, mu, done, iterations, evaluations]`` and its ``size``; the free record is
    the best collision-free point met, ``[q (n), cost, clearance, bounds (groups)]``
    (cost ``inf`` while none), its cost, clearance and bounds at ``rec_cost``,
    ``rec_clear`` and ``rec_bounds``."""
    cl = 2 * n + 1 + n * n
    free = cl + 1 + groups
    mu = free + n + 2 + groups
    return {
        "cost": n,
        "g": n + 1,
        "h": 2 * n + 1,
        "clear": cl,
        "bounds": cl + 1,
        "free": free,
        "rec_cost": free + n,
        "rec_clear": free + n + 1,
        "rec_bounds": free + n + 2,
        "mu": mu,
        "done": mu + 1,
        "it": mu + 2,
        "ev": mu + 3,
        "size": mu + 4,
    }


def _iterations(
    iterate: ca.Function, levels: int, lay: dict[str, int], npar: int, tag: str, cap: int
) -> ca.Function | None:
    """One start's iterations as nested conditionals (``None``: no iteration fits): level k
    iterates once and hands over to level k + 1 unless done, so a converged start returns
    at once; a level runs only while the solve has evaluations left under the start's
    cumulative cap."""
    xs, ps = ca.MX.sym("x", lay["size"]), ca.MX.sym("p", npar)
    hold = ca.Function("hold", [xs, ps], [xs])
    level = None
    for k in reversed(range(levels)):
        nxt = iterate(xs, ps)
        stop = ca.logic_or(nxt[lay["done"]], nxt[lay["ev"]] >= cap)
        out = nxt if level is None else level(stop, nxt, ps)
        level = ca.Function.conditional(
            f"{tag}_level_{k}", [ca.Function(f"{tag}_iterate_{k}", [xs, ps], [out])], hold
        )
    return level


def build_solve_function(
    pk: PairKinematics,
    config: RetargetConfig,
    name: str = "pair_solve",
    wrap_evaluate: Callable[[ca.Function], Any] | None = None,
    penalty: ca.Function | None = None,
    parts: SolveParts | None = None,
) -> ca.Function:
    """The pair solve as one CasADi function.

    Args:
        pk: The pair's kinematics (its Pinocchio model supplies the chains).
        config: Weights, scales, budget, iteration cap and tolerances.
        name: Function name (the C symbol when generated).
        wrap_evaluate: Replaces the one function that evaluates the residuals (and
            their Jacobian), e.g. by a counting ``casadi.Callback`` for tests; the result
            then runs only in CasADi's virtual machine.
        penalty: The collision part of an evaluation in place of the conditional CasADi
            form (:func:`payload.retarget.collision_eval.evaluate_function`), e.g. the C
            loop of :class:`payload.retarget.collision_c.NativeCollision`.
        parts: The solve's pieces when already built (:func:`solve_parts`; ``penalty``
            is then ignored).

    Returns:
        ``(q_prev (n), targets (13), q_ref (n), q_anchor (n), bounds (g)) -> (q (n),
        info (5), bounds (g))`` with ``info = [cost, iterations, converged, evaluations,
        clearance]``; ``q_prev`` is projected onto the box and is both the first start and
        the temporal term's reference. ``bounds`` are lower bounds of the ``g`` collision
        groups' clearances valid at ``q_anchor`` (``-inf``: unknown; pass the previous
        solve's output with its ``q``), :mod:`payload.retarget.collision_eval`; the output
        ``bounds`` are valid at the output ``q``. ``g`` is 0 without collision terms.
    """
    parts = parts if parts is not None else solve_parts(pk, config, penalty)
    evaluate = parts.evaluate if wrap_evaluate is None else wrap_evaluate(parts.evaluate)
    iterate = _iterate_function(parts, evaluate)
    n, ng, npar, lay = parts.n, parts.groups, parts.npar, parts.layout
    nx, i_b, i_done, i_ev = lay["size"], lay["bounds"], lay["done"], lay["ev"]
    q_prev = ca.MX.sym("q_prev", n)
    targets = ca.MX.sym("targets", N_FEATURES)
    q_ref = ca.MX.sym("q_ref", n)
    q_anchor, bounds_in = ca.MX.sym("q_anchor", n), ca.MX.sym("bounds", ng)
    p_mx, start_points = parts.prep(q_prev, targets, q_ref)
    # The starts in turn; each keeps the better state of itself and those before, and
    # runs only if the solve has an evaluation left under its cumulative cap. The first
    # start carries the collision bounds from the input anchor, the others from the best
    # state so far.
    xb, qs, ps = ca.MX.sym("best", nx), ca.MX.sym("start", n), ca.MX.sym("p", npar)
    qa, ba = ca.MX.sym("anchor", n), ca.MX.sym("anchor_bounds", ng)
    skip = ca.Function("skip", [xb, qs, ps, qa, ba], [xb])
    best: ca.MX = ca.MX(ca.DM(parts.initial))
    plan = budget_plan(config)
    for k, ((tag, _), (cap, levels)) in enumerate(zip(plan, parts.starts)):
        x0 = parts.init(qs, *evaluate(qs, ps, qa, ba), xb)
        lv = _iterations(iterate, levels, lay, npar, tag, cap)
        st = x0 if lv is None else lv(ca.logic_or(x0[i_done], x0[i_ev] >= cap), x0, ps)
        run = ca.Function(f"start_{tag}", [xb, qs, ps, qa, ba], [parts.finish(st, xb)])
        start = ca.Function.conditional(f"maybe_{tag}", [run], skip)
        anchor = (q_anchor, bounds_in) if k == 0 else (best[:n], best[i_b : i_b + ng])
        # RESUME starts again from the best point met (evaluated again: a start's best
        # state keeps the gradient of where its iterates stopped, not of its best point)
        q_start = best[:n] if tag == RESUME else start_points[:, k]
        best = start(best[i_ev] >= cap, best, q_start, p_mx, *anchor)
    q_out, info, bounds_out = parts.outputs(best)
    return ca.Function(
        name,
        [q_prev, targets, q_ref, q_anchor, bounds_in],
        [q_out, info, bounds_out],
        ["q_prev", "targets", "q_ref", "q_anchor", "bounds"],
        ["q", "info", "bounds_out"],
    )


def _outputs(
    pk: PairKinematics, config: RetargetConfig, best: ca.MX, lay: dict[str, int], ng: int
) -> tuple[ca.MX, ca.MX, ca.MX]:
    """The command, the info vector and the bounds at the command, from the best state."""
    n, i_cost, i_cl, i_b = pk.n, lay["cost"], lay["clear"], lay["bounds"]
    i_done, i_it, i_ev = lay["done"], lay["it"], lay["ev"]
    used, iters = best[i_ev], best[i_it]
    # Never a command inside the margin: if no start reached a collision-free point (both
    # the previous command and the posture reference were inside it), the safe posture.
    q_safe, cl_safe = safe_posture(pk, config)
    free = best[i_cl] >= 0
    q_out = ca.if_else(free, best[:n], ca.DM(q_safe))
    info = ca.vertcat(
        ca.if_else(free, best[i_cost], np.inf),
        iters,
        ca.logic_and(free, best[i_done]),
        used,
        ca.if_else(free, best[i_cl], cl_safe),
    )
    bounds_out = ca.if_else(free, best[i_b : i_b + ng], -np.inf * ca.DM.ones(ng))
    return q_out, info, bounds_out


def safe_posture(pk: PairKinematics, config: RetargetConfig) -> tuple[np.ndarray, float]:
    """A collision-free posture and its clearance [m]: the rest posture if it is, else the
    collision-free one nearest to it (range-normalised) among seeded samples of the box."""
    if not uses_collisions(pk, config):
        return pk.rest.copy(), 1.0
    col = pk.collision
    if col.clearance(pk.rest) >= 0:
        return pk.rest.copy(), col.clearance(pk.rest)
    rng = np.random.default_rng(99)
    qs = pk.lower + rng.random((4000, pk.n)) * pk.range
    dist = col.distances_many(qs)
    ok = np.flatnonzero(dist.min(axis=0) - col.margin >= col.margin)
    if ok.size == 0:
        raise RetargetError(f"pair {pk.name}: no collision-free posture found for the fallback")
    i = ok[np.argmin(np.sum(((qs[ok] - pk.rest) / pk.range) ** 2, axis=1))]
    return qs[i], float(dist[:, i].min() - col.margin)
