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


def rotate_by_quats(quats: np.ndarray, vectors: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Vectors rotated by quaternions, one each: what SciPy's
    ``Rotation.from_quat(quats[:, [1, 2, 3, 0]]).apply(vectors)`` (``.inv().apply`` with
    ``inverse``) computes, bit for bit as of SciPy 1.17, without importing SciPy (about
    0.15 s in a trial's process).

    As SciPy does: each quaternion is divided by its norm (summed x, y, z, w), the inverse
    is the conjugate, the matrix is the usual one of the products ``x * x``, ``x * y``, ...
    and the vectors are multiplied with what SciPy's compiled ``apply`` calls: numpy's
    ``matmul`` for a single vector (one step's, say), ``einsum("ijk,ik->ij")`` for one
    vector each.

    Args:
        quats: Quaternions (w, x, y, z), shape (N, 4), any non-zero norm.
        vectors: Shape (N, 3), or (3,) for every quaternion.
        inverse: Rotate by the inverses.

    Returns:
        Shape (N, 3).

    Raises:
        ValueError: A quaternion of zero or non-finite norm, or shapes that disagree.
    """
    q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if not (np.isfinite(norm).all() and (norm > 0.0).all()):
        raise ValueError("rotate_by_quats: a quaternion of zero or non-finite norm")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    if inverse:
        x, y, z = -x, -y, -z
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    m = np.empty((len(q), 3, 3))
    m[:, 0, 0] = x2 - y2 - z2 + w2
    m[:, 1, 0] = 2 * (xy + zw)
    m[:, 2, 0] = 2 * (xz - yw)
    m[:, 0, 1] = 2 * (xy - zw)
    m[:, 1, 1] = -x2 + y2 - z2 + w2
    m[:, 2, 1] = 2 * (yz + xw)
    m[:, 0, 2] = 2 * (xz + yw)
    m[:, 1, 2] = 2 * (yz - xw)
    m[:, 2, 2] = -x2 - y2 + z2 + w2
    v = np.asarray(vectors, dtype=np.float64)
    if v.shape in ((3,), (1, 3)):  # one vector for every quaternion: SciPy's matmul
        return np.matmul(m, v.reshape(3))
    if v.shape != (len(q), 3):
        raise ValueError(f"rotate_by_quats: {len(q)} quaternions, vectors of shape {v.shape}")
    return np.einsum("ijk,ik->ij", m, v)


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` random rotation matrices, row-major (n, 9): unit quaternions from normal
    draws (the kernels' self-checks' poses)."""
    q = rng.normal(size=(n, 4))
    return np.array([quat_to_matrix(v / np.linalg.norm(v)).ravel() for v in q])


__all__ = [
    "matrix_to_quat",
    "quat_to_matrix",
    "random_rotations",
    "rotate_by_quats",
    "yaw_matrix",
    "yaw_of_matrix",
    "yaw_quat",
]
