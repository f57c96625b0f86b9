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
"""

from payload.retarget import collision as _collision  # noqa: F401  (registers the collision model)
from payload.retarget.calibration import (
    PairCalibration,
    PairRange,
    calibrate,
    pair_range,
    wahba_rotation,
)
from payload.retarget.casadi_solver import BACKENDS, PairRetargeter, build_solve_function, cache_dir
from payload.retarget.errors import RetargetError
from payload.retarget.features import (
    N_FEATURES,
    PairFeatures,
    PairKinematics,
    features_from_points,
    features_jacobian_from_points,
)
from payload.retarget.hand import (
    DEFAULT_HAND,
    HandDescription,
    PairDescription,
    hand_from_dict,
    load_hand,
)
from payload.retarget.objective import Objective, RetargetConfig, cost_of_residuals, soft_l1
from payload.retarget.reference import ReferenceRetargeter
from payload.retarget.solver import Retargeter, SolveInfo

__all__ = [
    "BACKENDS",
    "DEFAULT_HAND",
    "N_FEATURES",
    "HandDescription",
    "Objective",
    "PairCalibration",
    "PairDescription",
    "PairFeatures",
    "PairKinematics",
    "PairRange",
    "PairRetargeter",
    "ReferenceRetargeter",
    "RetargetConfig",
    "RetargetError",
    "Retargeter",
    "SolveInfo",
    "build_solve_function",
    "cache_dir",
    "calibrate",
    "cost_of_residuals",
    "features_from_points",
    "features_jacobian_from_points",
    "hand_from_dict",
    "load_hand",
    "pair_range",
    "soft_l1",
    "wahba_rotation",
]
