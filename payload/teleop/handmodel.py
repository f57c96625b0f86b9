"""A kinematic human hand producing the 25 WebXR joints, for the synthetic operator.

Each finger is a chain of phalanges of fixed length flexing in its own plane; the thumb
flexes in a plane tilted toward the palm so that closing the aperture brings the thumb
and index tips together (a pinch) and opening it spreads them (about 9 cm at size 1).
The model is drawn for a right hand in its wrist frame (x toward the fingers, y toward
the thumb, z the back of the hand) and mirrored (y -> -y) for a left hand.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from payload.teleop.hands import JOINT_INDEX

# knuckle (phalanx-proximal) positions and phalanx lengths of a size-1 hand [m]
_FINGERS = {
    "index-finger": ((0.092, 0.024), (0.040, 0.024, 0.020)),
    "middle-finger": ((0.096, 0.003), (0.044, 0.027, 0.021)),
    "ring-finger": ((0.090, -0.016), (0.041, 0.026, 0.020)),
    "pinky-finger": ((0.082, -0.033), (0.032, 0.020, 0.018)),
}
_THUMB_BASE = np.array([0.03, 0.022, -0.015])
_THUMB_LENGTHS = (0.044, 0.033, 0.027)


def _chain(origin: np.ndarray, lengths, angles, u: np.ndarray, v: np.ndarray) -> list:
    """Joint points of a planar chain starting along ``u`` and flexing toward ``v``."""
    pts = [origin]
    cum = 0.0
    p = origin
    for length, ang in zip(lengths, angles):
        cum += ang
        p = p + length * (np.cos(cum) * u + np.sin(cum) * v)
        pts.append(p)
    return pts


@dataclass(frozen=True)
class HandModel:
    """A parametric hand.

    Attributes:
        side: ``"left"`` or ``"right"``.
        size: Scale factor on every length (1.0 = a medium adult hand).
    """

    side: str = "right"
    size: float = 1.0

    def local_joints(self, aperture: float, curl: float = 0.6) -> np.ndarray:
        """Joint positions in the wrist frame, shape (25, 3) [m].

        Args:
            aperture: 0 = pinch (thumb and index tips together), 1 = wide open.
            curl: Flexion of the middle, ring and pinky fingers [rad per joint].
        """
        s = float(np.clip(aperture, 0.0, 1.0))
        out = np.zeros((25, 3))
        x, z = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0])
        for name, ((kx, ky), lengths) in _FINGERS.items():
            knuckle = np.array([kx, ky, 0.0])
            base = np.array([0.03, ky * 0.6, 0.0])
            if name == "index-finger":
                angles = (0.75 - 0.65 * s, 0.55 - 0.45 * s, 0.35 - 0.3 * s)
            else:
                angles = (curl, curl, curl * 0.6)
            pts = _chain(knuckle, lengths, angles, x, z)
            out[JOINT_INDEX[f"{name}-metacarpal"]] = base
            parts = ("phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip")
            for part, p in zip(parts, pts):
                out[JOINT_INDEX[f"{name}-{part}"]] = p
        # thumb: starts along (forward, thumb side), flexes across the palm toward the index
        # plane chosen so the tips are ~18 mm apart pinched and ~95 mm open (size 1)
        u = np.array([0.573, 0.786, -0.232])
        v = np.array([0.633, -0.604, -0.484])
        u /= np.linalg.norm(u)
        v -= np.dot(v, u) * u
        v /= np.linalg.norm(v)
        ang = (0.2 + 0.3 * (1 - s), 0.2 + 0.4 * (1 - s), 0.1 + 0.35 * (1 - s))
        pts = _chain(_THUMB_BASE, _THUMB_LENGTHS, ang, u, v)
        for part, p in zip(("metacarpal", "phalanx-proximal", "phalanx-distal", "tip"), pts):
            out[JOINT_INDEX[f"thumb-{part}"]] = p
        out *= self.size
        if self.side == "left":
            out[:, 1] *= -1.0
        return out

    def joints(
        self, wrist: np.ndarray, rotation: np.ndarray, aperture: float, curl: float = 0.6
    ) -> np.ndarray:
        """Joint positions in the workbench frame, shape (25, 3) [m].

        Args:
            wrist: Wrist position, shape (3,) [m].
            rotation: Wrist frame -> workbench rotation, shape (3, 3).
            aperture: 0 = pinch, 1 = open.
            curl: Flexion of the other three fingers [rad].
        """
        local = self.local_joints(aperture, curl)
        return local @ np.asarray(rotation).T + np.asarray(wrist)
