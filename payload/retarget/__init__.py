"""Retargeting of the operator's thumb-index geometry to the payload's finger pairs.

The paper's eq. 2 (pair features) and eq. 3 (bounded soft-L1 least squares), with two
solvers on the same objective:

* :class:`PairRetargeter`, the production solver: one compiled CasADi call per pair
  solve, warm-started, never leaving the bounds, with a hard iteration cap;
* :class:`ReferenceRetargeter`, faithful to the paper: ``scipy.optimize.least_squares``
  (trf, soft_l1, at most 20 function evaluations, analytic Jacobian).

:func:`calibrate` maps human features to robot targets and a posture reference; hand
description files (:func:`load_hand`) name the frames and joints of each pair, so the
retargeter runs on any hand URDF.


Names load on first use (module ``__getattr__``), so importing the package (or
a command module inside it) costs no numerical library.
"""

from __future__ import annotations

from payload.lazy import lazy_exports

_LAZY: dict[str, str] = {
    "PairCalibration": "payload.retarget.calibration",
    "PairRange": "payload.retarget.calibration",
    "calibrate": "payload.retarget.calibration",
    "pair_range": "payload.retarget.calibration",
    "wahba_rotation": "payload.retarget.calibration",
    "BACKENDS": "payload.retarget.casadi_solver",
    "PairRetargeter": "payload.retarget.casadi_solver",
    "build_solve_function": "payload.retarget.casadi_solver",
    "RetargetError": "payload.retarget.errors",
    "N_FEATURES": "payload.retarget.features",
    "PairFeatures": "payload.retarget.features",
    "PairKinematics": "payload.retarget.features",
    "features_from_points": "payload.retarget.features",
    "features_jacobian_from_points": "payload.retarget.features",
    "DEFAULT_HAND": "payload.retarget.hand",
    "HandDescription": "payload.retarget.hand",
    "PairDescription": "payload.retarget.hand",
    "hand_from_dict": "payload.retarget.hand",
    "load_hand": "payload.retarget.hand",
    "Objective": "payload.retarget.objective",
    "RetargetConfig": "payload.retarget.objective",
    "cost_of_residuals": "payload.retarget.objective",
    "soft_l1": "payload.retarget.objective",
    "ReferenceRetargeter": "payload.retarget.reference",
    "Retargeter": "payload.retarget.solver",
    "SolveInfo": "payload.retarget.solver",
}
"""Each public name and the module defining it."""

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
