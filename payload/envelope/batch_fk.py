"""Forward kinematics of many configurations at once: numpy over the samples.

The reach report places 100,000 sampled configurations; a Pinocchio call per sample
(:func:`payload.envelope.sampling.fingertips`) costs about a second of Python loop. Here
every joint of the design's kinematic tree (the tree the URDF is written from, so the
same kinematics) moves the points of all samples in one array operation: Rodrigues'
formula for the revolute joints, a shift along the axis for the prismatic ones. The
test compares the result with Pinocchio on the generated URDF.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from payload.design.params import FINGERS
from payload.design.tree import ALL_JOINTS, Joint, KinematicTree


def _times(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``m @ p_i`` for every row of ``p`` (n, 3), ``m`` (3, 3): ``p @ m.T``, written out
    so that no multi-threaded BLAS call runs per joint (it thrashes on a loaded machine)."""
    return p[:, 0:1] * m[:, 0] + p[:, 1:2] * m[:, 1] + p[:, 2:3] * m[:, 2]


def _rotate(p: np.ndarray, axis: Sequence[float], q: np.ndarray) -> np.ndarray:
    """Points ``p`` (n, 3) each rotated by its ``q`` [rad] about the unit ``axis``
    (Rodrigues' formula for vectors), shape (n, 3)."""
    k = np.asarray(axis, dtype=float)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])  # k x .
    c, s = np.cos(q)[:, None], np.sin(q)[:, None]
    along = p[:, 0:1] * k[0] + p[:, 1:2] * k[1] + p[:, 2:3] * k[2]
    return p * c + _times(p, cross) * s + along * k * (1.0 - c)


def _path(tree: KinematicTree, link: str) -> list[Joint]:
    """The joints from the root to ``link``, root first."""
    by_child = {j.child: j for j in tree.joints}
    out = []
    while link in by_child:
        out.append(by_child[link])
        link = by_child[link].parent
    return out[::-1]


def frame_positions_batch(
    tree: KinematicTree, samples: np.ndarray, frames: Sequence[str]
) -> np.ndarray:
    """Payload-frame positions of named frames for every configuration row.

    Each frame's point is carried from its link back to the root, joint by joint, as an
    (n, 3) array: the joint's motion (a rotation about, or shift along, its axis by each
    sample's value), then its fixed origin.

    Args:
        tree: The design's kinematic tree.
        samples: Shape (n, 18), :data:`ALL_JOINTS` order [rad, m]; other joints at 0.
        frames: Frame names (e.g. ``A_tip``), k of them.

    Returns:
        Shape (n, k, 3) [m].
    """
    samples = np.atleast_2d(np.asarray(samples, dtype=float))
    n = len(samples)
    column = {name: i for i, name in enumerate(ALL_JOINTS)}
    by_name = {f.name: f for f in tree.frames}
    missing = [f for f in frames if f not in by_name]
    if missing:
        raise KeyError(f"no frame named {', '.join(missing)}")
    out = np.empty((n, len(frames), 3))
    for k, name in enumerate(frames):
        frame = by_name[name]
        p = np.tile(np.asarray(frame.xyz, dtype=float), (n, 1))
        for j in reversed(_path(tree, frame.parent)):
            q = samples[:, column[j.name]] if j.name in column else np.zeros(n)
            if j.kind == "revolute":
                p = _rotate(p, j.axis, q)
            elif j.kind == "prismatic":
                p = p + q[:, None] * np.asarray(j.axis, dtype=float)
            origin = j.origin()
            p = _times(p, origin[:3, :3]) + origin[:3, 3]
        out[:, k] = p
    return out


def fingertips_batch(tree: KinematicTree, samples: np.ndarray) -> np.ndarray:
    """Fingertip positions of every sample, shape (n, 4, 3), fingers A, B, C, D [m]."""
    return frame_positions_batch(tree, samples, [f"{f}_tip" for f in FINGERS])


__all__ = ["fingertips_batch", "frame_positions_batch"]
