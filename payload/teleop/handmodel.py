"""A kinematic human hand producing the 25 WebXR joints, for the synthetic operator.

Each finger is a chain of phalanges of fixed length flexing in its own plane; the thumb
flexes in a plane tilted toward the palm so that closing the aperture brings the thumb
and index tips together (a pinch) and opening it spreads them (about 9 cm at size 1).
The model is drawn for a right hand in its wrist frame (x toward the fingers, y toward
the thumb, z the back of the hand) and mirrored (y -> -y) for a left hand.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.teleop.handmodel_c import DEFAULT_CURL, compiled_held_hand, tremulous_wrist
from payload.teleop.hands import JOINT_INDEX, JOINTS_SHAPE

# knuckle (phalanx-proximal) positions and phalanx lengths of a size-1 hand [m]
_FINGERS = {
    "index-finger": ((0.092, 0.024), (0.040, 0.024, 0.020)),
    "middle-finger": ((0.096, 0.003), (0.044, 0.027, 0.021)),
    "ring-finger": ((0.090, -0.016), (0.041, 0.026, 0.020)),
    "pinky-finger": ((0.082, -0.033), (0.032, 0.020, 0.018)),
}
_THUMB_BASE = np.array([0.03, 0.022, -0.015])
_THUMB_LENGTHS = (0.044, 0.033, 0.027)


def _unit_thumb_plane() -> tuple[np.ndarray, np.ndarray]:
    """The thumb's flexion plane: ``u`` along it at rest, ``v`` toward the index."""
    u = np.array([0.573, 0.786, -0.232])
    v = np.array([0.633, -0.604, -0.484])
    u /= np.linalg.norm(u)
    v -= np.dot(v, u) * u
    v /= np.linalg.norm(v)
    return u, v


_THUMB_U, _THUMB_V = _unit_thumb_plane()
_X, _Z = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0])
_PARTS = ("phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip")
_THUMB_PARTS = ("metacarpal", "phalanx-proximal", "phalanx-distal", "tip")

# the five planar chains (four fingers, then the thumb) as arrays, so one hand is a few
# array operations: chain origins (5, 3), phalanx lengths (5, 3), flexion plane (u, v)
# (5, 3) each, the rows of the 25 joints the chain points (5, 4) fill, and the finger
# metacarpals (4, 3) with their rows (4,)
_ORIGINS = np.array([[kx, ky, 0.0] for (kx, ky), _ in _FINGERS.values()] + [_THUMB_BASE])
_LENGTHS = np.array([lengths for _, lengths in _FINGERS.values()] + [_THUMB_LENGTHS])
_U = np.array([_X] * 4 + [_THUMB_U])
_V = np.array([_Z] * 4 + [_THUMB_V])
_CHAIN_ROWS = np.array(
    [[JOINT_INDEX[f"{name}-{part}"] for part in _PARTS] for name in _FINGERS]
    + [[JOINT_INDEX[f"thumb-{part}"] for part in _THUMB_PARTS]]
)
_METACARPALS = np.array([[0.03, ky * 0.6, 0.0] for (_, ky), _ in _FINGERS.values()])
_METACARPAL_ROWS = np.array([JOINT_INDEX[f"{name}-metacarpal"] for name in _FINGERS])
assert next(iter(_FINGERS)) == "index-finger"  # the row whose angles follow the aperture
# the joint angles of the chains: the index's a - b s for the aperture s, the thumb's
# a + b (1 - s) (it starts along (forward, thumb side) and flexes across the palm toward
# the index: the plane is chosen so that the tips are ~18 mm apart pinched, ~95 mm open),
# the other three fingers' share of the curl
_INDEX_ANGLES = np.array([[0.75, 0.65], [0.55, 0.45], [0.35, 0.3]])
_THUMB_ANGLES = np.array([[0.2, 0.3], [0.2, 0.4], [0.1, 0.35]])
_CURL_SHARES = np.array([1.0, 1.0, 0.6])


@functools.lru_cache(maxsize=256)
def _local_joints(side: str, size: float, s: float, curl: float) -> np.ndarray:
    """:meth:`HandModel.local_joints` for a clipped aperture ``s`` (cached, read-only: the
    synthetic operator holds its aperture for long spells and both hands share it).

    Each chain starts at its origin along ``u`` and flexes toward ``v``: its points are
    the origin plus the cumulated phalanges ``length (cos(a) u + sin(a) v)``, ``a`` the
    cumulated joint angles."""
    out = np.zeros(JOINTS_SHAPE)
    c = 1 - s
    ia, ta = _INDEX_ANGLES.tolist(), _THUMB_ANGLES.tolist()
    fingers = [curl * k for k in _CURL_SHARES.tolist()]
    angles = np.array(
        [[a - b * s for a, b in ia], fingers, fingers, fingers, [a + b * c for a, b in ta]]
    )
    cum = np.cumsum(angles, axis=1)[:, :, None]  # (5, 3, 1)
    steps = _LENGTHS[:, :, None] * (np.cos(cum) * _U[:, None] + np.sin(cum) * _V[:, None])
    out[_METACARPAL_ROWS] = _METACARPALS
    out[_CHAIN_ROWS] = np.cumsum(np.concatenate([_ORIGINS[:, None], steps], axis=1), axis=1)
    out *= size
    if side == "left":
        out[:, 1] *= -1.0
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class HandModel:
    """A parametric hand.

    Attributes:
        side: ``"left"`` or ``"right"``.
        size: Scale factor on every length (1.0 = a medium adult hand).
    """

    side: str = "right"
    size: float = 1.0

    def local_joints(self, aperture: float, curl: float = DEFAULT_CURL) -> np.ndarray:
        """Joint positions in the wrist frame, shape (25, 3) [m].

        Args:
            aperture: 0 = pinch (thumb and index tips together), 1 = wide open.
            curl: Flexion of the middle, ring and pinky fingers [rad per joint].
        """
        s = min(max(float(aperture), 0.0), 1.0)  # np.clip's result, without its overhead
        return _local_joints(self.side, float(self.size), s, float(curl)).copy()

    def joints(
        self, wrist: np.ndarray, rotation: np.ndarray, aperture: float, curl: float = DEFAULT_CURL
    ) -> np.ndarray:
        """Joint positions in the workbench frame, shape (25, 3) [m].

        Args:
            wrist: Wrist position, shape (3,) [m].
            rotation: Wrist frame -> workbench rotation, shape (3, 3).
            aperture: 0 = pinch, 1 = open.
            curl: Flexion of the other three fingers [rad].
        """
        s = min(max(float(aperture), 0.0), 1.0)
        local = _local_joints(self.side, float(self.size), s, float(curl))
        return local @ np.asarray(rotation).T + np.asarray(wrist)


_IDENTITY = np.eye(3)
_IDENTITY.setflags(write=False)

MODEL_TABLES = {
    "origins": _ORIGINS,
    "lengths": _LENGTHS,
    "u": _U,
    "v": _V,
    "chain_rows": _CHAIN_ROWS,
    "metacarpals": _METACARPALS,
    "metacarpal_rows": _METACARPAL_ROWS,
    "index_angles": _INDEX_ANGLES,
    "thumb_angles": _THUMB_ANGLES,
    "curl_shares": _CURL_SHARES,
}
"""The model's tables, for its compiled form (:mod:`payload.teleop.handmodel_c`)."""


def _held_hand_numpy(
    left: bool,
    size: float,
    aperture: float,
    curl: float,
    wrist: np.ndarray,
    amp: float,
    arg: float,
    phases: np.ndarray,
    noise: np.ndarray,
) -> np.ndarray:
    """:func:`held_hand` in numpy."""
    model = HandModel("left" if left else "right", size)
    at = tremulous_wrist(wrist, amp, arg, phases)
    return model.joints(at, _IDENTITY, aperture, curl) + noise


@functools.cache
def held_hand_kernel() -> Any:
    """The process's compiled :func:`held_hand` (:mod:`payload.teleop.handmodel_c`,
    checked when built), or None: the numpy code draws the hands."""
    return compiled_held_hand(MODEL_TABLES, _held_hand_numpy)


def held_hand(
    model: HandModel,
    wrist: np.ndarray,
    amp: float,
    arg: float,
    phases: np.ndarray,
    aperture: float,
    noise: np.ndarray,
    curl: float = DEFAULT_CURL,
) -> np.ndarray:
    """A tracked hand of the synthetic operator, shape (25, 3) [m]: ``model``'s joints,
    unrotated, at the wrist ``wrist + amp sin(arg + phases)`` (its tremor), plus the
    tracker's ``noise`` (25, 3) (a float64 array of the caller's own, which the compiled
    form writes the joints over: :mod:`payload.teleop.handmodel_c`, the same bits)."""
    left, size = model.side == "left", float(model.size)
    kernel = held_hand_kernel()
    if kernel is not None:
        out = kernel(left, size, float(aperture), float(curl), wrist, amp, arg, phases, noise)
        if out is not None:
            return out
    return _held_hand_numpy(left, size, aperture, curl, wrist, amp, arg, phases, noise)
