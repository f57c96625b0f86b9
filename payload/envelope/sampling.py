"""Uniform samples of the joint space, and their frames on the shared kinematics.

Forward kinematics is Pinocchio's (:class:`payload.kinematics.Kinematics`), the model
the retargeter and the review use, on the design's generated URDF
(:func:`payload.envelope.kinematics.design_kinematics`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from payload.design.params import FINGERS
from payload.design.tree import ALL_JOINTS, KinematicTree

if TYPE_CHECKING:  # Pinocchio loads with the kinematics, not with the sampling
    from payload.kinematics import Kinematics


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


def configurations(kin: Kinematics, samples: np.ndarray) -> np.ndarray:
    """Configuration rows (:data:`ALL_JOINTS` order) as Pinocchio configurations, (n, nq)."""
    samples = np.atleast_2d(np.asarray(samples, dtype=float))
    out = np.tile(kin.neutral(), (len(samples), 1))
    out[:, kin.q_indices(ALL_JOINTS)] = samples
    return out


def frame_positions(kin: Kinematics, samples: np.ndarray, frames: Sequence[str]) -> np.ndarray:
    """Payload-frame positions of ``frames`` for configuration rows, shape (n, k, 3) [m].

    Args:
        kin: The shared kinematics (:func:`payload.envelope.kinematics.design_kinematics`).
        samples: Shape (n, 18), :data:`ALL_JOINTS` order [rad, m].
        frames: Frame names (e.g. ``A_tip``), k of them.
    """
    return kin.frame_positions_batch(configurations(kin, samples), list(frames))


def fingertips(kin: Kinematics, samples: np.ndarray) -> np.ndarray:
    """Fingertip positions of every sample, shape (n, 4, 3), fingers A, B, C, D [m].

    Args:
        kin: The shared kinematics (:func:`payload.envelope.kinematics.design_kinematics`).
        samples: Shape (n, 18), :data:`ALL_JOINTS` order [rad, m].
    """
    return frame_positions(kin, samples, [f"{f}_tip" for f in FINGERS])


__all__ = [
    "configurations",
    "fingertips",
    "frame_positions",
    "sample_configurations",
]
