"""Hand frames: the 25 WebXR XRHand joints per hand, and the WebXR -> workbench conversion.

WebXR reference spaces are Y up, X right, -Z forward (metres). The workbench is
REP-103: X forward, Y left, Z up. So ``x_wb = -z_xr``, ``y_wb = -x_xr``, ``z_wb = y_xr``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from payload.errors import PayloadError
from payload.rotations import matrix_to_quat, quat_to_matrix
from payload.vecmath import F64, cross

XR_JOINTS: tuple[str, ...] = (
    "wrist",
    "thumb-metacarpal",
    "thumb-phalanx-proximal",
    "thumb-phalanx-distal",
    "thumb-tip",
    *(
        f"{finger}-{part}"
        for finger in ("index-finger", "middle-finger", "ring-finger", "pinky-finger")
        for part in (
            "metacarpal",
            "phalanx-proximal",
            "phalanx-intermediate",
            "phalanx-distal",
            "tip",
        )
    ),
)
"""The 25 WebXR XRHand joint names in the specification's order."""

JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(XR_JOINTS)}
JOINTS_SHAPE: tuple[int, int] = (len(XR_JOINTS), 3)
"""A hand's joint positions: one row (x, y, z) per joint."""
WRIST = JOINT_INDEX["wrist"]
THUMB_TIP = JOINT_INDEX["thumb-tip"]
THUMB_DISTAL = JOINT_INDEX["thumb-phalanx-distal"]
INDEX_TIP = JOINT_INDEX["index-finger-tip"]
INDEX_DISTAL = JOINT_INDEX["index-finger-phalanx-distal"]
INDEX_KNUCKLE = JOINT_INDEX["index-finger-phalanx-proximal"]
MIDDLE_KNUCKLE = JOINT_INDEX["middle-finger-phalanx-proximal"]
PINKY_KNUCKLE = JOINT_INDEX["pinky-finger-phalanx-proximal"]

WEBXR_TO_WORKBENCH = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Rotation taking WebXR (Y up, -Z forward) vectors to workbench (REP-103) vectors."""


def round_to_grid(joints: np.ndarray, grid: float) -> np.ndarray:
    """Joint positions rounded to ``grid`` [m], a new array (what a headset reporting on
    that grid gives: :func:`payload.trials.jointcodec.quantize_joints`). NaN stays NaN."""
    # rint is what round(decimals=0) calls on floats (the same bits, without its wrappers)
    return np.rint(np.asarray(joints, dtype=np.float64) / grid) * grid


class HandFrameError(PayloadError):
    """A hand frame is malformed (wrong shape, unknown hand, non-finite timestamp)."""


@dataclass(frozen=True)
class Hand:
    """One tracked hand.

    Attributes:
        joints: Joint positions, shape (25, 3) [m], in :data:`XR_JOINTS` order; NaN rows
            when not tracked.
        tracked: Whether the tracker reports the hand.
        orientations: Optional joint orientations as quaternions (w, x, y, z), shape (25, 4).
    """

    joints: np.ndarray
    tracked: bool = True
    orientations: np.ndarray | None = None

    def __post_init__(self) -> None:
        j = np.array(self.joints, dtype=np.float64)
        if j.shape != (25, 3):
            raise HandFrameError(f"hand joints must have shape (25, 3), got {j.shape}")
        j.setflags(write=False)
        object.__setattr__(self, "joints", j)
        if self.orientations is not None:
            o = np.array(self.orientations, dtype=np.float64)
            if o.shape != (25, 4):
                raise HandFrameError(f"hand orientations must have shape (25, 4), got {o.shape}")
            o.setflags(write=False)
            object.__setattr__(self, "orientations", o)

    @classmethod
    def taking(cls, joints: np.ndarray, tracked: bool = True) -> Hand:
        """A hand of joints made for it: a float64 array (25, 3) of the caller's own
        (C-contiguous, owning its data, writeable, held by nothing else), frozen here and
        kept instead of copied. Anything else is copied and checked as the constructor
        does."""
        if (
            type(joints) is np.ndarray
            and joints.dtype == F64
            and joints.shape == JOINTS_SHAPE
            and joints.base is None
            and joints.flags.c_contiguous
            and joints.flags.writeable
        ):
            joints.setflags(write=False)
            hand = object.__new__(cls)
            hand.__dict__.update(joints=joints, tracked=tracked, orientations=None)
            return hand
        return cls(joints, tracked)

    @staticmethod
    def untracked() -> Hand:
        return Hand(np.full(JOINTS_SHAPE, np.nan), tracked=False)

    def joint(self, name: str) -> np.ndarray:
        """Position of a named joint, shape (3,) [m]."""
        return self.joints[JOINT_INDEX[name]]

    @property
    def wrist(self) -> np.ndarray:
        return self.joints[WRIST]

    def is_valid(self, max_extent: float = 0.35) -> bool:
        """Tracked, finite, and every joint within ``max_extent`` metres of the wrist."""
        if not self.tracked or not np.all(np.isfinite(self.joints)):
            return False
        return bool(np.all(np.linalg.norm(self.joints - self.wrist, axis=1) <= max_extent))


@dataclass(frozen=True)
class HandFrame:
    """Both hands at one instant.

    Attributes:
        stamp: Time [s] (monotonic within a session).
        left: The left hand.
        right: The right hand.
        frame: ``"workbench"`` (REP-103, Z up) or ``"webxr"`` (Y up).
    """

    stamp: float
    left: Hand
    right: Hand
    frame: str = "workbench"

    def __post_init__(self) -> None:
        stamp = self.stamp
        if not (math.isfinite(stamp) if type(stamp) is float else np.isfinite(stamp)):
            raise HandFrameError(f"hand frame stamp is not finite: {self.stamp}")
        if self.frame not in ("workbench", "webxr"):
            raise HandFrameError(f"unknown hand frame convention {self.frame!r}")

    def hand(self, side: str) -> Hand:
        if side in ("left", "L"):
            return self.left
        if side in ("right", "R"):
            return self.right
        raise HandFrameError(f"unknown hand {side!r} (expected left/right)")

    def to_workbench(self) -> HandFrame:
        """This frame in workbench coordinates (no-op when already there)."""
        if self.frame == "workbench":
            return self

        def conv(h: Hand) -> Hand:
            joints = h.joints @ WEBXR_TO_WORKBENCH.T
            ori = None
            if h.orientations is not None:
                ori = np.array([_rotate_quat(q) for q in h.orientations])
            return Hand(joints, h.tracked, ori)

        return HandFrame(self.stamp, conv(self.left), conv(self.right), "workbench")


def _rotate_quat(q: np.ndarray) -> np.ndarray:
    """Express a WebXR orientation quaternion (w, x, y, z) in the workbench frame."""
    r = quat_to_matrix(q)
    return matrix_to_quat(WEBXR_TO_WORKBENCH @ r @ WEBXR_TO_WORKBENCH.T)


def wrist_frame(hand: Hand) -> np.ndarray:
    """Wrist frame built from joint positions alone, as a (4, 4) transform wrist -> workbench.

    x points from the wrist to the middle-finger knuckle (along the hand), z is normal to
    the plane of x and the pinky-to-index knuckle direction, y completes the right-handed
    frame. Independent of the tracker's joint orientations, so positions-only data works.
    """
    w = hand.joints[WRIST]
    along = hand.joints[MIDDLE_KNUCKLE] - w
    across = hand.joints[INDEX_KNUCKLE] - hand.joints[PINKY_KNUCKLE]
    x = along / math.sqrt(along.dot(along))  # np.linalg.norm's formula, without its overhead
    z = cross(x, across)
    z /= math.sqrt(z.dot(z))
    y = cross(z, x)
    t = np.eye(4)
    t[:3, :3] = np.column_stack([x, y, z])
    t[:3, 3] = w
    return t


def pinch_points(hand: Hand, frame: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Thumb and index fingertip and distal-joint points, optionally in a given frame.

    Args:
        hand: The hand.
        frame: A (4, 4) transform frame -> workbench; points are expressed in that frame.

    Returns:
        ``p1``/``a1`` (thumb tip, thumb distal joint) and ``p2``/``a2`` (index tip, index
        distal joint), shape (3,) each [m].
    """
    pts = {
        "p1": hand.joints[THUMB_TIP],
        "a1": hand.joints[THUMB_DISTAL],
        "p2": hand.joints[INDEX_TIP],
        "a2": hand.joints[INDEX_DISTAL],
    }
    if frame is None:
        return {k: v.copy() for k, v in pts.items()}
    rot, pos = frame[:3, :3], frame[:3, 3]
    return {k: rot.T @ (v - pos) for k, v in pts.items()}
