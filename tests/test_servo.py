"""The one servo model (payload.design.servo) and its consumers: MuJoCo, the emulator, the
driver's bring-up and ``payload summary``.

Step responses are compared by rise time (10-90 %), overshoot and 2 % settling time; the
closed form is the textbook underdamped second-order step response of the derived
``kp``, ``kv + damping`` and the joint's inertia, taken from MuJoCo's own mass matrix.
"""

from __future__ import annotations

import copy
import math
import re
import struct
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from firmware_interface.control_table import ADDR
from firmware_interface.options import EMULATOR_LATENCY_MS
from firmware_interface.servo_dynamics import design_plants, plant_for
from firmware_interface.servo_model import ServoModel
from payload.cli import main
from payload.design import load_design
from payload.design.mjcf import MESH_DIR, to_mjcf
from payload.design.params import design_from_dict, design_to_dict
from payload.design.servo import TICKS_PER_RAD, dead_band_ticks, joint_servo, no_load_speed
from payload.design.summary import servo_summary
from payload.design.tree import build_tree, load_inertia

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
JOINT = "A_mcp_flex"
STEP_TICKS = 33  # the 0.05 rad goal step of the issue, in whole encoder ticks
DT = 0.001


@pytest.fixture(scope="module")
def design():
    return load_design(ROOT / "cad" / "design.toml")


def _model(design) -> mujoco.MjModel:
    xml, _ = to_mjcf(build_tree(design))
    xml = xml.replace(f'meshdir="{MESH_DIR}"', f'meshdir="{ROOT / "cad" / "meshes"}"')
    return mujoco.MjModel.from_xml_string(xml)


def _variant(design, **servo) -> object:
    data = copy.deepcopy(design_to_dict(design))
    data["servo"].update(servo)
    return design_from_dict(data)


def _mujoco_step(model: mujoco.MjModel, seconds: float) -> tuple[np.ndarray, float]:
    """MCP flexion of finger A after a goal step, every other joint held at home.

    Returns:
        (response [rad] sampled every DT from t = DT, joint inertia M_ii [kg m^2]).
    """
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("home").id)
    j = model.joint(JOINT).id
    qa, va = model.jnt_qposadr[j], model.jnt_dofadr[j]
    held_q, held_v = d.qpos.copy(), np.zeros(model.nv)
    a = model.actuator(JOINT).id
    q0 = d.qpos[qa]
    d.ctrl[a] = q0 + STEP_TICKS / TICKS_PER_RAD
    mujoco.mj_forward(model, d)
    unit = np.zeros(model.nv)
    unit[va] = 1.0
    column = np.zeros(model.nv)
    mujoco.mj_mulM(model, d, column, unit)  # M e_i: the i-th column of the mass matrix
    inertia = float(column[va])
    out = []
    for _ in range(round(seconds / DT)):
        mujoco.mj_step(model, d)
        keep_q, keep_v = d.qpos[qa], d.qvel[va]
        d.qpos[:], d.qvel[:] = held_q, held_v
        d.qpos[qa], d.qvel[va] = keep_q, keep_v
        out.append(d.qpos[qa] - q0)
    return np.array(out), inertia


def _write(servo: ServoModel, name: str, value: int, size: int) -> None:
    fmt = {1: "<B", 2: "<h", 4: "<i"}[size]
    assert servo.write(ADDR[name], struct.pack(fmt, value)) == 0, name


def _emulator_step(
    plant, gains, cap_ma: int, seconds: float, blocked: bool = False, step: int = STEP_TICKS
):
    """The emulated servo brought up as the driver does, then a goal step of ``step`` ticks.

    Returns:
        (response [rad] every DT from t = DT, present current [mA] at the end).
    """
    servo = ServoModel(1, 2048.0, now=0.0, plant=plant)
    _write(servo, "operating_mode", 5, 1)
    for name, g in zip(("position_p_gain", "position_i_gain", "position_d_gain"), gains):
        _write(servo, name, g, 2)
    _write(servo, "goal_current", cap_ma, 2)
    _write(servo, "torque_enable", 1, 1)
    servo.blocked = blocked
    _write(servo, "goal_position", 2048 + step, 4)
    out = []
    for k in range(1, round(seconds / DT) + 1):
        servo.advance(k * DT)
        out.append((servo.pos - 2048.0) / TICKS_PER_RAD)
    return np.array(out), servo.current


def _metrics(y: np.ndarray, final: float) -> dict[str, float]:
    t = np.arange(1, len(y) + 1) * DT
    rise = t[np.argmax(y >= 0.9 * final)] - t[np.argmax(y >= 0.1 * final)]
    outside = np.nonzero(np.abs(y - final) > 0.02 * abs(final))[0]
    settle = t[outside[-1]] if len(outside) else 0.0
    return {"rise": rise, "overshoot": (y.max() - final) / final, "settle": settle}


def _closed_form(kp: float, b: float, m: float, step: float, n: int) -> np.ndarray:
    wn, zeta = math.sqrt(kp / m), b / (2.0 * math.sqrt(kp * m))
    wd = wn * math.sqrt(1.0 - zeta**2)
    t = np.arange(1, n + 1) * DT
    env = np.exp(-zeta * wn * t)
    return step * (1.0 - env * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t)))


def test_free_finger_step_mujoco_emulator_and_closed_form_agree(design):
    """Without Coulomb friction (the closed form is linear): MuJoCo, the emulator and the
    textbook response of the derived parameters agree within 5 % in rise time, 3 points
    of overshoot and 10 % in 2 % settling time."""
    frictionless = _variant(design, coulomb=0.0)
    seconds = 3.0
    y_mj, inertia = _mujoco_step(_model(frictionless), seconds)
    tree = build_tree(frictionless)
    js = joint_servo(frictionless, "finger")
    # the emulator's load is the design's parallel-axis sum; MuJoCo's is its mass matrix
    assert js.armature + load_inertia(tree, "finger") == pytest.approx(inertia, rel=1e-3)
    plant = plant_for(frictionless, "finger", load_inertia(tree, "finger"))
    cap = round(frictionless.servo.current_limit * 1000)
    y_em, _ = _emulator_step(plant, js.gains, cap, seconds)
    step = STEP_TICKS / TICKS_PER_RAD
    y_cf = _closed_form(js.kp, js.kv + js.damping, inertia, step, len(y_mj))
    ref = _metrics(y_cf, step)
    assert 0.05 < ref["overshoot"] < 0.9  # an underdamped servo: the metrics mean something
    for name, y in (("mujoco", y_mj), ("emulator", y_em)):
        m = _metrics(y, step)
        assert m["rise"] == pytest.approx(ref["rise"], rel=0.05), name
        assert m["overshoot"] == pytest.approx(ref["overshoot"], abs=0.03), name
        assert m["settle"] == pytest.approx(ref["settle"], rel=0.10), name


def test_free_finger_step_with_friction_mujoco_and_emulator_agree(design):
    """With the design's Coulomb friction both rise alike, overshoot alike and come to
    rest inside the friction dead band ``coulomb / kp`` around the goal."""
    seconds = 2.0
    y_mj, inertia = _mujoco_step(_model(design), seconds)
    js = joint_servo(design, "finger")
    plant = plant_for(design, "finger", inertia - js.armature)
    y_em, _ = _emulator_step(plant, js.gains, round(design.servo.current_limit * 1000), seconds)
    step = STEP_TICKS / TICKS_PER_RAD
    m_mj, m_em = _metrics(y_mj, step), _metrics(y_em, step)
    assert m_em["rise"] == pytest.approx(m_mj["rise"], rel=0.10)
    assert m_em["overshoot"] == pytest.approx(m_mj["overshoot"], abs=0.05)
    band = design.servo.coulomb / js.kp
    for y in (y_mj, y_em):
        assert abs(y[-1] - step) <= band * 1.05
        assert np.ptp(y[-200:]) < 0.02 * step  # at rest


@pytest.mark.parametrize("kind", ["finger", "abduction", "stage"])
def test_the_dead_band_is_the_largest_step_an_emulated_servo_at_rest_ignores(design, kind):
    """``dead_band_ticks`` (move_to_home's tolerance) against the emulator's integration:
    a goal step of the band's whole ticks leaves the shaft at rest, one tick more moves
    it; and it equals MuJoCo's frictionloss / kp in ticks."""
    band = dead_band_ticks(design, kind)
    js = joint_servo(design, kind)
    assert band == pytest.approx(js.frictionloss / js.kp / js.scale * TICKS_PER_RAD, rel=1e-12)
    moved = []
    for step in (math.floor(band), math.floor(band) + 1):
        s = ServoModel(1, 2048.0, plant=plant_for(design, kind, 0.0))
        s._set("operating_mode", 5)
        for name, value in zip(("position_p_gain", "position_i_gain", "position_d_gain"),
                               js.gains):  # fmt: skip
            s._set(name, value)
        s._set("goal_current", round(design.servo.current_limit * 1000))
        s._set("torque_enable", 1)
        s._set("goal_position", 2048 + step)
        for k in range(1, 301):
            s.advance(k * 1e-3)
        moved.append(s.physical != 2048.0)
    assert moved == [False, True]


def test_blocked_finger_torque_is_goal_current_times_kt(design):
    """A finger held still far from its goal pushes with Goal Current x kt in MuJoCo
    (actuator force at its clamp) and in the emulator (present current at the cap); the
    datasheet's stall point read proportionally gives the same torque."""
    model = _model(design)
    j = model.joint(JOINT).id
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("home").id)
    home = d.qpos[model.jnt_qposadr[j]]
    model.jnt_range[j] = (home - 1e-4, home + 1e-4)  # a hard block
    d.ctrl[model.actuator(JOINT).id] = home + 0.5
    for _ in range(200):
        mujoco.mj_step(model, d)
    torque_mj = d.actuator_force[model.actuator(JOINT).id]
    js = joint_servo(design, "finger")
    cap = round(design.servo.current_limit * 1000)
    plant = plant_for(design, "finger", 0.0)
    _, current = _emulator_step(plant, js.gains, cap, 0.2, blocked=True, step=326)  # 0.5 rad
    s = design.servo
    torque_em = current * 1e-3 * s.kt
    assert current == pytest.approx(cap)
    assert torque_mj == pytest.approx(torque_em, rel=1e-9)
    assert torque_em == pytest.approx(s.stall_torque * s.current_limit / s.stall_current, rel=1e-3)


def test_no_load_speed_of_the_model_matches_the_datasheet(design):
    """The supply, kt, R and the friction give the datasheet's 81 rpm within 5 %."""
    assert no_load_speed(design) == pytest.approx(design.servo.no_load_speed, rel=0.05)


def test_emulated_servo_runs_at_the_no_load_speed_when_the_voltage_saturates(design):
    plant = plant_for(design, "finger", 0.0)
    servo = ServoModel(1, 0.0, now=0.0, plant=plant)
    _write(servo, "operating_mode", 5, 1)
    _write(servo, "position_p_gain", 16000, 2)
    _write(servo, "goal_current", 1750, 2)
    _write(servo, "torque_enable", 1, 1)
    _write(servo, "goal_position", 40000, 4)
    servo.advance(1.0)
    omega = servo.vel / TICKS_PER_RAD
    s = design.servo
    # saturated: R i + kt w = V with kt i = b w + c at steady speed
    assert omega == pytest.approx(no_load_speed(design), rel=1e-3)
    assert omega * 60 / (2 * math.pi) == pytest.approx(81.0, rel=0.05)
    assert servo.current * 1e-3 == pytest.approx((s.viscous * omega + s.coulomb) / s.kt, rel=1e-3)


def test_summary_servo_block(design):
    """summary --json's servo block: per joint kind, the derived parameters and a natural
    frequency and damping ratio that MuJoCo's free response confirms (finger flexion)."""
    tree = build_tree(design)
    out = servo_summary(tree)
    keys = {"kp", "kv", "damping", "armature", "frictionloss", "torque_cap", "natural_hz",
            "damping_ratio"}  # fmt: skip
    assert set(out) == {"finger", "abduction", "rail", "stage"}
    assert all(set(v) == keys for v in out.values())
    # the rail's pinion: force = torque / r, stiffness and inertia through r^2
    r = design.rail.drive_radius
    assert out["rail"]["kp"] == pytest.approx(out["finger"]["kp"] / r**2)
    assert out["rail"]["torque_cap"] == pytest.approx(out["finger"]["torque_cap"] / r)
    # finger flexion: the ringing MuJoCo shows (zero crossings of the frictionless response)
    y, _ = _mujoco_step(_model(_variant(design, coulomb=0.0)), 1.5)
    step = STEP_TICKS / TICKS_PER_RAD
    crossings = np.nonzero(np.diff(np.sign(y - step)))[0]
    period = 2 * np.mean(np.diff(crossings)) * DT
    zeta = out["finger"]["damping_ratio"]
    hz = out["finger"]["natural_hz"] * math.sqrt(1 - zeta**2)
    assert 1.0 / period == pytest.approx(hz, rel=0.03)


def test_payload_summary_json_has_the_servo_block(capsys):
    import json

    assert main(["summary", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["servo"]) == {"finger", "abduction", "rail", "stage"}
    assert out["servo"]["finger"]["damping_ratio"] > 0


def test_a_gain_changed_in_a_scratch_project_changes_model_emulator_and_bring_up(
    tmp_path, monkeypatch
):
    """`payload new`, finger P 600 -> 1350: the built MJCF's finger kp scales by 2.25, the
    emulated finger's ringing frequency by 1.5 (sqrt of the stiffness) and the driver
    writes 1350 at bring-up."""
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.emulator import EmulatorProcess

    root = tmp_path / "variant"
    assert main(["new", str(root)]) == 0
    path = root / "cad" / "design.toml"
    text = path.read_text()
    text, n = re.subn(r"(?m)^finger = \[600, 0, 200\]", "finger = [1350, 0, 200]", text)
    assert n == 1
    path.write_text(text)
    assert tomllib.loads(text)["servo"]["gains"]["finger"] == [1350, 0, 200]
    assert main(["build", "--project", str(root)]) == 0
    before = mujoco.MjModel.from_xml_path(str(ROOT / "urdf" / "payload.xml"))
    after = mujoco.MjModel.from_xml_path(str(root / "urdf" / "payload.xml"))
    a = before.actuator(JOINT).id
    assert after.actuator_gainprm[a, 0] == pytest.approx(2.25 * before.actuator_gainprm[a, 0])
    abd = before.actuator("A_mcp_abd").id  # the abduction servo keeps its gains
    assert after.actuator_gainprm[abd, 0] == pytest.approx(before.actuator_gainprm[abd, 0])

    def ringing_hz(design) -> float:
        plant = design_plants(design, {1: "finger"})[1]
        js = joint_servo(design, "finger")
        y, _ = _emulator_step(plant, js.gains, round(design.servo.current_limit * 1e3), 1.5)
        crossings = np.nonzero(np.diff(np.sign(y - STEP_TICKS / TICKS_PER_RAD)))[0]
        return 1.0 / (2 * np.mean(np.diff(crossings[:4])) * DT)

    # without Coulomb friction, so that the servo rings long enough to time it
    ours = _variant(load_design(ROOT / "cad" / "design.toml"), coulomb=0.0)
    theirs = _variant(load_design(path), coulomb=0.0)
    assert ringing_hz(theirs) / ringing_hz(ours) == pytest.approx(1.5, rel=0.05)
    monkeypatch.setenv("PAYLOAD_PROJECT", str(root))
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, latency_timer_ms=EMULATOR_LATENCY_MS) as drv,
    ):
        drv.bring_up()
        table = emu.table(drv.map.servos[0].id)
    p = ADDR["position_p_gain"]
    assert int.from_bytes(table[p : p + 2], "little") == 1350
