"""A real acquisition: seeded CTB offset, an operator that lines up and closes, honest
failure, and a CTB moved only by contacts."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from payload.rotations import quat_to_matrix, yaw_matrix
from payload.sim import SimDriver, WorldConfig, build_world
from payload.sim.world import CTB_SIZES, Handle
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.operator import OperatorPlan, SyntheticOperator, WorldView
from payload.trials.acquisition import OFFSET_RANGE_M, YAW_RANGE_DEG, sample_offset
from payload.trials.recorder import read_recording
from payload.trials.runner import run_trial

GRASP = np.array([-0.01, 0.0, -0.34])


def _operator(seed: int = 3) -> SyntheticOperator:
    plan = OperatorPlan(route=np.array([[0.0, 0, 0], [1.0, 0, 0]]), grasp_body=GRASP)
    op = SyntheticOperator(plan, seed, CalibrationProcedure())
    op.phase = "acquisition"  # past calibration
    return op


def _view(t: float, handle_body: np.ndarray, contact: bool = False) -> WorldView:
    z = np.zeros(3)
    return WorldView(t, z, np.eye(3), z, z, contact, handle_body)


def test_offsets_are_seeded_and_within_range():
    a, b = sample_offset(4), sample_offset(4)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]
    offsets = np.array([sample_offset(s)[0] for s in range(50)])
    yaws = np.array([sample_offset(s)[1] for s in range(50)])
    assert np.all(np.abs(offsets) <= np.asarray(OFFSET_RANGE_M))
    assert np.all(np.abs(yaws) <= YAW_RANGE_DEG)
    assert np.unique(offsets[:, 0]).size == 50  # every seed its own


def test_the_operator_creeps_toward_a_misaligned_handle_and_brakes_when_lined_up():
    op = _operator()
    centre = 0.5 * (op.plan.neutral_left + op.plan.neutral_right)
    ahead = GRASP + np.array([0.03, 0.0, 0.0])  # the handle is 3 cm ahead of the pinch
    t = 0.0
    for _ in range(100):  # 2 s: reaction delay and arm lag
        op.act(_view(t, ahead))
        t += 0.02
    mid = 0.5 * (op.wrist["left"] + op.wrist["right"]) - centre
    assert mid[0] > op.plan.base.sphere_radius  # both wrists pushed forward: creep ahead
    assert abs(mid[1]) < 0.01 and abs(mid[2]) < 0.01
    assert op.acquisition == "approach"
    for _ in range(300):  # lined up (the vehicle arrived): wrists back to neutral
        op.act(_view(t, GRASP.copy()))
        t += 0.02
    mid = 0.5 * (op.wrist["left"] + op.wrist["right"]) - centre
    assert np.linalg.norm(mid) < op.plan.base.sphere_radius
    assert op.acquisition == "close" and op.aperture < 0.45  # settled, now closing


def test_an_acquisition_that_never_touches_fails_honestly():
    op = _operator()
    t = 0.0
    while not op.finished and t < 120.0:
        op.act(_view(t, GRASP.copy(), contact=False))
        t += 0.02
    assert op.finished and op.acquisition == "gave_up"
    assert op.attempt == op.traits.attempts
    assert op.phase == "acquisition" and op.contact_seen_at is None


def test_the_operator_sees_contact_late():
    op = _operator()
    t, seen_at = 0.0, None
    while t < 60.0 and op.acquisition != "close":
        op.act(_view(t, GRASP.copy()))
        t += 0.02
    touch = t + 0.5
    while t < touch + 2.0:
        op.act(_view(t, GRASP.copy(), contact=t >= touch))
        if op.contact_seen_at is not None and seen_at is None:
            seen_at = op.contact_seen_at
        t += 0.02
    assert seen_at is not None
    assert seen_at - touch == pytest.approx(op.traits.reaction, abs=0.021)


def test_ctb_watch_catches_an_applied_force():
    w = build_world(WorldConfig(ctb="single"))
    sim = SimDriver(w)
    sim.step(2)
    assert sim.ctb_external_max == 0.0
    sim.data.xfrc_applied[w.ctb, 0] = 0.01
    sim.step(1)
    assert sim.ctb_external_max == pytest.approx(0.01)


def rec_meta_matches(out, offset: np.ndarray, yaw: float) -> bool:
    meta = read_recording(out / "log.mcap").meta
    return meta["ctb_offset_m"] == offset.tolist() and meta["ctb_yaw_deg"] == yaw


@pytest.mark.parametrize("ctb", ["single", "rigid"])
def test_a_trial_records_its_offset_from_its_first_step(tmp_path, ctb):
    out = tmp_path / ctb
    result = run_trial(7, out_dir=out, max_time=2.0, ctb=ctb)
    metrics = json.loads((out / "metrics.json").read_text())
    offset, yaw = np.asarray(metrics["ctb_offset_m"]), metrics["ctb_yaw_deg"]
    draws = [sample_offset(7, k) for k in range(100)]  # one of the seed's draws
    assert any(np.array_equal(offset, o) and yaw == y for o, y in draws)
    assert rec_meta_matches(out, offset, yaw)
    assert metrics["ctb"] == ctb and metrics["propulsion"] == "nozzles"
    assert result["ctb_external_max"] == 0.0 and result["equality_constraints"] == 0
    rec = read_recording(out / "log.mcap")
    # first recorded step: the CTB sits at the grasp point moved by the offset and yawed
    rot = quat_to_matrix(rec.astrobee_quat[0])
    body = rot.T @ (rec.ctb_pos[0] - rec.astrobee_pos[0])
    size, handle = CTB_SIZES[ctb], Handle()
    drop = handle.height / 2 + handle.standoff + size.height / 2
    nominal = np.asarray(rec.meta["grasp_body_m"]) - np.array([0.0, 0.0, drop])
    np.testing.assert_allclose(body, nominal + offset, atol=2e-4)  # 20 ms of free drift
    rel = rot.T @ quat_to_matrix(rec.ctb_quat[0])
    np.testing.assert_allclose(rel, yaw_matrix(math.radians(yaw)), atol=1e-3)


def test_the_handle_in_the_body_frame_is_mujocos():
    """After Astrobee has turned and moved, the handle's centre in the body frame, with
    and without the site and rotation given (the rotation of the world state's
    quaternion): the site's position (as the last step's kinematics left it) less the
    body's (the state's), taken into the body frame with MuJoCo's own matrix of the
    state's quaternion (``mju_quat2Mat``)."""
    import mujoco

    from payload.schema import VehicleTwist
    from payload.trials.acquisition import handle_in_body, handle_site

    driver = SimDriver()
    driver.command_twist(VehicleTwist(np.array([0.05, 0.02, 0.0]), np.array([0.0, 0.0, 0.2]), 0))
    for _ in range(40):
        state = driver.step()
    site = handle_site(driver)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, state.astrobee_quat)
    want = mat.reshape(3, 3).T @ (driver.data.site_xpos[site] - state.astrobee_pos)
    got = handle_in_body(driver)
    given = handle_in_body(driver, site, quat_to_matrix(state.astrobee_quat))
    assert given.tobytes() == got.tobytes()
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert float(np.linalg.norm(got)) > 0.1  # the handle is away from the centre
