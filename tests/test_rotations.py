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


def test_rotating_by_quaternions_gives_scipys_bits():
    """The metrics' and the route figure's rotations are SciPy's ``Rotation.from_quat``
    then ``apply`` (or ``inv().apply``), bit for bit, on quaternions of any norm and
    vectors of many scales; one vector is rotated by every quaternion; a zero quaternion
    is refused, as SciPy refuses it."""
    import pytest
    from scipy.spatial.transform import Rotation

    from payload.rotations import rotate_by_quats

    rng = np.random.default_rng(7)
    n = 20000
    q = rng.normal(size=(n, 4)) * rng.choice((1e-3, 1.0, 1e3), size=(n, 1))
    v = rng.normal(size=(n, 3)) * rng.choice((1e-4, 1.0, 30.0), size=(n, 1))
    scipy_rot = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    for inverse, want in ((False, scipy_rot.apply(v)), (True, scipy_rot.inv().apply(v))):
        assert rotate_by_quats(q, v, inverse=inverse).tobytes() == want.tobytes()
    # a single vector (for every quaternion, or one step's) goes through numpy's matmul
    one = np.array([1.0, 0.0, 0.0])
    assert rotate_by_quats(q[:50], one).tobytes() == scipy_rot[:50].apply(one).tobytes()
    for k in range(0, n, 7):
        single = Rotation.from_quat(q[k : k + 1, [1, 2, 3, 0]]).inv().apply(v[k : k + 1])
        assert rotate_by_quats(q[k : k + 1], v[k : k + 1], True).tobytes() == single.tobytes()
    with pytest.raises(ValueError, match="zero or non-finite"):
        rotate_by_quats(np.zeros((1, 4)), one)
    with pytest.raises(ValueError):
        Rotation.from_quat(np.zeros(4))
