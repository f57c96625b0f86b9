"""Rotation helpers against MuJoCo's own quaternion routines."""

from __future__ import annotations

import mujoco
import numpy as np

from payload.rotations import matrix_to_quat, quat_to_matrix, yaw_of_matrix


def test_quaternions_match_mujoco_and_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        expected = np.zeros(9)
        mujoco.mju_quat2Mat(expected, q)
        np.testing.assert_allclose(quat_to_matrix(q), expected.reshape(3, 3), atol=1e-12)
        back = matrix_to_quat(quat_to_matrix(q))
        np.testing.assert_allclose(back, q if q[0] >= 0 else -q, atol=1e-9)


def test_yaw_of_a_pure_yaw():
    for yaw in np.linspace(-3.0, 3.0, 13):
        q = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        assert abs(yaw_of_matrix(quat_to_matrix(q)) - yaw) < 1e-12
