"""The stowed-posture search: the finger posture with the largest clearance."""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping, Sequence

import numpy as np

from payload.design.params import FINGER_JOINTS, FINGERS
from payload.envelope.containment import box_clearance, protrusion
from payload.envelope.fit_results import (
    PostureSearch,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.progress import Progress, quiet
from payload.envelope.vehicle import Vehicle


def with_finger_posture(q: Mapping[str, float], finger: Sequence[float]) -> dict[str, float]:
    """``q`` with the same [mcp_flex, mcp_abd, pip, dip] on every finger [rad]."""
    out = dict(q)
    for f in FINGERS:
        for j, v in zip(FINGER_JOINTS, finger):
            out[f"{f}_{j}"] = float(v)
    return out


def finger_links(geom: PayloadGeometry) -> list[str]:
    """Links moved by a finger joint (the four fingers' links)."""
    fingers = {f"{f}_{j}" for f in FINGERS for j in FINGER_JOINTS}
    moved: set[str] = set()
    for j in geom.tree.joints:
        if j.name in fingers or j.parent in moved:
            moved.add(j.child)
    return [n for n in geom.links if n in moved]


def envelope_margin(
    geom: PayloadGeometry,
    poses: Mapping[str, np.ndarray],
    vehicle: Vehicle,
    links: Sequence[str] | None = None,
) -> tuple[float, str]:
    """Smallest signed part clearance to the walls (negative: protrusion) [m], and where.

    Closed form on the convex-hull vertices (exact for the polyhedral solids); the
    mounted part's mount face is left out.

    Args:
        geom: Collision geometry.
        poses: Link poses in the payload frame.
        vehicle: The vehicle.
        links: Links considered (default: all).
    """
    lo, hi = vehicle.bay_lower, vehicle.bay_upper
    best, where = np.inf, ""
    for name in geom.links if links is None else links:
        pts = geom.hull_vertices(name, poses[name])
        prot, w = protrusion(pts, lo, hi)
        if prot > 0:
            value = -prot
        else:
            skip = (5,) if name == geom.root else ()
            value, w = box_clearance(pts, lo, hi, skip)
        if value < best:
            best, where = value, f"{name} / {vehicle.walls[w]} wall"
    return float(best), where


def search_stowed_posture(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    q: Mapping[str, float],
    grid: int = 6,
    starts: int = 3,
    progress: Progress = quiet,
) -> PostureSearch:
    """The finger posture, inside the joint limits, that maximises the minimum clearance.

    The objective is the smaller of the fingers' envelope margin
    (:func:`envelope_margin`) and the smallest signed distance between a finger link
    and any non-adjacent link (parts the fingers do not move keep their clearance
    whatever the posture, and are reported apart); the four finger joints
    are shared by every finger (as the design's ``[stowed]`` posture is). A grid of
    ``grid**4`` postures seeds bounded Nelder-Mead refinements from the ``starts``
    best.

    Args:
        geom: Collision geometry.
        vehicle: The vehicle.
        q: The stowed configuration (rail, stage) the fingers are folded in.
        grid: Grid points per joint.
        starts: Local refinements.
        progress: Progress callback.

    Returns:
        The best posture found and its clearance.
    """
    t0 = time.perf_counter()
    limits = _finger_limits(geom)
    base = dict(q)
    base["stage"] = geom.tree.joint_map["stage"].lower
    fingers = finger_links(geom)
    pairs = [(a, b) for a, b in geom.pairs if a in fingers or b in fingers]
    count = 0

    def evaluate(x: np.ndarray) -> tuple[float, str]:
        nonlocal count
        count += 1
        x = np.clip(x, limits[:, 0], limits[:, 1])
        poses = geom.poses(with_finger_posture(base, x))
        margin, where = envelope_margin(geom, poses, vehicle, fingers)
        d, (a, b) = geom.min_distance(poses, pairs)
        if d < margin:
            return d, f"{a} / {b}"
        return margin, where

    axes = [np.linspace(lo, hi, grid) for lo, hi in limits]
    seeds = []
    total = grid**4
    for i, x in enumerate(itertools.product(*axes)):
        seeds.append((evaluate(np.array(x))[0], np.array(x)))
        if i % 25 == 0:
            progress("posture search: grid", i / total)
    seeds.sort(key=lambda s: -s[0])
    best_x, best_v = seeds[0][1], seeds[0][0]
    from scipy import optimize  # about 0.5 s of imports, for the search alone

    for k, (_, x0) in enumerate(seeds[:starts]):
        progress("posture search: refine", k / starts)
        res = optimize.minimize(
            lambda x: -evaluate(x)[0],
            x0,
            method="Nelder-Mead",
            options={
                "xatol": 1e-4,
                "fatol": 1e-7,
                "maxfev": 400,
                "initial_simplex": _simplex(x0, limits),
            },
        )
        x = np.clip(res.x, limits[:, 0], limits[:, 1])
        if -res.fun > best_v:
            best_x, best_v = x, -res.fun
    value, where = evaluate(best_x)
    progress("posture search", 1.0)
    finger = tuple(float(v) for v in best_x)
    return PostureSearch(finger, value, where, count, time.perf_counter() - t0)  # type: ignore[arg-type]


def _finger_limits(geom: PayloadGeometry) -> np.ndarray:
    """[lower, upper] of [mcp_flex, mcp_abd, pip, dip] (finger A's, shared by all), (4, 2)."""
    joints = geom.tree.joint_map
    return np.array([[joints[f"A_{j}"].lower, joints[f"A_{j}"].upper] for j in FINGER_JOINTS])


def _simplex(x0: np.ndarray, limits: np.ndarray) -> np.ndarray:
    step = 0.1 * (limits[:, 1] - limits[:, 0])
    pts = [x0]
    for i in range(len(x0)):
        x = x0.copy()
        x[i] = x[i] - step[i] if x[i] + step[i] > limits[i, 1] else x[i] + step[i]
        pts.append(x)
    return np.array(pts)


__all__ = [
    "envelope_margin",
    "finger_links",
    "search_stowed_posture",
    "with_finger_posture",
]
