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
from typing import Any

import casadi as ca
import numpy as np

from payload.retarget.budget import budget_plan, table_seeds
from payload.retarget.errors import RetargetError
from payload.retarget.features import N_FEATURES, PairKinematics
from payload.retarget.objective import RetargetConfig
from payload.retarget.symbolic import (
    clearance_and_penalty,
    paper_residuals_expr,
    uses_collisions,
)

_MU0 = 1e-4
_MU_MAX = 1e12
_BOUND_EPS = 1e-12
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
    pk: PairKinematics, config: RetargetConfig, wrap: Callable[[ca.Function], Any] | None = None
) -> tuple[Any, ca.Function]:
    """``evaluate(q, par) -> (cost, g, H)`` and one guarded iteration ``iterate(x, par) -> x``.

    The state is ``x = [q (n), cost, g (n), H (n*n), mu, done, iterations, evaluations]``.
    One iteration proposes a step and evaluates the residuals and their Jacobian at the
    candidate once (one residual evaluation), then keeps the candidate if its cost is
    lower; ``done`` is set by the convergence tests or by a damping that ran away.
    ``wrap`` replaces ``evaluate`` (e.g. by a counting callback); the iteration is then
    built as an MX graph that calls it.
    """
    n = pk.n
    lb, ub = pk.lower, pk.upper
    npar = N_FEATURES + 2 * n
    q = ca.SX.sym("q", n)
    par = ca.SX.sym("p", npar)
    t, qr, qp = par[:N_FEATURES], par[N_FEATURES : N_FEATURES + n], par[N_FEATURES + n :]
    r = paper_residuals_expr(pk, config, q, t, qr, qp)
    jac = ca.jacobian(r, q)
    cp = clearance_and_penalty(pk, config, q)
    if cp is not None:
        # the penalty residual's row by one reverse sweep (its gradient)
        clear = ca.mmin(cp[0])
        r, jac = ca.vertcat(r, cp[1]), ca.vertcat(jac, ca.gradient(cp[1], q).T)
    else:
        clear = ca.SX(1.0)
    s1 = ca.sqrt(1.0 + r * r)
    w1 = 1.0 / s1  # rho'(r^2), the IRLS weight
    cost = ca.sum1(s1 - 1.0)
    grad = ca.mtimes(jac.T, w1 * r)
    jw = ca.mtimes(ca.diag(ca.sqrt(w1)), jac)
    hess = ca.vec(ca.densify(ca.mtimes(jw.T, jw)))
    evaluate = ca.Function("evaluate", [q, par], [cost, grad, hess, clear], {"cse": True})
    # The iteration calls ``evaluate`` as a function (MX graph), so its code exists once.
    sym = ca.MX.sym
    if wrap is not None:
        evaluate = wrap(evaluate)
    par = sym("p", npar)

    nn = n * n
    i_cost, i_g, i_h = n, n + 1, 2 * n + 1
    i_cl = i_h + nn
    i_mu, i_it, i_ev = i_cl + 1, i_cl + 3, i_cl + 4
    lbv, ubv, rng = ca.DM(lb), ca.DM(ub), ca.DM(ub - lb)
    x = sym("x", _state_size(n))
    qk, ck, gk, mu, clk = x[:n], x[i_cost], x[i_g : i_g + n], x[i_mu], x[i_cl]
    hk = ca.reshape(x[i_h : i_h + nn], n, n)
    active = ca.logic_or(
        ca.logic_and(qk <= lbv + _BOUND_EPS, gk > 0), ca.logic_and(qk >= ubv - _BOUND_EPS, gk < 0)
    )
    free = 1.0 - active
    damping = mu * ca.fmax(ca.diag(hk), 1e-9) + 1e-14
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
    cc, gc, hc, clc = evaluate(qc, par)  # the iteration's one residual evaluation
    better = _better(cc, clc, ck, clk)
    gain = (ck - cc) / ca.fmax(predicted, 1e-300)
    mu_ok = ca.fmax(mu * ca.fmax(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-12)
    pg = qc - ca.fmin(ca.fmax(qc - gc, lbv), ubv)
    conv = ca.logic_or(ca.mmax(ca.fabs(pg)) <= config.gtol, ck - cc <= config.ftol * ck)
    mu_up = 4.0 * mu
    kept = ca.vertcat(qc, cc, gc, hc, clc, mu_ok, conv)
    held = ca.vertcat(x[:i_mu], mu_up, mu_up >= _MU_MAX)
    out = ca.vertcat(ca.if_else(better, kept, held), x[i_it] + 1.0, x[i_ev] + 1.0)
    iterate = ca.Function("iterate", [x, par], [out])
    return evaluate, iterate


def _better(c_new: Any, cl_new: Any, c_old: Any, cl_old: Any) -> Any:
    """A point beats another: both collision-free (clearance >= 0) and a lower cost, or
    it is collision-free and the other is not, or neither is and it is less deep."""
    free_new, free_old = cl_new >= 0, cl_old >= 0
    return ca.logic_or(
        ca.logic_and(free_new, ca.logic_or(c_new < c_old, ca.logic_not(free_old))),
        ca.logic_and(ca.logic_not(free_old), ca.logic_and(ca.logic_not(free_new), cl_new > cl_old)),
    )


def _state_size(n: int) -> int:
    """``[q (n), cost, g (n), H (n*n), clearance, mu, done, iterations, evaluations]``."""
    return 2 * n + n * n + 6


def build_solve_function(
    pk: PairKinematics,
    config: RetargetConfig,
    name: str = "pair_solve",
    wrap_evaluate: Callable[[ca.Function], Any] | None = None,
) -> ca.Function:
    """The pair solve as one CasADi function.

    Args:
        pk: The pair's kinematics (its Pinocchio model supplies the chains).
        config: Weights, scales, budget, iteration cap and tolerances.
        name: Function name (the C symbol when generated).
        wrap_evaluate: Replaces the one function that evaluates the residuals (and
            their Jacobian), e.g. by a counting ``casadi.Callback`` for tests; the result
            then runs only in CasADi's virtual machine.

    Returns:
        ``(q_prev (n), targets (13), q_ref (n)) -> (q (n), info (5))`` with
        ``info = [cost, iterations, converged, evaluations, clearance]``; ``q_prev`` is projected
        onto the box and is both the first start and the temporal term's reference.
    """
    n = pk.n
    npar = N_FEATURES + 2 * n
    lbv, ubv = ca.DM(pk.lower), ca.DM(pk.upper)
    evaluate, iterate = _step_functions(pk, config, wrap_evaluate)
    nx = _state_size(n)
    i_cost, i_done, i_it, i_ev = n, nx - 3, nx - 2, nx - 1
    xs, ps = ca.MX.sym("x", nx), ca.MX.sym("p", npar)
    hold = ca.Function("hold", [xs, ps], [xs])

    def chain(tag: str, cap: int) -> ca.Function:
        # The cap as nested conditionals: level k iterates once and hands over to level
        # k + 1 unless done, so a converged start returns at once. A level runs only
        # while the solve has evaluations left under this start's cumulative cap.
        level = None
        levels = min(config.max_iterations, cap - 1)
        for k in reversed(range(levels)):
            nxt = iterate(xs, ps)
            stop = ca.logic_or(nxt[i_done], nxt[i_ev] >= cap)
            out = nxt if level is None else level(stop, nxt, ps)
            level = ca.Function.conditional(
                f"{tag}_level_{k}", [ca.Function(f"{tag}_iterate_{k}", [xs, ps], [out])], hold
            )
        return level

    q_prev = ca.MX.sym("q_prev", n)
    targets = ca.MX.sym("targets", N_FEATURES)
    q_ref = ca.MX.sym("q_ref", n)
    q0 = ca.fmin(ca.fmax(q_prev, lbv), ubv)
    p_mx = ca.vertcat(targets, q_ref, q0)
    seeds = {"prev": q0, "ref": ca.fmin(ca.fmax(q_ref, lbv), ubv)}
    tags = [tag for tag, _ in budget_plan(config) if tag.startswith("seed")]
    for tag, q_seed in zip(tags, table_seeds(pk, config, targets, q_ref, q0, len(tags))):
        seeds[tag] = q_seed
    # The starts in turn; each keeps the lower-cost state of itself and those before, and
    # runs only if the solve has an evaluation left under its cumulative cap.
    xb, qs = ca.MX.sym("best", nx), ca.MX.sym("start", n)
    skip = ca.Function("skip", [xb, qs, ps], [xb])
    i_cl = 2 * n + 1 + n * n
    inf_state = ca.DM.zeros(nx)
    inf_state[i_cost] = np.inf
    inf_state[i_cl] = -np.inf
    best: ca.MX = ca.MX(inf_state)
    for tag, cap in budget_plan(config):
        c0, g0, h0, cl0 = evaluate(qs, ps)
        pg0 = qs - ca.fmin(ca.fmax(qs - g0, lbv), ubv)
        done0 = ca.mmax(ca.fabs(pg0)) <= config.gtol
        x0 = ca.vertcat(qs, c0, g0, h0, cl0, _MU0, done0, xb[i_it], xb[i_ev] + 1.0)
        lv = chain(tag, cap)
        st = x0 if lv is None else lv(ca.logic_or(x0[i_done], x0[i_ev] >= cap), x0, ps)
        kept = ca.if_else(_better(st[i_cost], st[i_cl], xb[i_cost], xb[i_cl]), st, xb)
        kept = ca.vertcat(kept[:i_it], st[i_it], st[i_ev])
        run = ca.Function(f"start_{tag}", [xb, qs, ps], [kept])
        start = ca.Function.conditional(f"maybe_{tag}", [run], skip)
        best = start(best[i_ev] >= cap, best, seeds[tag], p_mx)
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
    return ca.Function(
        name,
        [q_prev, targets, q_ref],
        [q_out, info],
        ["q_prev", "targets", "q_ref"],
        ["q", "info"],
    )


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
    dist = np.array(col.distance_function().map(qs.shape[0])(qs.T))
    ok = np.flatnonzero(dist.min(axis=0) - col.margin >= col.margin)
    if ok.size == 0:
        raise RetargetError(f"pair {pk.name}: no collision-free posture found for the fallback")
    i = ok[np.argmin(np.sum(((qs[ok] - pk.rest) / pk.range) ** 2, axis=1))]
    return qs[i], float(dist[:, i].min() - col.margin)
