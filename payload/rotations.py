"""Rotation helpers shared by the modules: quaternions are (w, x, y, z), unit norm."""

from __future__ import annotations

import math

import numpy as np

_LAST: tuple[bytes, np.ndarray] = (b"", np.eye(3))
"""The last quaternion converted (its bytes) and its matrix: the control loop asks for the
rotation of the same state three or four times a step."""


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z), shape (3, 3) (a fresh array)."""
    global _LAST
    q = np.asarray(quat, dtype=float)
    key = q.tobytes() if q.shape == (4,) else b""
    last = _LAST
    if key and key == last[0]:  # the same bits: the same matrix
        return last[1].copy()
    w, x, y, z = q.tolist()  # floats: the same arithmetic, sooner
    out = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    if key:
        _LAST = (key, out.copy())
    return out


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix, shape (4,)."""
    m = np.asarray(r, dtype=float)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = np.array(
            [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        )
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.empty(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    if q[0] < 0:
        q = -q
    return q / np.linalg.norm(q)


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about z by ``yaw`` [rad], shape (3, 3)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_quat(yaw: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation about z by ``yaw`` [rad]."""
    return np.array([math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)])


def yaw_of_matrix(rot: np.ndarray) -> float:
    """Heading [rad]: the angle of the rotated x axis in the world xy plane."""
    return math.atan2(rot[1, 0], rot[0, 0])


__all__ = ["matrix_to_quat", "quat_to_matrix", "yaw_matrix", "yaw_of_matrix", "yaw_quat"]
