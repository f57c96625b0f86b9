"""The best-known optimum of eq. 3, for judging how close a solver's answer comes.

For one pair solve (targets, posture reference, previous command), eq. 3 is minimised
by ``scipy.optimize.least_squares`` (trf, soft_l1, the residuals and their Jacobian
from the CasADi rebuild of the kinematics compiled to C, :class:`CompiledObjective`;
up to :data:`OPTIMUM_NFEV` function evaluations) from several starts: the previous
command, the posture reference, the rest posture, every answer the benchmarked solvers
gave at this step, and :data:`RANDOM_STARTS` seeded random postures in the box. Each
start's answer is costed again with Pinocchio and numpy; the lowest cost found, or a
solver's own cost when it is lower still, is the best-known optimum; a solve counts as
optimal when its cost is within :data:`OPTIMUM_TOLERANCE` (relative) of it. With
self-collision modelled, the objective carries the collision penalty residual and only
answers that keep the margin count (the constrained optimum).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from payload.retarget.collision import register as register_collision_model
from payload.retarget.features import N_FEATURES, PairKinematics
from payload.retarget.objective import (
    Objective,
    RetargetConfig,
    collision_residual,
    cost_of_residuals,
)
from payload.retarget.symbolic import (
    clearance_and_penalty,
    paper_residuals_expr,
    residuals_expr,
    uses_collisions,
)

OPTIMUM_NFEV = 400
"""Function evaluations of each scipy start of the best-known optimum."""

OPTIMUM_TOLERANCE = 1e-3
"""A solve is optimal when its cost is ``<= best * (1 + OPTIMUM_TOLERANCE)``."""

RANDOM_STARTS = 1
"""Seeded random starts of the best-known optimum, besides the informed ones."""


class CompiledObjective:
    """Eq. 3's residuals and dense Jacobian of one pair as compiled C (VM without a compiler).

    ``(q, targets, q_ref, q_prev) -> (r (m), J (m, n))``, m = 13 + 2n, plus the penalty row
    with self-collision modelled.
    """

    def __init__(self, pk: PairKinematics, config: RetargetConfig) -> None:
        from payload.retarget.compiled import _compiled_or_none

        register_collision_model()  # pk.collision, when the config models it
        n = pk.n
        q, t = ca.SX.sym("q", n), ca.SX.sym("t", N_FEATURES)
        qr, qp = ca.SX.sym("qr", n), ca.SX.sym("qp", n)
        name = "payload_objective_" + "".join(c if c.isalnum() else "_" for c in pk.name)
        if uses_collisions(pk, config):
            # eq. 3's rows as one expression, the penalty row as calls of the shared
            # distance functions (small C; see PairCollision.distances_expr)
            paper = ca.Function(
                "paper_rows", [q, t, qr, qp], [paper_residuals_expr(pk, config, q, t, qr, qp)]
            )
            qm, tm = ca.MX.sym("q", n), ca.MX.sym("t", N_FEATURES)
            qrm, qpm = ca.MX.sym("qr", n), ca.MX.sym("qp", n)
            cp = clearance_and_penalty(pk, config, qm)
            assert cp is not None
            r = ca.vertcat(paper(qm, tm, qrm, qpm), cp[1])
            self.function = ca.Function(
                name, [qm, tm, qrm, qpm], [r, ca.densify(ca.jacobian(r, qm))]
            )
        else:
            r = residuals_expr(pk, config, q, t, qr, qp)
            self.function = ca.Function(
                name, [q, t, qr, qp], [r, ca.densify(ca.jacobian(r, q))], {"cse": True}
            )
        self.m, self.n = int(r.shape[0]), n
        self._c = _compiled_or_none(self.function)

    def __call__(
        self, q: np.ndarray, targets: np.ndarray, q_ref: np.ndarray, q_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        c = self._c
        if c is None:
            r, j = self.function(q, targets, q_ref, q_prev)
            return np.array(r).reshape(-1), np.array(j)
        for buf, v in zip(c.inputs, (q, targets, q_ref, q_prev)):
            buf[:] = v
        c()
        return c.outputs[0].copy(), c.outputs[1].reshape((self.m, self.n), order="F").copy()


def _inside(q: np.ndarray, pk: PairKinematics) -> np.ndarray:
    # trf needs a strictly feasible start
    span = pk.upper - pk.lower
    return np.clip(q, pk.lower + 1e-10 * span, pk.upper - 1e-10 * span)


def best_known_cost(
    pk: PairKinematics,
    objective: Objective,
    compiled: CompiledObjective,
    targets: np.ndarray,
    q_prev: np.ndarray,
    q_ref: np.ndarray,
    starts: Sequence[np.ndarray],
    rng: np.random.Generator,
    clearance: Callable[[np.ndarray], float] | None = None,
) -> float:
    """Lowest eq. 3 cost scipy finds from ``starts`` plus the informed and random starts.

    Args:
        pk: The pair's kinematics.
        objective: Its eq. 3 residuals (numpy, with Pinocchio: the final costs).
        compiled: The same residuals compiled (the starts' iterations).
        targets: Robot targets, shape (13,).
        q_prev: Previous command (temporal term's reference), shape (n,).
        q_ref: Posture reference, shape (n,).
        starts: Extra starts, e.g. the solvers' answers, each shape (n,).
        rng: Source of the random starts.
        clearance: The self-collision clearance of a posture [m] (solver geometry); when
            given, only answers with a non-negative clearance count (the constrained
            optimum), and ``inf`` is returned if none has one.
    """

    def fun(q: np.ndarray) -> np.ndarray:
        return compiled(q, targets, q_ref, q_prev)[0]

    def jac(q: np.ndarray) -> np.ndarray:
        return compiled(q, targets, q_ref, q_prev)[1]

    def pinocchio_cost(q: np.ndarray) -> float:
        f, _ = pk.features_jacobian(q)
        r = objective.residuals(f, q, targets, q_ref, q_prev)
        if uses_collisions(pk, objective.config):
            col = pk.collision
            r = np.append(r, collision_residual(col.distances(q) - col.margin, objective.config))
        return cost_of_residuals(r)

    candidates = [q_prev, q_ref, pk.rest, *starts]
    candidates += list(pk.lower + rng.random((RANDOM_STARTS, pk.n)) * pk.range)
    unique: list[np.ndarray] = []
    for q in candidates:
        q = _inside(np.asarray(q, dtype=float), pk)
        if all(np.max(np.abs(q - u)) > 1e-9 for u in unique):
            unique.append(q)
    best = np.inf
    for q0 in unique:
        res = least_squares(
            fun,
            q0,
            jac=jac,
            bounds=(pk.lower, pk.upper),
            method="trf",
            loss="soft_l1",
            f_scale=1.0,
            max_nfev=OPTIMUM_NFEV,
        )
        q = np.clip(res.x, pk.lower, pk.upper)
        if clearance is None or clearance(q) >= 0:
            best = min(best, pinocchio_cost(q))
    return float(best)
