"""Uniform samples of the joint space and their fingertips, batched."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from payload.design.params import FINGERS
from payload.design.tree import ALL_JOINTS, KinematicTree, rpy_matrix
from payload.envelope.pairs import (
    ReachError,
)

CHUNK = 20_000
"""Configurations per batch of the vectorised forward kinematics."""


def batch_link_poses(
    tree: KinematicTree, q: Mapping[str, np.ndarray], links: Sequence[str] | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Vectorised forward kinematics of the tree for a batch of configurations.

    Args:
        tree: The kinematic tree.
        q: Joint name -> values, shape (n,) each (a missing joint is 0) [rad or m].
        links: Links to return (default: all).

    Returns:
        Link name -> (rotations, shape (n, 3, 3); positions, shape (n, 3) [m]), in the
        payload frame.
    """
    n = len(next(iter(q.values()))) if q else 1
    names = list(tree.link_map) if links is None else list(links)
    parent_of = {j.child: j for j in tree.joints}
    needed: set[str] = set()
    for name in names:
        while name in parent_of and name not in needed:
            needed.add(name)
            name = parent_of[name].parent
    rot = {tree.root: np.broadcast_to(np.eye(3), (n, 3, 3))}
    pos = {tree.root: np.zeros((n, 3))}
    for j in tree.joints:
        if j.child not in needed:
            continue
        r_p, p_p = rot[j.parent], pos[j.parent]
        r_o = rpy_matrix(j.rpy)
        r_po = r_p @ r_o
        p_c = p_p + r_p @ np.asarray(j.xyz, dtype=float)
        values = q.get(j.name)
        axis = np.asarray(j.axis, dtype=float)
        if j.kind == "revolute" and values is not None:
            k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            s, c = np.sin(values)[:, None, None], np.cos(values)[:, None, None]
            r_m = np.eye(3) + s * k + (1 - c) * (k @ k)
            rot[j.child] = r_po @ r_m
        else:
            rot[j.child] = r_po
            if j.kind == "prismatic" and values is not None:
                p_c = p_c + (r_po @ axis) * np.asarray(values)[:, None]
        pos[j.child] = p_c
    return {name: (rot[name], pos[name]) for name in names}


def batch_frames(
    tree: KinematicTree, q: Mapping[str, np.ndarray], frames: Sequence[str]
) -> dict[str, np.ndarray]:
    """Payload-frame positions of named frames for a batch of configurations.

    Args:
        tree: The kinematic tree.
        q: Joint name -> values, shape (n,) each [rad or m].
        frames: Frame names (e.g. ``A_tip``).

    Returns:
        Frame name -> positions, shape (n, 3) [m].
    """
    fmap = {f.name: f for f in tree.frames}
    missing = [f for f in frames if f not in fmap]
    if missing:
        raise ReachError(f"unknown frame(s): {', '.join(missing)}")
    poses = batch_link_poses(tree, q, sorted({fmap[f].parent for f in frames}))
    out = {}
    for name in frames:
        fr = fmap[name]
        r, p = poses[fr.parent]
        out[name] = p + r @ np.asarray(fr.xyz, dtype=float)
    return out


def sample_configurations(
    tree: KinematicTree, n: int, rng: np.random.Generator, stage: float | None = None
) -> np.ndarray:
    """Uniform samples of the 17 manipulation joints inside their limits.

    Args:
        tree: The kinematic tree.
        n: Number of configurations.
        rng: Random generator.
        stage: Deployment coordinate of every sample (default: fully deployed) [m].

    Returns:
        Shape (n, 18), columns in :data:`ALL_JOINTS` order [rad, m].
    """
    lo = np.array([tree.joint_map[j].lower for j in ALL_JOINTS])
    hi = np.array([tree.joint_map[j].upper for j in ALL_JOINTS])
    out = lo + (hi - lo) * rng.random((n, len(ALL_JOINTS)))
    out[:, -1] = tree.joint_map["stage"].upper if stage is None else stage
    return out


def columns(samples: np.ndarray) -> dict[str, np.ndarray]:
    """Configuration rows (:data:`ALL_JOINTS` order) as joint name -> column."""
    return {j: samples[:, i] for i, j in enumerate(ALL_JOINTS)}


def fingertips(tree: KinematicTree, samples: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
    """Fingertip positions of every sample, in chunks.

    Args:
        tree: The kinematic tree.
        samples: Shape (n, 18), :data:`ALL_JOINTS` order.
        chunk: Batch size.

    Returns:
        Shape (n, 4, 3), fingers A, B, C, D, payload frame [m].
    """
    out = np.empty((len(samples), len(FINGERS), 3))
    frames = [f"{f}_tip" for f in FINGERS]
    for start in range(0, len(samples), chunk):
        block = samples[start : start + chunk]
        tips = batch_frames(tree, columns(block), frames)
        for i, name in enumerate(frames):
            out[start : start + chunk, i] = tips[name]
    return out


__all__ = [
    "CHUNK",
    "batch_frames",
    "batch_link_poses",
    "columns",
    "fingertips",
    "sample_configurations",
]
