"""The reference solver, faithful to the paper: ``scipy.optimize.least_squares``.

Trust-region reflective (``trf``) with the soft-L1 loss, box bounds, at most
``config.max_nfev`` (paper: 20) function evaluations per pair solve, and the analytic
Jacobian from Pinocchio's frame Jacobians through :mod:`payload.retarget.features`.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from payload.retarget.solver import Retargeter, SolveInfo


class ReferenceRetargeter(Retargeter):
    """Eq. 3 solved with ``scipy.optimize.least_squares`` (trf, soft_l1, analytic Jacobian).

    See :class:`~payload.retarget.solver.Retargeter` for the arguments and ``solve``.
    """

    def _solve(
        self, targets: np.ndarray, q_prev: np.ndarray, q_ref: np.ndarray
    ) -> tuple[np.ndarray, SolveInfo]:
        obj, pk = self.objective, self.kinematics
        cache: dict[str, object] = {}
        calls = [0]  # every residual evaluation, including any the Jacobian re-runs

        def fun(q: np.ndarray) -> np.ndarray:
            calls[0] += 1
            f, jf = pk.features_jacobian(q)
            cache["q"], cache["jf"] = q.copy(), jf
            return obj.residuals(f, q, targets, q_ref, q_prev)

        def jac(q: np.ndarray) -> np.ndarray:
            last = cache.get("q")
            if last is None or not np.array_equal(last, q):
                fun(q)
            return obj.jacobian(cache["jf"])  # type: ignore[arg-type]

        res = least_squares(
            fun,
            q_prev,
            jac=jac,
            bounds=(self.lower, self.upper),
            method="trf",
            loss="soft_l1",
            f_scale=1.0,
            max_nfev=self.config.max_nfev,
        )
        # trf keeps every iterate strictly inside the bounds: no clipping here, so a
        # violation would show in the benchmark's bound check.
        return np.array(res.x, dtype=float), SolveInfo(
            float(res.cost), int(res.nfev), bool(res.status > 0), calls[0]
        )
