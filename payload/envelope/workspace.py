"""Fingertip workspaces and the rail's pair spacing."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from payload.design.params import FINGERS
from payload.envelope.pairs import PAIRS
from payload.kinematics import Kinematics

MIN_HULL_POINTS = 4
"""Reachable samples a workspace needs for its hull (four points span a volume)."""


class Workspace(NamedTuple):
    """A fingertip's sampled, reachable workspace.

    Attributes:
        finger: Finger name.
        points: Reachable fingertip positions, shape (k, 3), payload frame [m].
        hull_volume: Volume of the points' convex hull [m^3] (NaN with fewer than
            :data:`MIN_HULL_POINTS` points: see :attr:`too_few`).
        lower: Lower bounding-box corner, shape (3,) [m] (NaN without points).
        upper: Upper bounding-box corner, shape (3,) [m] (NaN without points).
        below_vehicle: Largest depth of the fingertip below the vehicle's bottom face [m]
            (NaN without points).
        reachable: Fraction of the samples kept (the finger touching nothing).
    """

    finger: str
    points: np.ndarray
    hull_volume: float
    lower: np.ndarray
    upper: np.ndarray
    below_vehicle: float
    reachable: float

    @property
    def too_few(self) -> bool:
        """Whether too few samples reached (fewer than :data:`MIN_HULL_POINTS`) to measure
        the workspace: the finger almost never moves free, or the sampling is too sparse."""
        return len(self.points) < MIN_HULL_POINTS


def workspace(
    finger: str, points: np.ndarray, bottom_z: float, keep: np.ndarray | None = None
) -> Workspace:
    """Hull volume, bounds and depth below the vehicle of a fingertip cloud.

    Too few points for a hull (a finger that almost never moves free) is a result, not an
    error: the workspace says so (:attr:`Workspace.too_few`) and the reach fails on it.

    Args:
        finger: Finger name.
        points: Shape (n, 3) [m].
        bottom_z: z of the vehicle's bottom face [m].
        keep: Samples to keep, shape (n,) (default: all).
    """
    from scipy.spatial import ConvexHull  # imported when used: the reach check starts without it

    frac = 1.0 if keep is None else float(np.mean(keep))
    pts = points if keep is None else points[keep]
    if len(pts) == 0:
        nan = np.full(3, np.nan)
        return Workspace(finger, pts, float("nan"), nan, nan.copy(), float("nan"), frac)
    volume = float(ConvexHull(pts).volume) if len(pts) >= MIN_HULL_POINTS else float("nan")
    return Workspace(
        finger,
        pts,
        volume,
        pts.min(axis=0),
        pts.max(axis=0),
        float(bottom_z - pts[:, 2].min()),
        frac,
    )


def rail_spacing(kin: Kinematics) -> tuple[float, float]:
    """Pair spacing along the rail axis at the two rail limits [m].

    The spacing is the x distance between the pairs' centres (the midpoints of the
    pairs' MCP flexion axes, pair R minus pair L), on the shared kinematics.
    """
    (i,) = kin.q_indices(["rail"])
    knuckles = [f"{f}_knuckle" for f in FINGERS]
    dx = []
    for rail in (kin.lower[i], kin.upper[i]):
        q = kin.configuration({"rail": float(rail)})
        pos = dict(zip(knuckles, kin.frame_positions(q, knuckles)))
        centre = {
            p: 0.5 * (pos[f"{a}_knuckle"] + pos[f"{b}_knuckle"]) for p, (a, b) in PAIRS.items()
        }
        dx.append(float(centre["R"][0] - centre["L"][0]))
    return min(dx), max(dx)


def value_range(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of ``values``; (NaN, NaN) when empty."""
    if len(values) == 0:
        return (float("nan"), float("nan"))
    return (float(values.min()), float(values.max()))


__all__ = [
    "MIN_HULL_POINTS",
    "Workspace",
    "rail_spacing",
    "value_range",
    "workspace",
]
