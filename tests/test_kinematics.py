"""payload.kinematics: Pinocchio frame positions and Jacobians against independent models."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yourdfpy
from conftest import URDF

from payload.design import ALL_JOINTS, FINGERS, build_tree
from payload.kinematics import Kinematics, KinematicsError

FRAMES = [f"{f}_{k}" for f in FINGERS for k in ("tip", "distal")]

# A small arm with an unaligned revolute axis, a rotated joint origin and a prismatic
# joint, built by the test itself.
SMALL_URDF = """<?xml version="1.0"?>
<robot name="small">
  <link name="root"/>
  <link name="a"/>
  <link name="b"/>
  <link name="c"/>
  <link name="tip"/>
  <joint name="j1" type="revolute">
    <parent link="root"/><child link="a"/>
    <origin xyz="0.01 0.02 0.03" rpy="0.3 -0.2 0.5"/>
    <axis xyz="0 0.6 0.8"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="prismatic">
    <parent link="a"/><child link="b"/>
    <origin xyz="0 0 0.05" rpy="0 0.4 0"/>
    <axis xyz="0.6 0.8 0"/>
    <limit lower="0" upper="0.04" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="b"/><child link="c"/>
    <origin xyz="0.04 0 0" rpy="1.5707963 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="tip_fixed" type="fixed">
    <parent link="c"/><child link="tip"/>
    <origin xyz="0.03 0.01 -0.02" rpy="0 0 0"/>
  </joint>
</robot>
"""


@pytest.fixture(scope="module")
def kin() -> Kinematics:
    return Kinematics()


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple[Kinematics, Path]:
    path = tmp_path_factory.mktemp("small") / "small.urdf"
    path.write_text(SMALL_URDF)
    return Kinematics(path), path


def _yourdfpy_positions(path: Path, names, q: np.ndarray, frames) -> np.ndarray:
    robot = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
    robot.update_cfg(dict(zip(names, q)))
    return np.array([robot.get_transform(f, robot.base_link)[:3, 3] for f in frames])


def test_default_model_has_every_payload_joint_and_frame(kin):
    assert kin.urdf == URDF.resolve()  # the current project's (this checkout's) URDF
    assert set(kin.joint_names) == set(ALL_JOINTS)
    assert kin.nq == kin.nv == len(ALL_JOINTS)
    for name in FRAMES:
        kin.frame_id(name)


def test_positions_match_the_design_trees_forward_kinematics(kin, design):
    tree = build_tree(design)
    rng = np.random.default_rng(0)
    for q in kin.random_configurations(20, rng):
        values = {n: q[kin.q_indices([n])[0]] for n in ALL_JOINTS}
        expected = tree.frame_positions(values)
        got = kin.frame_positions(q, FRAMES)
        for name, p in zip(FRAMES, got):
            np.testing.assert_allclose(p, expected[name], atol=1e-12)


def test_positions_match_yourdfpy_on_the_payload(kin):
    q = kin.random_configurations(1, np.random.default_rng(1))[0]
    names = list(kin.joint_names)
    expected = _yourdfpy_positions(URDF, names, q[kin.q_indices(names)], FRAMES)
    np.testing.assert_allclose(kin.frame_positions(q, FRAMES), expected, atol=1e-10)


def test_positions_match_yourdfpy_on_a_small_arm_with_odd_axes(small):
    k, path = small
    names = list(k.joint_names)
    assert names == ["j1", "j2", "j3"]
    for q in k.random_configurations(5, np.random.default_rng(2)):
        expected = _yourdfpy_positions(path, names, q, ["tip", "c"])
        np.testing.assert_allclose(k.frame_positions(q, ["tip", "c"]), expected, atol=1e-10)


def _fd_jacobian(k: Kinematics, q: np.ndarray, frames, h: float = 1e-6) -> np.ndarray:
    jac = np.zeros((len(frames), 3, k.nv))
    for i in range(k.nq):
        dq = np.zeros(k.nq)
        dq[i] = h
        jac[:, :, i] = (k.frame_positions(q + dq, frames) - k.frame_positions(q - dq, frames)) / (
            2 * h
        )
    return jac


@pytest.mark.parametrize("which", ["payload", "small"])
def test_jacobians_match_central_finite_differences(kin, small, which):
    k = kin if which == "payload" else small[0]
    frames = FRAMES if which == "payload" else ["tip", "c"]
    for q in k.random_configurations(10, np.random.default_rng(3)):
        pos, jac = k.frame_jacobians(q, frames)
        np.testing.assert_allclose(pos, k.frame_positions(q, frames), atol=1e-15)
        fd = _fd_jacobian(k, q, frames)
        assert np.linalg.norm(jac - fd) / np.linalg.norm(fd) < 1e-8


def test_batches_equal_single_calls(kin):
    qs = kin.random_configurations(7, np.random.default_rng(4))
    pos = kin.frame_positions_batch(qs, FRAMES)
    pos_j, jac = kin.frame_jacobians_batch(qs, FRAMES)
    for i, q in enumerate(qs):
        p1, j1 = kin.frame_jacobians(q, FRAMES)
        np.testing.assert_array_equal(pos[i], p1)
        np.testing.assert_array_equal(pos_j[i], p1)
        np.testing.assert_array_equal(jac[i], j1)


def test_random_configurations_respect_the_limits(kin):
    qs = kin.random_configurations(500, np.random.default_rng(5))
    assert np.all(qs >= kin.lower) and np.all(qs <= kin.upper)
    assert np.all(qs.min(axis=0) < kin.lower + 0.05 * (kin.upper - kin.lower))


def test_configuration_by_name_and_chain_structure(kin):
    q = kin.configuration({"A_pip": 0.3, "rail": 0.02})
    assert q[kin.q_indices(["A_pip"])[0]] == 0.3
    assert q[kin.q_indices(["rail"])[0]] == 0.02
    chain = [kin.model.names[j] for j in kin.chain("stage", "A_tip")]
    assert chain == ["A_mcp_flex", "A_mcp_abd", "A_pip", "A_dip"]
    chain = [kin.model.names[j] for j in kin.chain("base", "D_distal")]
    assert chain == ["stage", "rail", "D_mcp_flex", "D_mcp_abd", "D_pip", "D_dip"]
    kind, axis = kin.joint_motion(kin.joint_id("stage"))
    assert kind == "prismatic"
    np.testing.assert_allclose(axis, [0, 0, -1])
    kind, axis = kin.joint_motion(kin.joint_id("A_mcp_abd"))
    assert kind == "revolute"
    np.testing.assert_allclose(axis, [0, 1, 0])


def test_a_shared_name_means_the_link(kin):
    # "stage" is both a joint and a link in our URDF.
    fid = kin.frame_id("stage")
    assert kin.model.frames[fid].type == kin.model.frames[fid].type.BODY


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda k: k.frame_id("Z_tip"), "no frame 'Z_tip'"),
        (lambda k: k.joint_id("elbow"), "no joint 'elbow'"),
        (lambda k: k.frame_positions(np.zeros(3), ["A_tip"]), "expected shape (18,)"),
        (lambda k: k.frame_positions(np.full(18, np.nan), ["A_tip"]), "non-finite"),
        (lambda k: k.frame_positions_batch(np.zeros((2, 5)), ["A_tip"]), "expected shape (m, 18)"),
        (lambda k: k.chain("A_tip", "C_tip"), "not an ancestor"),
    ],
)
def test_bad_input_raises_a_clear_error(kin, call, message):
    with pytest.raises(KinematicsError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call(kin)


def test_missing_or_broken_urdf_is_a_kinematics_error(tmp_path):
    with pytest.raises(KinematicsError, match="URDF not found"):
        Kinematics(tmp_path / "nope.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'>")
    with pytest.raises(KinematicsError, match="cannot load URDF"):
        Kinematics(bad)
