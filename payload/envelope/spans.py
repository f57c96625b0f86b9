"""A pair's fingertip separation (eq. 2's l) over its joint space."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import optimize
from scipy.spatial import ConvexHull, cKDTree

from payload.design.params import FINGER_JOINTS
from payload.design.tree import KinematicTree
from payload.envelope.pairs import (
    PAIRS,
    ReachError,
    grasp_base,
    pair_joints,
)
from payload.envelope.sampling import (
    batch_frames,
)


class SpanRange(NamedTuple):
    """Range of a pair's fingertip separation (eq. 2's l) over its joint space.

    Attributes:
        pair: Pair name.
        minimum: Smallest separation [m].
        maximum: Largest separation [m].
        q_min: The 8 pair joints (finger 1 then finger 2) at the minimum [rad].
        q_max: The 8 pair joints at the maximum [rad].
    """

    pair: str
    minimum: float
    maximum: float
    q_min: np.ndarray
    q_max: np.ndarray


def pair_tips(tree: KinematicTree, pair: str, q8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fingertips of a pair for joint rows of shape (n, 8), at :func:`grasp_base`."""
    names = pair_joints(pair)
    q = {j: q8[:, i] for i, j in enumerate(names)}
    q.update({j: np.full(len(q8), v) for j, v in grasp_base(tree).items()})
    tips = batch_frames(tree, q, [f"{f}_tip" for f in PAIRS[pair]])
    f1, f2 = PAIRS[pair]
    return tips[f"{f1}_tip"], tips[f"{f2}_tip"]


def _finger_tips(tree: KinematicTree, finger: str, q4: np.ndarray) -> np.ndarray:
    """Fingertip of one finger for joint rows of shape (n, 4), rail and stage at 0 [m]."""
    names = [f"{finger}_{j}" for j in FINGER_JOINTS]
    return batch_frames(tree, {j: q4[:, i] for i, j in enumerate(names)}, [f"{finger}_tip"])[
        f"{finger}_tip"
    ]


def _check_common_parent(tree: KinematicTree, pair: str) -> None:
    f1, f2 = PAIRS[pair]
    p1, p2 = tree.joint_map[f"{f1}_mcp_flex"].parent, tree.joint_map[f"{f2}_mcp_flex"].parent
    if p1 != p2:
        raise ReachError(f"pair {pair}: fingers {f1} and {f2} hang from different links")


def span_range(
    tree: KinematicTree,
    pair: str,
    q1: np.ndarray,
    q2: np.ndarray,
    refine: bool = True,
) -> SpanRange:
    """Smallest and largest fingertip separation of a pair over every combination.

    Args:
        tree: The kinematic tree.
        pair: ``L`` or ``R``.
        q1: Finger 1 joint samples, shape (n1, 4) [rad].
        q2: Finger 2 joint samples, shape (n2, 4) [rad].
        refine: Refine both extremes by a bounded local search (L-BFGS-B).

    Returns:
        The :class:`SpanRange` (over the n1 x n2 combinations when not refined).
    """
    _check_common_parent(tree, pair)
    f1, f2 = PAIRS[pair]
    p1 = _finger_tips(tree, f1, q1)
    p2 = _finger_tips(tree, f2, q2)
    # nearest: a k-d tree over finger 2's cloud
    dist, idx = cKDTree(p2).query(p1, k=1, workers=-1)
    i_min = int(np.argmin(dist))
    j_min = int(idx[i_min])
    # farthest: attained at hull vertices of both clouds (a convex function of each point)
    h1 = _hull_indices(p1)
    h2 = _hull_indices(p2)
    d = np.linalg.norm(p1[h1][:, None, :] - p2[h2][None, :, :], axis=2)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    i_max, j_max = int(h1[a]), int(h2[b])
    x_min = np.concatenate([q1[i_min], q2[j_min]])
    x_max = np.concatenate([q1[i_max], q2[j_max]])
    lo_d, hi_d = float(dist[i_min]), float(d[a, b])
    if refine:
        x_min, lo_d = _refine_span(tree, pair, x_min, +1.0, lo_d)
        x_max, hi_d = _refine_span(tree, pair, x_max, -1.0, hi_d)
    return SpanRange(pair, lo_d, hi_d, x_min, x_max)


def _hull_indices(points: np.ndarray) -> np.ndarray:
    if len(points) < 5:
        return np.arange(len(points))
    try:
        return ConvexHull(points).vertices
    except Exception:  # degenerate (coplanar) clouds: every point is a candidate
        return np.arange(len(points))


def span_of(tree: KinematicTree, pair: str, q8: np.ndarray) -> np.ndarray:
    """Fingertip separation for pair joint rows of shape (n, 8) [m], shape (n,)."""
    p1, p2 = pair_tips(tree, pair, np.atleast_2d(q8))
    return np.linalg.norm(p2 - p1, axis=1)


def _refine_span(
    tree: KinematicTree, pair: str, x0: np.ndarray, sign: float, value: float
) -> tuple[np.ndarray, float]:
    names = pair_joints(pair)
    bounds = [(tree.joint_map[j].lower, tree.joint_map[j].upper) for j in names]
    h = 1e-6

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        rows = np.vstack([x, x + h * np.eye(len(x))])
        s = span_of(tree, pair, rows)
        return float(sign * s[0]), sign * (s[1:] - s[0]) / h

    res = optimize.minimize(
        fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 60}
    )
    x = np.clip(res.x, [b[0] for b in bounds], [b[1] for b in bounds])
    s = float(span_of(tree, pair, x)[0])
    if sign * s < sign * value:
        return x, s
    return x0, value


__all__ = [
    "SpanRange",
    "pair_tips",
    "span_of",
    "span_range",
]
