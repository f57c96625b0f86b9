"""Fingertip workspaces and the rail's pair spacing."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from payload.design.params import FINGERS
from payload.envelope.pairs import (
    PAIRS,
    ReachError,
)
from payload.kinematics import Kinematics


class Workspace(NamedTuple):
    """A fingertip's sampled, reachable workspace.

    Attributes:
        finger: Finger name.
        points: Reachable fingertip positions, shape (k, 3), payload frame [m].
        hull_volume: Volume of the points' convex hull [m^3].
        lower: Lower bounding-box corner, shape (3,) [m].
        upper: Upper bounding-box corner, shape (3,) [m].
        below_vehicle: Largest depth of the fingertip below the vehicle's bottom face [m].
        reachable: Fraction of the samples kept (the finger touching nothing).
    """

    finger: str
    points: np.ndarray
    hull_volume: float
    lower: np.ndarray
    upper: np.ndarray
    below_vehicle: float
    reachable: float


def workspace(
    finger: str, points: np.ndarray, bottom_z: float, keep: np.ndarray | None = None
) -> Workspace:
    """Hull volume, bounds and depth below the vehicle of a fingertip cloud.

    Args:
        finger: Finger name.
        points: Shape (n, 3) [m].
        bottom_z: z of the vehicle's bottom face [m].
        keep: Samples to keep, shape (n,) (default: all).
    """
    from scipy.spatial import ConvexHull  # imported when used: the reach check starts without it

    frac = 1.0 if keep is None else float(np.mean(keep))
    pts = points if keep is None else points[keep]
    if len(pts) < 4:
        raise ReachError(f"finger {finger}: fewer than 4 reachable samples; sample more")
    hull = ConvexHull(pts)
    return Workspace(
        finger,
        pts,
        float(hull.volume),
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
    "Workspace",
    "rail_spacing",
    "value_range",
    "workspace",
]
