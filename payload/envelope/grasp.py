"""CTB grasp check: which thicknesses an opposing pair can close on."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from payload.design.tree import ALL_JOINTS, KinematicTree
from payload.envelope.batch_fk import frame_positions_batch
from payload.envelope.pairs import (
    OPPOSITION_CONE,
    PAIRS,
    grasp_base,
    pair_joints,
    pair_side,
)
from payload.envelope.sampling import frame_positions
from payload.envelope.vehicle import Vehicle
from payload.kinematics import Kinematics
from payload.project import SOURCES


class GraspFeature(NamedTuple):
    """A thickness of the Cargo Transfer Bag an opposing pair may close on.

    Attributes:
        name: What it is.
        thickness: Object thickness between the pads [m].
        source: Where the number comes from (``ASSUMPTION`` when it is not measured).
    """

    name: str
    thickness: float
    source: str


CTB_FEATURES: tuple[GraspFeature, ...] = (
    GraspFeature("handle strap (flat webbing)", 0.003, "ASSUMPTION: soft strap, ~3 mm"),
    GraspFeature("handle strap folded double", 0.006, "ASSUMPTION"),
    GraspFeature("bag edge: fabric wall with piping", 0.010, "ASSUMPTION"),
    GraspFeature("bag edge: two walls at a seam", 0.020, "ASSUMPTION"),
    GraspFeature("half CTB across its 23.5 cm side", 0.235, f"{SOURCES} (NASA packing data)"),
    GraspFeature("rigid CTB model across its 25 cm side", 0.25, f"{SOURCES} (pyastrobee)"),
)
"""Default features checked by the grasp check (``--thickness`` adds more)."""


class GraspResult(NamedTuple):
    """Whether a pair can close on a thickness, with a witness configuration.

    Attributes:
        feature: The feature checked.
        pair: Pair name.
        closes: A witness exists.
        span: The witness's fingertip separation [m] (NaN when none).
        angle: The witness's pinch-axis angle from the across-array axis [rad].
        depth: How far the witness's higher pad stays below the vehicle's bottom face [m].
        q: The witness's 8 pair joints [rad] (empty when none); the rail and stage are
            at :func:`grasp_base` (rail at home, stage deployed).
    """

    feature: GraspFeature
    pair: str
    closes: bool
    span: float
    angle: float
    depth: float
    q: np.ndarray


def opposition(p1: np.ndarray, p2: np.ndarray, side_sign: float) -> np.ndarray:
    """Angle between the pinch axis p1 -> p2 and the across-array direction [rad], (n,).

    Args:
        p1: Finger 1 tips, shape (n, 3) [m].
        p2: Finger 2 tips, shape (n, 3) [m].
        side_sign: +1 when finger 2 sits on the +y side, -1 when on the -y side.
    """
    d = p2 - p1
    cos = side_sign * d[:, 1] / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def pair_tips(
    kin: Kinematics, tree: KinematicTree, pair: str, q8: np.ndarray, batch: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Fingertips of a pair for joint rows of shape (n, 8), at :func:`grasp_base`, (n, 3) each.

    The other fingers' joints are 0 (they do not move this pair's fingertips). With
    ``batch`` the rows go through the numpy forward kinematics of the design's tree
    (:mod:`payload.envelope.batch_fk`, the same kinematics to rounding) instead of
    Pinocchio: the way for many rows at once.
    """
    q8 = np.atleast_2d(q8)
    rows = np.zeros((len(q8), len(ALL_JOINTS)))
    rows[:, [ALL_JOINTS.index(j) for j in pair_joints(pair)]] = q8
    for j, v in grasp_base(tree).items():
        rows[:, ALL_JOINTS.index(j)] = v
    frames = [f"{f}_tip" for f in PAIRS[pair]]
    tips = (
        frame_positions_batch(tree, rows, frames) if batch else frame_positions(kin, rows, frames)
    )
    return tips[:, 0], tips[:, 1]


def _pinch(
    kin: Kinematics,
    tree: KinematicTree,
    pair: str,
    rows: np.ndarray,
    side: float,
    batch: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Span [m], cosine of the opposition angle and higher tip z [m] for (n, 8) rows."""
    p1, p2 = pair_tips(kin, tree, pair, rows, batch)
    d = p2 - p1
    span = np.linalg.norm(d, axis=1)
    cos = side * d[:, 1] / np.maximum(span, 1e-12)
    return span, cos, np.maximum(p1[:, 2], p2[:, 2])


def symmetric_samples(
    tree: KinematicTree, pair: str, n: int, rng: np.random.Generator
) -> np.ndarray:
    """Pair configurations with both fingers at the same joint values, shape (n, 8) [rad].

    The two fingers of a pair face each other (one turned half a turn about z), so
    equal joint values place the fingertips symmetrically about the vertical axis
    between the two MCP joints: a family of opposing pinches that uniform sampling of
    the 8 joints rarely visits.
    """
    names = pair_joints(pair)[:4]
    lo = np.array([tree.joint_map[j].lower for j in names])
    hi = np.array([tree.joint_map[j].upper for j in names])
    half = lo + (hi - lo) * rng.random((n, 4))
    return np.hstack([half, half])


def grasp_check(
    kin: Kinematics,
    tree: KinematicTree,
    pair: str,
    candidates: np.ndarray,
    vehicle: Vehicle,
    features: Sequence[GraspFeature],
    is_free: Callable[[np.ndarray], bool] | None = None,
    window: float = 3e-3,
    tolerance: float = 1e-4,
    attempts: int = 8,
) -> list[GraspResult]:
    """Which thicknesses an opposing pair can close on, below the vehicle.

    A pair closes on thickness t when it has a witness: a configuration inside the
    joint limits with its pads opposing (pinch axis within :data:`OPPOSITION_CONE` of
    the across-array axis), both pads wholly below the vehicle's bottom face (rail at
    home, stage deployed: :func:`grasp_base`), a
    fingertip separation within ``tolerance`` of t plus the two pad radii, and no
    contact of the pair's links (``is_free``). The candidates whose separation lies
    within ``window`` of the target are moved onto it by a bounded least-squares step
    over the pair's 8 joints, then checked.

    Args:
        kin: The shared kinematics of the design.
        tree: The kinematic tree (joint limits, pad radius, home rail).
        pair: ``L`` or ``R``.
        candidates: Pair joint rows (finger 1 then finger 2), shape (m, 8) [rad].
        vehicle: The vehicle.
        features: Thicknesses to check.
        is_free: Collision check of the pair's 8 joints (default: none).
        window: Largest separation error of a starting candidate [m].
        tolerance: Largest separation error of a witness [m].
        attempts: Candidates tried per feature.

    Returns:
        One :class:`GraspResult` per feature (the nearest opposing candidate when none
        closes).
    """
    r = tree.design.finger.pad.radius
    bounds = np.array(
        [[tree.joint_map[j].lower, tree.joint_map[j].upper] for j in pair_joints(pair)]
    )
    side = pair_side(tree, pair)
    # screening the many candidates: numpy FK; the witnesses themselves: Pinocchio
    span, cos, z = _pinch(kin, tree, pair, candidates, side, batch=True)
    ok = (cos >= np.cos(OPPOSITION_CONE)) & (z + r <= vehicle.bottom_z)
    cand, span, cos, z = candidates[ok], span[ok], cos[ok], z[ok]
    out = []
    for feat in features:
        if len(cand) == 0:
            out.append(GraspResult(feat, pair, False, np.nan, np.nan, np.nan, np.empty(0)))
            continue
        target = feat.thickness + 2 * r
        order = np.argsort(np.abs(span - target))
        found = None
        for i in order[:attempts]:
            if abs(span[i] - target) > window:
                break
            found = _witness(kin, tree, pair, feat, cand[i], bounds, vehicle, is_free, tolerance)
            if found is not None:
                break
        if found is None:
            i = order[0]
            # the reported figures of the nearest candidate: Pinocchio, as for a witness
            (s,), (c,), (zz,) = _pinch(kin, tree, pair, cand[i][None, :], side)
            found = GraspResult(
                feat,
                pair,
                False,
                float(s),
                float(np.arccos(np.clip(c, -1, 1))),
                float(vehicle.bottom_z - (zz + r)),
                cand[i],
            )
        out.append(found)
    return out


def _witness(
    kin: Kinematics,
    tree: KinematicTree,
    pair: str,
    feat: GraspFeature,
    start: np.ndarray,
    bounds: np.ndarray,
    vehicle: Vehicle,
    is_free: Callable[[np.ndarray], bool] | None,
    tolerance: float,
) -> GraspResult | None:
    """Move one candidate onto the feature's separation; the witness when it holds."""
    from scipy import optimize  # imported when used: the reach check starts without it

    r = tree.design.finger.pad.radius
    side = pair_side(tree, pair)
    target = feat.thickness + 2 * r
    res = optimize.least_squares(
        lambda x: _pinch(kin, tree, pair, x[None, :], side)[0] - target,
        start,
        bounds=(bounds[:, 0], bounds[:, 1]),
        max_nfev=30,
        xtol=1e-12,
    )
    q8 = np.clip(res.x, bounds[:, 0], bounds[:, 1])
    (s,), (c,), (zz,) = _pinch(kin, tree, pair, q8[None, :], side)
    ang = float(np.arccos(np.clip(c, -1.0, 1.0)))
    depth = float(vehicle.bottom_z - (zz + r))
    if abs(s - target) > tolerance or ang > OPPOSITION_CONE or depth < 0:
        return None
    if is_free is not None and not is_free(q8):
        return None
    return GraspResult(feat, pair, True, float(s), ang, depth, q8)


__all__ = [
    "CTB_FEATURES",
    "GraspFeature",
    "GraspResult",
    "grasp_check",
    "opposition",
    "pair_tips",
    "symmetric_samples",
]
