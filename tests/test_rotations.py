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


def test_a_repeated_quaternion_gives_a_fresh_matrix_of_the_same_bits():
    """The loop converts the same state's quaternion several times a step: each call
    returns its own array (changing one changes no other), with MuJoCo's matrix; a
    quaternion differing only in a zero's sign or its shape is converted afresh."""
    q = np.array([0.8, 0.0, 0.6, 0.0])
    first = quat_to_matrix(q)
    first[0, 0] = 99.0
    again = quat_to_matrix(q.copy())
    want = np.zeros(9)
    mujoco.mju_quat2Mat(want, q)
    np.testing.assert_allclose(again.ravel(), want, atol=1e-15)
    assert again is not first and again[0, 0] != 99.0
    signed = quat_to_matrix(np.array([0.8, -0.0, 0.6, 0.0]))
    assert signed.tobytes() != again.tobytes()  # x y - z w = -0.0 - 0.0: a signed zero
    np.testing.assert_array_equal(signed, again)
    try:
        quat_to_matrix(q.reshape(2, 2))  # the same bytes, another shape: not a quaternion
    except ValueError:
        pass
    else:
        raise AssertionError("a (2, 2) array was taken for a quaternion")
