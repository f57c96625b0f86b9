"""The finger pairs of the reach analysis: names, joints, links, sides."""

from __future__ import annotations

import numpy as np

from payload.design.params import FINGER_JOINTS
from payload.design.tree import KinematicTree
from payload.envelope import MIN_SAMPLES
from payload.errors import PayloadError

PAIRS: dict[str, tuple[str, str]] = {"L": ("A", "C"), "R": ("B", "D")}
"""Finger pairs: the left hand drives L = (A, C), the right hand R = (B, D)."""

OPPOSITION_CONE = np.radians(30.0)
"""Largest angle between a pinch axis and the across-array (y) axis for opposing pads [rad]."""


class ReachError(PayloadError):
    """Bad input to the reach analysis (a sample count, a thickness, a pair)."""


def check_reach_numbers(
    samples: int, seed: int, workers: int | None, error: type[Exception] = ReachError
) -> None:
    """Refuse a reach analysis's ``--samples`` below :data:`MIN_SAMPLES`, a negative
    ``--seed`` or ``--workers`` below 1 (``None``: the default) with one line, as
    ``error`` (``payload report reach``'s, or a command that runs the analysis, e.g.
    ``payload sweep``)."""
    if samples < MIN_SAMPLES:
        raise error(f"--samples must be >= {MIN_SAMPLES}, got {samples}")
    if seed < 0:
        raise error(f"--seed must be >= 0, got {seed}")
    if workers is not None and workers < 1:
        raise error(f"--workers must be >= 1, got {workers}")


def pair_joints(pair: str) -> list[str]:
    """The 8 joints of a pair: finger 1's four, then finger 2's."""
    if pair not in PAIRS:
        raise ReachError(f"unknown pair {pair!r} (expected one of: {', '.join(PAIRS)})")
    return [f"{f}_{j}" for f in PAIRS[pair] for j in FINGER_JOINTS]


def grasp_base(tree: KinematicTree) -> dict[str, float]:
    """Rail and stage of every grasp witness: rail at home, stage fully deployed [m]."""
    return {"rail": float(tree.design.home.rail), "stage": float(tree.joint_map["stage"].upper)}


def finger_link_names(tree: KinematicTree, finger: str) -> list[str]:
    """The links moved by a finger's joints."""
    names = {f"{finger}_{j}" for j in FINGER_JOINTS}
    moved: set[str] = set()
    for j in tree.joints:
        if j.name in names or j.parent in moved:
            moved.add(j.child)
    return [link.name for link in tree.links if link.name in moved]


def pair_side(tree: KinematicTree, pair: str) -> float:
    """+1 when finger 2 of the pair sits on the +y side of finger 1, else -1."""
    f1, f2 = PAIRS[pair]
    y1 = tree.joint_map[f"{f1}_mcp_flex"].xyz[1]
    y2 = tree.joint_map[f"{f2}_mcp_flex"].xyz[1]
    return 1.0 if y2 > y1 else -1.0


__all__ = [
    "OPPOSITION_CONE",
    "PAIRS",
    "ReachError",
    "check_reach_numbers",
    "finger_link_names",
    "grasp_base",
    "pair_joints",
    "pair_side",
]
