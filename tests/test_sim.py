"""The zero-gravity ISS simulator: world, servo limits, momentum, vehicle controller, grasp."""

from __future__ import annotations

import functools
import io
import itertools
import json
import math
import operator
import time
import types
import warnings
from contextlib import redirect_stderr, redirect_stdout

import mujoco
import numpy as np
import pytest

from payload.design import FINGERS, MANIPULATION_JOINTS, design_from_dict
from payload.schema import (
    HEALTHS,
    Health,
    PayloadCommand,
    PayloadDriver,
    PayloadState,
    SchemaError,
    VehicleTwist,
)
from payload.sim import (
    PAYLOAD_PREFIX,
    CtbSize,
    IssLayout,
    IssModule,
    JerkLimitedProfile,
    MassProperties,
    SimDriver,
    SimError,
    VehicleController,
    VehicleError,
    WorldConfig,
    build_world,
    min_time_to_speed,
    opposing,
)
from payload.sim.bench import RouteFollower
from payload.sim.contact import SIDES

# Figures from docs/sources.md, typed here independently of the code under test.
XC330_STALL = 0.93  # [N m] at 5 V
XC330_STALL_CURRENT = 1.80  # [A]
CURRENT_CAP = 0.35  # [A]
NO_LOAD_SPEED = 81 * 2 * math.pi / 60  # [rad/s]
NOMINAL_FORCE = np.array([0.680, 0.332, 0.394])  # [N]
NOMINAL_TORQUE = NOMINAL_FORCE / 10  # [N m], "roughly a tenth"
NOMINAL_ACCEL = 0.0175  # [m/s^2]
NOMINAL_SPEED = 0.20  # [m/s]


@pytest.fixture(scope="module")
def world():
    return build_world()


@pytest.fixture(scope="module")
def bare_world():
    """Astrobee and the payload, no CTB."""
    return build_world(WorldConfig(ctb=None))


def _quat_to_rot(quat) -> np.ndarray:
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.asarray(quat, float))
    return rot.reshape(3, 3)


def _fingers_touching_by_name(sim: SimDriver) -> set[str]:
    """Fingertip pads touching the CTB, from geom names (independent of ContactMonitor)."""
    out = set()
    for i in range(sim.data.ncon):
        c = sim.data.contact[i]
        if c.dist > 0:
            continue
        names = [mujoco.mj_id2name(sim.model, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in c.geom]
        for a, b in (names, names[::-1]):
            if a.startswith("ctb") and b.startswith(PAYLOAD_PREFIX) and b.endswith("_distal_pad"):
                out.add(b[len(PAYLOAD_PREFIX)])
    return out


# -- world ----------------------------------------------------------------------------------------
def test_scene_compiles_and_steps_without_warnings(world):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # MuJoCo's compile-time warnings arrive as UserWarning
        fresh = build_world()
    model = fresh.model
    assert model.opt.timestep == pytest.approx(0.001)
    assert np.all(model.opt.gravity == 0.0)
    assert fresh.model.nu == 18
    # Menagerie-style smoke test: random controls inside the control ranges
    data = fresh.make_data("home")
    rng = np.random.default_rng(0)
    lo, hi = model.actuator_ctrlrange.T
    for _ in range(100):
        data.ctrl[:] = rng.uniform(lo, hi)
        mujoco.mj_step(model, data, nstep=20)
    assert all(data.warning[i].number == 0 for i in range(len(data.warning)))
    assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
    # deployed, nothing touches anything at the start
    assert fresh.make_data("home").ncon == 0
    # stowed, the payload touches nothing of the world (its own stowed keyframe has the
    # curled pads in the finger brackets: a payload-design matter, not the world's)
    stowed = fresh.make_data("stowed")
    payload = {b for b in range(model.nbody) if model.body_rootid[b] == fresh.astrobee}
    payload.discard(fresh.astrobee)
    for i in range(stowed.ncon):
        bodies = {int(model.geom_bodyid[g]) for g in stowed.contact[i].geom}
        assert bodies <= payload


def test_names_and_paper_order(world):
    for i, name in enumerate(MANIPULATION_JOINTS):
        assert world.name(mujoco.mjtObj.mjOBJ_ACTUATOR, world.ctrl[i]) == PAYLOAD_PREFIX + name
        jnt = int(np.flatnonzero(world.model.jnt_qposadr == world.qpos[i])[0])
        assert world.name(mujoco.mjtObj.mjOBJ_JOINT, jnt) == PAYLOAD_PREFIX + name
    for f in FINGERS:
        assert mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_SITE, f"payload/{f}_tip") >= 0


def test_astrobee_and_ctb_bodies(world):
    m = world.model
    assert m.body_mass[world.astrobee] == pytest.approx(9.5838)
    assert m.body_inertia[world.astrobee] == pytest.approx([0.15343, 0.14271, 0.16230])
    box = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "astrobee_collision")
    assert 2 * m.geom_size[box] == pytest.approx([0.32, 0.32, 0.32])
    # single CTB: 50.2 x 42.5 x 24.8 cm, 15.4 kg, solid-box inertia
    bag = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ctb_bag")
    assert 2 * m.geom_size[bag] == pytest.approx([0.502, 0.425, 0.248])
    assert m.body_mass[world.ctb] == pytest.approx(15.4)
    a, b, c = 0.502, 0.425, 0.248
    expected = 15.4 / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    assert m.body_inertia[world.ctb] == pytest.approx(expected)
    # friction from the design file on every CTB geom
    for g in world.ctb_geoms:
        assert m.geom_friction[g, 0] == pytest.approx(world.design.finger.pad.friction)
    heavy = build_world(WorldConfig(ctb="double", ctb_mass=20.0))
    assert heavy.model.body_mass[heavy.ctb] == pytest.approx(20.0)


def test_vehicle_geometry_comes_from_the_design(world):
    """The payload mount and Astrobee's box follow the design's [vehicle] table."""
    import dataclasses

    m = world.model
    base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, PAYLOAD_PREFIX + "base")
    box = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "astrobee_collision")
    assert m.body_parentid[base] == world.astrobee
    # cad/design.toml: a 0.32 m cube, bays centred and 0.10 m deep -> (0, 0, -0.16 + 0.10)
    assert world.vehicle.body_size == pytest.approx(tuple(world.design.vehicle["body_size"]))
    assert m.body_pos[base] == pytest.approx([0.0, 0.0, -0.06], abs=1e-12)
    assert world.mount == pytest.approx([0.0, 0.0, -0.06], abs=1e-12)
    # deeper bays (0.14 m) in a smaller, off-centre body
    vehicle = {"body_size": [0.34, 0.30, 0.30], "body_offset": [0.03, -0.02]}
    vehicle["bay_size"] = [0.20, 0.10, 0.14]
    other = build_world(design=dataclasses.replace(world.design, vehicle=vehicle))
    m2 = other.model
    base2 = mujoco.mj_name2id(m2, mujoco.mjtObj.mjOBJ_BODY, PAYLOAD_PREFIX + "base")
    # payload origin = top centre of the bays = (-0.03, 0.02, -0.30 / 2 + 0.14)
    expected = np.array([-0.03, 0.02, -0.01])
    assert m2.body_pos[base2] == pytest.approx(expected, abs=1e-12)
    assert m2.body_quat[base2] == pytest.approx(m.body_quat[base])
    assert other.mount == pytest.approx(expected, abs=1e-12)
    assert 2 * m2.geom_size[box] == pytest.approx([0.34, 0.30, 0.30])
    # the live page draws the same box (scene_of sends it to the page)
    from payload.trials.live import scene_of

    sent = scene_of(types.SimpleNamespace(world=other))
    assert sent["vehicle_body_size"] == pytest.approx(2 * m2.geom_size[box])
    assert m2.geom_pos[box] == pytest.approx([0.0, 0.0, 0.0])
    # the CTB starts under the moved payload: its offset moves with the mount
    d, d2 = world.make_data(), other.make_data()

    def ctb_in_body(w, data):
        rot = data.xmat[w.astrobee].reshape(3, 3)
        return rot.T @ (data.xpos[w.ctb] - data.xpos[w.astrobee])

    moved = ctb_in_body(other, d2) - ctb_in_body(world, d)
    assert moved == pytest.approx(expected - [0.0, 0.0, -0.06], abs=1e-9)


def test_bad_config_is_one_clear_error():
    with pytest.raises(SimError, match="unknown CTB size 'huge'"):
        WorldConfig(ctb="huge")
    with pytest.raises(SimError, match="ctb_mass"):
        WorldConfig(ctb_mass=-1.0)
    with pytest.raises(SimError, match=r"IssLayout\.kibo_width"):
        IssLayout(kibo_width=0.0)
    with pytest.raises(SimError, match="hatch"):
        IssLayout(hatch=3.0)


def test_iss_volumes_and_route():
    layout = IssLayout()
    kibo, vest, _ = layout.zones()
    assert kibo.size == pytest.approx([1.7, 7.3, 2.0])  # docs/sources.md
    assert vest.size[[0, 2]] == pytest.approx([1.3, 1.3])  # the common hatch
    assert layout.route_length() == pytest.approx(9.0, abs=0.5)
    start, turn, end = layout.route()
    assert layout.module_at(start) is IssModule.KIBO
    assert layout.module_at(turn) is IssModule.NODE2
    assert layout.module_at(end) is IssModule.NODE2
    assert layout.module_at(vest.centre) is IssModule.VESTIBULE
    assert layout.module_at((0.0, 0.0, 5.0)) is None
    assert layout.module_at((layout.hatch_x, kibo.hi[1] + 0.1, 0.0)) is None
    # the route leaves Kibo forward (Astrobee's x along the first leg) and turns in Node 2
    first, second = np.diff(layout.route(), axis=0)
    assert abs(np.dot(first, second)) < 1e-9
    heading = np.array([math.cos(layout.start_yaw()), math.sin(layout.start_yaw()), 0.0])
    assert heading @ first == pytest.approx(np.linalg.norm(first))


def test_route_clears_the_collision_geometry(world):
    """Every point of the route has room for the vehicle + payload + CTB stack."""
    m = world.model
    data = world.make_data()
    # the stack's extent around the Astrobee centre, from the compiled model
    lo = np.array([-0.16, -0.16, 0.0])
    hi = np.array([0.16, 0.16, 0.16])
    ctb_lo = data.xpos[world.ctb] - data.xpos[world.astrobee] - m.geom_size[world.ctb_geoms[0]]
    lo = np.minimum(lo, ctb_lo)
    half = np.max(np.abs(np.vstack([lo, hi])[:, :2]))  # the vehicle yaws: use a square
    lo[:2], hi[:2] = -half, half
    walls = [
        (data.geom_xpos[g] - m.geom_size[g], data.geom_xpos[g] + m.geom_size[g])
        for g in world.iss_geoms
    ]
    route = world.layout.route()
    for a, b in itertools.pairwise(route):
        for t in np.linspace(0.0, 1.0, 60):
            p = a + t * (b - a)
            for w_lo, w_hi in walls:
                overlap = np.all(p + hi > w_lo) and np.all(p + lo < w_hi)
                assert not overlap, f"route point {p} hits an ISS geom"


def test_walls_stop_the_vehicle(bare_world):
    sim = SimDriver(bare_world)
    kibo = bare_world.layout.kibo
    a = bare_world.astrobee_dof
    sim.data.qvel[a : a + 3] = [0.3, 0.0, 0.0]  # toward Kibo's +x rack face, 0.85 m away
    mujoco.mj_forward(sim.model, sim.data)
    hit = False
    for _ in range(250):
        sim.step()
        for i in range(sim.data.ncon):
            hit |= any(int(g) in bare_world.iss_geoms for g in sim.data.contact[i].geom)
    assert hit
    assert sim.data.qvel[a] < 0.1  # stopped or bounced
    assert sim.data.qpos[bare_world.astrobee_qpos] < kibo.hi[0]


# -- servos ---------------------------------------------------------------------------------------
def test_servo_force_limits_are_the_current_capped_xc330(world):
    torque = XC330_STALL * CURRENT_CAP / XC330_STALL_CURRENT  # torque ~ current
    d = world.design
    # the design's kt is the datasheet's stall ratio rounded to 0.517 N m/A
    assert d.servo.kt * CURRENT_CAP == pytest.approx(torque, rel=1e-3)
    torque = d.servo.kt * CURRENT_CAP
    expected = [torque] * 16 + [torque / d.rail.drive_radius, torque / d.stage.drive_radius]
    got = world.model.actuator_forcerange[world.ctrl_all]
    assert np.all(world.model.actuator_forcelimited[world.ctrl_all])
    assert got[:, 1] == pytest.approx(expected, rel=1e-6)
    assert got[:, 0] == pytest.approx(-np.array(expected), rel=1e-6)
    assert torque == pytest.approx(0.181, abs=5e-4)


def test_astrobee_mass_properties_come_from_the_design_vehicle_table(world, design_dict):
    """The world's Astrobee body takes the design's ``[vehicle]`` mass and inertia: the
    committed figures (docs/sources.md, typed here), and a changed table changes it."""
    assert world.model.body_mass[world.astrobee] == 9.5838
    assert world.model.body_inertia[world.astrobee].tolist() == [0.15343, 0.14271, 0.16230]
    vehicle = {**design_dict.get("vehicle", {}), "mass": 12.5, "inertia": [0.2, 0.3, 0.4]}
    other = build_world(design=design_from_dict({**design_dict, "vehicle": vehicle}))
    assert other.model.body_mass[other.astrobee] == 12.5
    assert other.model.body_inertia[other.astrobee].tolist() == [0.2, 0.3, 0.4]
    with pytest.raises(Exception, match=r"vehicle\.mass"):
        design_from_dict({**design_dict, "vehicle": {**vehicle, "mass": -1.0}})


def test_stale_payload_model_is_refused(design_dict):
    changed = {**design_dict, "servo": {**design_dict["servo"], "current_limit": 0.5}}
    with pytest.raises(SimError, match="payload build"):
        build_world(design=design_from_dict(changed))


def test_grip_force_bounded_by_current_capped_servo(world):
    sim = SimDriver(world)
    pinch = world.pinch
    # finger A slams closed as far as it goes (onto the handle), the others stay open
    q = pinch.command_q(False)
    sim.send(PayloadCommand(q, pinch.stage, 0.0))
    sim.step(40)
    q[0] = world.design.finger.limits.mcp_flex.upper
    sim.send(PayloadCommand(q, pinch.stage, 0.0))
    cap = world.design.servo.kt * CURRENT_CAP  # kt: the datasheet's stall ratio, rounded
    assert cap == pytest.approx(XC330_STALL * CURRENT_CAP / XC330_STALL_CURRENT, rel=1e-3)
    peak = 0.0
    for _ in range(50):
        sim.step()
        peak = max(peak, abs(sim.data.actuator_force[world.ctrl[0]]))
        assert peak <= cap * (1 + 1e-9)
    assert "A" in sim.world_state().touching
    assert peak == pytest.approx(cap, rel=1e-6)  # it did push as hard as it can
    state = sim.read()
    assert state.health & Health.OVERLOAD
    assert state.effort[0] == pytest.approx(cap, rel=1e-6)


def test_servo_speed_bounded_by_no_load_speed(world):
    sim = SimDriver(world)
    # finger A swings its abduction through 1 rad in free space
    q = sim.read().q.copy()
    q[1] = -1.0
    sim.send(PayloadCommand(q, world.design.home.stage, 0.0))
    peak, arrived = 0.0, None
    for _ in range(50):
        sim.step()
        peak = max(peak, abs(sim.read().dq[1]))
        if arrived is None and abs(sim.read().q[1] + 1.0) < 0.01:
            arrived = sim.time
    assert sim.data.ncon == 0
    assert arrived is not None
    # the target is slewed at the no-load speed; MuJoCo's position actuator has no voltage
    # limit (docs/servo.md), so the underdamped servo (damping ratio ~0.1) rings past that
    # speed by up to its overshoot on the slewing target: 12 % here
    assert peak <= 1.15 * NO_LOAD_SPEED
    assert 0.99 / NO_LOAD_SPEED <= arrived <= 0.5
    # the rail: on average no faster than its pinion at the servo's no-load speed
    sim.reset()
    q = sim.read().q.copy()
    start = q[16]
    q[16] = 0.0
    sim.send(PayloadCommand(q, world.design.home.stage, 0.0))
    travel_time = None
    for _ in range(100):
        sim.step()
        if travel_time is None and sim.read().q[16] <= 1e-3:
            travel_time = sim.time
    fastest = (start - 1e-3) / (NO_LOAD_SPEED * world.design.rail.drive_radius)
    assert travel_time is not None
    assert fastest <= travel_time <= fastest + 0.3


# -- momentum -------------------------------------------------------------------------------------
def _momentum(model, data) -> tuple[np.ndarray, np.ndarray]:
    """Linear and angular (about the world origin) momentum, summed body by body."""
    p, ang = np.zeros(3), np.zeros(3)
    jp, jr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for b in range(1, model.nbody):
        mujoco.mj_jacBodyCom(model, data, jp, jr, b)
        v, w = jp @ data.qvel, jr @ data.qvel
        rot = data.ximat[b].reshape(3, 3)
        inertia = rot @ np.diag(model.body_inertia[b]) @ rot.T
        p += model.body_mass[b] * v
        ang += model.body_mass[b] * np.cross(data.xipos[b], v) + inertia @ w
    return p, ang


def test_momentum_conserved_in_free_drift(world):
    sim = SimDriver(world)  # vehicle controller off, payload servos holding home
    m, d = sim.model, sim.data
    v = np.array([0.03, -0.02, 0.01])
    w = np.array([0.01, -0.02, 0.03])
    a, c = world.astrobee_dof, world.ctb_dof
    d.qvel[a : a + 3] = v
    d.qvel[a + 3 : a + 6] = d.xmat[world.astrobee].reshape(3, 3).T @ w
    r = d.xpos[world.ctb] - d.xpos[world.astrobee]  # the CTB drifts along, rigidly
    d.qvel[c : c + 3] = v + np.cross(w, r)
    d.qvel[c + 3 : c + 6] = d.xmat[world.ctb].reshape(3, 3).T @ w
    mujoco.mj_forward(m, d)
    p0, l0 = _momentum(m, d)
    mujoco.mj_subtreeVel(m, d)
    assert d.subtree_linvel[0] * m.body_subtreemass[0] == pytest.approx(p0, rel=1e-9)
    worst_p = worst_l = 0.0
    for _ in range(50):
        state = sim.step(10)
        assert not sim.monitor.ctb_touched(d) and not state.touching
        p, ang = _momentum(m, d)
        worst_p = max(worst_p, np.linalg.norm(p - p0) / np.linalg.norm(p0))
        worst_l = max(worst_l, np.linalg.norm(ang - l0) / np.linalg.norm(l0))
    assert d.time == pytest.approx(10.0)
    assert worst_p < 1e-6
    assert worst_l < 1e-6
    assert sim.warnings() == {}


# -- vehicle controller ---------------------------------------------------------------------------
def test_profile_matches_closed_form_minimum_time():
    a, j, v = 0.0175, 0.035, 0.2
    profile = JerkLimitedProfile(np.array([a]), np.array([j]))
    dt, t = 0.001, 0.0
    vel, acc = profile.velocity.copy(), profile.acceleration.copy()
    while vel[0] < v and t < 30:
        previous = acc.copy()
        vel, acc = profile.step(np.array([v]), dt)
        t += dt
        assert abs(acc[0]) <= a + 1e-12
        assert abs(acc[0] - previous[0]) <= j * dt * (1 + 1e-9)
    assert t == pytest.approx(min_time_to_speed(v, a, j), abs=dt)
    assert min_time_to_speed(v, a, j) == pytest.approx(v / a + a / j)
    # short move: the acceleration bound is never reached
    assert min_time_to_speed(1e-3, a, j) == pytest.approx(2 * math.sqrt(1e-3 / j))
    for _ in range(2000):  # stays at the target without overshoot
        vel, acc = profile.step(np.array([v]), dt)
        assert vel[0] == pytest.approx(v, abs=1e-9)
    # and back down through zero to a negative target, as fast as the bounds allow
    t = 0.0
    while vel[0] > -v and t < 60:
        vel, acc = profile.step(np.array([-v]), dt)
        t += dt
    assert t == pytest.approx(min_time_to_speed(2 * v, a, j), abs=dt)


def test_force_bounds_follow_the_cargo_moment():
    h = 0.3
    plant = MassProperties(26.0, np.array([0.0, 0.0, -h]), np.diag([2.0, 2.0, 0.7]))
    ctl = VehicleController(plant, "nominal", torque_share=1.0, propulsion="box")
    # F_x makes a pitch moment h F_x, F_y a roll moment h F_y; F_z none
    expected = np.minimum(NOMINAL_FORCE, [NOMINAL_TORQUE[1] / h, NOMINAL_TORQUE[0] / h, np.inf])
    assert ctl.force_max == pytest.approx(expected)
    assert ctl.accel_max == pytest.approx(np.minimum(NOMINAL_ACCEL, 0.8 * expected / 26.0))
    with pytest.raises(VehicleError, match="unknown flight mode 'warp'"):
        VehicleController(plant, "warp")
    with pytest.raises(VehicleError, match="torque_share"):
        VehicleController(plant, torque_share=0.0)


@pytest.mark.parametrize("axis", [0, 1])
def test_vehicle_reaches_speed_within_bounds(bare_world, axis):
    sim = SimDriver(bare_world, flight_mode="nominal", propulsion="box")
    d = sim.data
    if axis == 1:  # face +x so that body y runs along Kibo's length (room to accelerate)
        d.qpos[bare_world.astrobee_qpos + 3 : bare_world.astrobee_qpos + 7] = [1, 0, 0, 0]
        mujoco.mj_forward(sim.model, d)
    mass = float(sim.model.body_subtreemass[bare_world.astrobee])
    command = np.zeros(3)
    command[axis] = 0.2
    sim.command_twist(VehicleTwist(command, np.zeros(3), 0.0))
    # the bounds: a = min(mode, 80 % of the force bound / mass), jerk 0.035 m/s^3
    a, j = min(NOMINAL_ACCEL, 0.8 * NOMINAL_FORCE[axis] / mass), 0.035
    t_bound = min_time_to_speed(0.2, a, j)  # v/a + a/j: arrive with zero acceleration
    near = 0.995 * 0.2
    t_fastest = near / a + a / (2 * j)  # pass `near` still at full acceleration
    reached = None
    for _ in range(round((t_bound + 5.0) / 0.02)):
        # the wrench is set in the body frame at the start of the period, held in the world
        rot = d.xmat[bare_world.astrobee].reshape(3, 3).copy()
        state = sim.step()
        force = rot.T @ d.xfrc_applied[bare_world.astrobee, :3]
        torque = rot.T @ d.xfrc_applied[bare_world.astrobee, 3:]
        assert np.all(np.abs(force) <= NOMINAL_FORCE * (1 + 1e-9))
        assert np.all(np.abs(torque) <= NOMINAL_TORQUE * (1 + 1e-9))
        speed = state.astrobee_linear[axis]
        assert speed <= NOMINAL_SPEED * 1.005
        assert state.module is IssModule.KIBO and not sim.contacts()
        if reached is None and speed >= near:
            reached = state.time
    assert reached is not None
    # within the time the bounds allow, and no faster than they allow (50 Hz hold: 1 step)
    assert t_fastest - 0.02 <= reached <= t_bound
    assert state.astrobee_linear[axis] == pytest.approx(0.2, abs=5e-4)
    assert np.all(np.abs(np.delete(state.astrobee_linear, axis)) < 5e-4)


def test_vehicle_wrench_saturates_at_its_bounds_after_a_kick(bare_world):
    sim = SimDriver(bare_world, flight_mode="nominal", propulsion="box")
    d = sim.data
    sim.command_twist(VehicleTwist.zero())  # station keeping
    sim.step()
    a = bare_world.astrobee_dof
    rot = d.xmat[bare_world.astrobee].reshape(3, 3)
    d.qvel[a : a + 3] = rot @ np.array([0.0, 0.15, 0.05])  # a knock: body y and z
    d.qvel[a + 3 : a + 6] = [0.0, 0.0, 0.3]  # and a spin about body z
    mujoco.mj_forward(sim.model, d)
    peak_f, peak_t = np.zeros(3), np.zeros(3)
    for _ in range(500):
        rot = d.xmat[bare_world.astrobee].reshape(3, 3).copy()
        state = sim.step()
        force = np.abs(rot.T @ d.xfrc_applied[bare_world.astrobee, :3])
        torque = np.abs(rot.T @ d.xfrc_applied[bare_world.astrobee, 3:])
        assert np.all(force <= NOMINAL_FORCE * (1 + 1e-9))
        assert np.all(torque <= NOMINAL_TORQUE * (1 + 1e-9))
        peak_f, peak_t = np.maximum(peak_f, force), np.maximum(peak_t, torque)
    # the feedback asked for more than the bounds, and got exactly the bounds
    assert peak_f[1] == pytest.approx(NOMINAL_FORCE[1], rel=1e-6)
    assert peak_t[2] == pytest.approx(NOMINAL_TORQUE[2], rel=1e-6)
    # and still brought the vehicle to rest (force-bound braking takes about 5 s)
    assert np.linalg.norm(state.astrobee_linear) < 2e-3
    assert np.linalg.norm(state.astrobee_angular) < 2e-3


# -- contact indicator and grasp ------------------------------------------------------------------
def test_opposing_indicator_logic():
    assert opposing({"A", "C"}) and opposing({"B", "D"}) and opposing({"A", "B", "C", "D"})
    assert not opposing({"A", "B"}) and not opposing({"C", "D"}) and not opposing(set())
    # every set of touching fingers, as the monitor returns it (a frozenset, looked up) and
    # as a list: opposing when a finger of each side of the array is among them
    for bits in range(1 << len(FINGERS)):
        fingers = [f for k, f in enumerate(FINGERS) if bits >> k & 1]
        both = all(set(side) & set(fingers) for side in SIDES.values())
        assert opposing(frozenset(fingers)) is opposing(fingers) is both


def test_module_at_is_the_first_zone_containing_the_point():
    """Points inside, outside and on the faces of the zones, as arrays, tuples and lists:
    the module of the first zone (vestibule, Kibo, Node 2) whose box holds the point."""
    layout = IssLayout()
    kibo, vest, node2 = layout.zones()
    rng = np.random.default_rng(5)
    lo = np.min([z.lo for z in (kibo, vest, node2)], axis=0) - 0.5
    hi = np.max([z.hi for z in (kibo, vest, node2)], axis=0) + 0.5
    points = list(rng.uniform(lo, hi, size=(2000, 3)))
    for zone in (kibo, vest, node2):  # the corners and face centres: on the boundary
        for corner in itertools.product(*zip(zone.lo, zone.hi)):
            points.append(np.array(corner))
        points.append(np.array([zone.lo[0], *zone.centre[1:]]))
    seen = set()
    for p in points:
        want = next((z.module for z in (vest, kibo, node2) if z.contains(p)), None)
        for given in (p, tuple(p.tolist()), p.tolist()):
            assert layout.module_at(given) is want
        seen.add(want)
    assert seen == {IssModule.KIBO, IssModule.VESTIBULE, IssModule.NODE2, None}


def test_every_health_flag_combination_is_its_enum_value():
    """``HEALTHS[bits]``: the flags whose bits are set, or-ed together (OK for none)."""
    flags = [h for h in Health.__members__.values() if h]  # each flag, OK (0) aside
    assert len(HEALTHS) == 2 ** len(flags) and Health(sum(flags)) is HEALTHS[-1]
    for bits, health in enumerate(HEALTHS):
        combined = functools.reduce(operator.or_, (f for f in flags if bits & f), Health.OK)
        assert health is combined and int(health) == bits


def test_one_side_touching_is_not_opposing(world):
    sim = SimDriver(world)
    pinch = world.pinch
    sim.send(PayloadCommand(pinch.command_q(False), pinch.stage, 0.0))
    sim.step(50)
    q = pinch.command_q(False)
    for k, f in enumerate(FINGERS):
        if f in ("A", "B"):
            q[4 * k] = pinch.closed[0]
    sim.send(PayloadCommand(q, pinch.stage, 0.0))
    for _ in range(100):
        state = sim.step()
        if state.touching:
            break
    assert state.touching and state.touching <= {"A", "B"}
    assert state.touching == _fingers_touching_by_name(sim)
    assert not state.opposing_contact and not sim.monitor.opposing(sim.data)
    # every contact on request: the same pad-CTB pairs, pressing (MuJoCo's contact force)
    contacts = sim.contacts()
    assert len(contacts) == sim.data.ncon
    pads = {
        other[len(PAYLOAD_PREFIX)]
        for c in contacts
        for one, other in ((c.geom1, c.geom2), (c.geom2, c.geom1))
        if c.dist <= 0 and one.startswith("ctb") and other.endswith("_distal_pad")
    }
    assert pads == state.touching
    assert all(c.normal_force > 0 for c in contacts if c.dist < 0)


def test_ctb_moves_only_through_contact(world):
    sim = SimDriver(world, carrying=False)
    q0 = sim.data.qpos[world.ctb_qpos : world.ctb_qpos + 7].copy()
    # slide sideways: side 2's straight fingers reach the handle after about 14 mm
    sim.command_twist(VehicleTwist(np.array([0.0, 0.02, 0.0]), np.zeros(3), 0.0))
    first_touch = None
    for _ in range(300):
        sim.step()
        q = sim.data.qpos[world.ctb_qpos : world.ctb_qpos + 7]
        if first_touch is None and sim.monitor.ctb_touched(sim.data):
            first_touch = sim.time
        if first_touch is None:
            assert np.array_equal(q, q0), "the CTB moved before anything touched it"
    assert first_touch is not None
    moved = np.linalg.norm(sim.data.qpos[world.ctb_qpos : world.ctb_qpos + 3] - q0[:3])
    assert moved > 1e-3


def test_scripted_grasp_then_1m_translation_carries_the_ctb(world):
    sim = SimDriver(world)
    pinch = world.pinch
    ctb0 = sim.world_state().ctb_pos.copy()
    # pre-shape, then close both pairs on the handle (fixed joint commands)
    sim.send(PayloadCommand(pinch.command_q(False), pinch.stage, 0.0))
    for _ in range(50):
        state = sim.step()
        assert not state.touching and np.array_equal(state.ctb_pos, ctb0)
    sim.send(PayloadCommand(pinch.command_q(True), pinch.stage, sim.time))
    touched = False
    for _ in range(75):
        state = sim.step()
        touched |= sim.monitor.ctb_touched(sim.data)
        if not touched:
            assert np.array_equal(state.ctb_pos, ctb0)
    assert state.opposing_contact
    assert state.touching == _fingers_touching_by_name(sim) == set(FINGERS)
    # 1 m of commanded translation along the body x axis, braking to a stop
    start = state.astrobee_pos.copy()
    heading = _quat_to_rot(state.astrobee_quat)[:, 0]
    in_body0 = state.ctb_in_body()
    ctb_start = state.ctb_pos.copy()
    follower = RouteFollower(
        np.array([start, start + heading]),
        speed=0.2,
        brake=0.8 * float(sim.controller.accel_max[0]),
        omega=0.1745,
    )
    steps = 0
    while steps < 4000:
        twist = follower.twist(state.astrobee_pos, state.astrobee_quat, state.time)
        sim.command_twist(twist)
        state = sim.step()
        steps += 1
        assert state.opposing_contact, f"lost opposing contact at t = {state.time:.2f} s"
        assert state.touching == _fingers_touching_by_name(sim)
        assert sim.monitor.opposing(sim.data)  # the one-pass indicator agrees
        if not np.any(twist.linear) and np.linalg.norm(state.astrobee_linear) < 1e-3:
            break
    moved = state.astrobee_pos - start
    assert moved @ heading == pytest.approx(1.0, abs=0.03)
    carried = state.ctb_pos - ctb_start
    assert carried == pytest.approx(moved, abs=0.01)
    assert np.linalg.norm(state.ctb_in_body() - in_body0) < 0.01
    assert sim.warnings() == {}


# -- driver ---------------------------------------------------------------------------------------
def test_sim_driver_protocol(world):
    with SimDriver(world) as sim:
        assert isinstance(sim, PayloadDriver)
        state = sim.read()
        assert isinstance(state, PayloadState)
        home = world.design.home
        assert state.q == pytest.approx([*home.finger * 4, home.rail], abs=1e-9)
        assert state.deploy == pytest.approx(home.stage)
        with pytest.raises(SimError, match="expected a PayloadCommand"):
            sim.send(np.zeros(17))  # type: ignore[arg-type]
        with pytest.raises(SimError, match="expected a VehicleTwist"):
            sim.command_twist((0.1, 0, 0))  # type: ignore[arg-type]
        # beyond the range: clipped to it, as the servos' position limits do
        q = state.q.copy()
        q[16] = 0.2
        sim.send(PayloadCommand(q, 0.075, 0.0))
        sim.step(100)
        assert sim.read().q[16] == pytest.approx(world.design.rail.travel, abs=2e-3)
        ws = sim.world_state()
        assert ws.module is IssModule.KIBO
        assert ws.astrobee_quat @ ws.astrobee_quat == pytest.approx(1.0)
        assert sim.module_at(ws.ctb_pos) is IssModule.KIBO
    with pytest.raises(SimError, match="closed"):
        sim.read()


def _quat_mul(a, b) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def _inertia_from_model(m, d, bodies, frame_body: int):
    """Mass, CoM and inertia about the CoM of ``bodies``, from MuJoCo's per-body inertials.

    Each body's principal frame is placed from ``body_ipos``/``body_iquat`` and the body pose
    (``xpos``/``xquat``); the sum uses the parallel-axis theorem about the combined CoM and is
    expressed in ``frame_body``'s frame. The CoM is relative to that body's CoM.
    """
    masses, centres, tensors = [], [], []
    for b in bodies:
        rb = _quat_to_rot(d.xquat[b])
        centres.append(d.xpos[b] + rb @ m.body_ipos[b])
        ri = _quat_to_rot(_quat_mul(d.xquat[b], m.body_iquat[b]))
        tensors.append(ri @ np.diag(m.body_inertia[b]) @ ri.T)
        masses.append(m.body_mass[b])
    masses, centres = np.array(masses), np.array(centres)
    total = masses.sum()
    com = masses @ centres / total
    inertia = np.zeros((3, 3))
    for mass, c, tensor in zip(masses, centres, tensors):
        r = c - com
        inertia += tensor + mass * (r @ r * np.eye(3) - np.outer(r, r))
    rf = _quat_to_rot(d.xquat[frame_body])
    origin = d.xpos[frame_body] + rf @ m.body_ipos[frame_body]
    return total, rf.T @ (com - origin), rf.T @ inertia @ rf


def test_mass_properties_match_mujoco_com(world):
    sim = SimDriver(world)
    props = sim.mass_properties(include_ctb=True)
    m, d = sim.model, sim.data
    assert props.mass == pytest.approx(m.body_subtreemass[0])
    rot = d.xmat[world.astrobee].reshape(3, 3)
    assert d.xipos[world.astrobee] + rot @ props.com == pytest.approx(d.subtree_com[0])
    assert np.allclose(props.inertia, props.inertia.T)
    assert np.all(np.linalg.eigvalsh(props.inertia) > 0)


def test_mass_properties_inertia_matches_mujoco(world):
    """The inertia tensor against an independent sum of MuJoCo's per-body inertials."""
    sim = SimDriver(world)
    m, d = sim.model, sim.data
    # a general pose: Astrobee turned about a skew axis, fingers and rail off home, CTB turned
    a = world.astrobee_qpos
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    d.qpos[a + 3 : a + 7] = np.append(math.cos(0.35), math.sin(0.35) * axis)
    lo, hi = m.jnt_range[[int(np.flatnonzero(m.jnt_qposadr == q)[0]) for q in world.qpos]].T
    d.qpos[world.qpos] = lo + np.linspace(0.2, 0.8, len(world.qpos)) * (hi - lo)
    c = world.ctb_qpos
    d.qpos[c + 3 : c + 7] = _quat_mul(d.qpos[a + 3 : a + 7], [math.cos(0.2), 0.0, math.sin(0.2), 0])
    mujoco.mj_forward(m, d)

    def subtree(root: int) -> list[int]:
        out = []
        for b in range(1, m.nbody):
            p = b
            while p not in (0, root):
                p = int(m.body_parentid[p])
            if p == root:
                out.append(b)
        return out

    vehicle = subtree(world.astrobee)
    assert world.astrobee in vehicle and world.ctb not in vehicle
    assert len(vehicle) > 1 + 4 * 4  # Astrobee, the payload structure, four 4-link fingers
    for include_ctb, bodies in ((False, vehicle), (True, [*vehicle, world.ctb])):
        props = sim.mass_properties(include_ctb=include_ctb)
        mass, com, inertia = _inertia_from_model(m, d, bodies, world.astrobee)
        assert props.mass == pytest.approx(mass)
        np.testing.assert_allclose(props.com, com, rtol=0, atol=1e-12)
        np.testing.assert_allclose(props.inertia, inertia, rtol=1e-9, atol=1e-12)
    # the payload and the CTB matter: the result is not Astrobee's own inertia
    assert not np.allclose(props.inertia, np.diag(m.body_inertia[world.astrobee]), rtol=0.05)


def test_ctb_sizes_are_the_standard_ones():
    from payload.sim import CTB_SIZES

    assert CTB_SIZES["single"] == CtbSize("single", 0.502, 0.425, 0.248, 15.4)
    assert CTB_SIZES["half"].mass == 7.3 and CTB_SIZES["double"].mass == 31.0


# -- command line ---------------------------------------------------------------------------------
def test_bench_sim_json():
    from payload.cli import main

    out, err = io.StringIO(), io.StringIO()
    start = time.perf_counter()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(["bench", "sim", "--seconds", "1", "--json", "--no-progress"])
    outside = time.perf_counter() - start
    assert code == 0
    lines = out.getvalue().strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    for key in ("sim_seconds", "wall_seconds", "realtime_factor", "physics_hz", "control_hz"):
        assert key in result
    assert result["sim_seconds"] == pytest.approx(1.0)
    assert result["physics_hz"] == 1000 and result["control_hz"] == 50
    # the bench's clock against this one: it cannot have run longer than the call did
    assert 0 < result["wall_seconds"] <= outside
    assert result["realtime_factor"] >= result["sim_seconds"] / outside
    assert result["propulsion"] == "nozzles"
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):  # no bar to a pipe: not even a newline
        code = main(["bench", "sim", "--seconds", "0.2", "--json", "--propulsion", "box"])
    assert code == 0 and json.loads(out.getvalue())["propulsion"] == "box"
    assert err.getvalue() == ""


def test_bench_sim_bad_input_exits_2():
    from payload.cli import main

    err = io.StringIO()
    with redirect_stderr(err), redirect_stdout(io.StringIO()):
        code = main(["bench", "sim", "--seconds", "-1", "--no-progress"])
    assert code == 2
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and "--seconds" in lines[0]


def test_the_physics_step_is_1_ms_by_default_and_a_2_ms_world_is_derived_from_its_step(world):
    """1 kHz is the default; a 2 ms world has the 2 ms timestep, 10 substeps, and the
    pad contact derived from 2 ms (pad_contact called here with the step)."""
    from payload.design.params import load_design
    from payload.sim.pads import pad_contact

    assert WorldConfig().physics_dt == 0.001 and WorldConfig().substeps == 20
    assert world.model.opt.timestep == 0.001
    fast = build_world(WorldConfig(physics_dt=0.002))
    assert fast.model.opt.timestep == 0.002 and fast.config.substeps == 10
    design = load_design(fast.config.design)
    size = fast.config.ctb_size
    for dt, w in ((0.001, world), (0.002, fast)):
        c = pad_contact(design, str(w.config.payload_mjcf), design.pinch.finger, size.mass, dt)
        pad = w.pad_geoms["A"]
        assert tuple(w.model.geom_solref[pad]) == pytest.approx(c.solref, rel=1e-12)
        assert c.solref[0] >= 2 * dt  # MuJoCo's stability floor of the time constant
    with SimDriver(fast) as sim:
        sim.step()
        assert sim.time == pytest.approx(0.02, abs=1e-12)  # one control period either way
    for bad in (0.0, -0.001, 0.0015, float("nan")):
        with pytest.raises(SimError, match="physics_dt"):
            WorldConfig(physics_dt=bad)


def test_a_payload_state_of_frozen_vectors_is_the_constructors():
    """``PayloadState.of_frozen`` takes read-only vectors as they are, and anything else as
    the constructor does: the same fields, the same refusals."""
    n = len(MANIPULATION_JOINTS)
    rng = np.random.default_rng(3)
    buf = rng.normal(size=3 * n)
    buf[n + 4] = np.nan  # a velocity not measured
    buf.setflags(write=False)
    q, dq, effort = buf[:n], buf[n : 2 * n], buf[2 * n :]
    made = PayloadState.of_frozen(q, 0.01, 2.5, dq, effort, Health.LIMIT)
    built = PayloadState(q.copy(), 0.01, 2.5, dq.copy(), effort.copy(), Health.LIMIT)
    for name, given in (("q", q), ("dq", dq), ("effort", effort)):
        assert getattr(made, name) is given  # taken, not copied
        assert getattr(made, name).tobytes() == getattr(built, name).tobytes()
        assert not getattr(made, name).flags.writeable
    assert (made.deploy, made.stamp, made.health) == (built.deploy, built.stamp, built.health)
    # writeable, a list or another length: built (copied and checked) as the constructor does
    loose = PayloadState.of_frozen(q.copy(), 0.0, 0.0, list(dq), effort)
    assert loose.q.tobytes() == q.tobytes() and not loose.q.flags.writeable
    with pytest.raises(SchemaError, match=f"expected {n} values"):
        PayloadState.of_frozen(buf[: n - 1], 0.0, 0.0, dq, effort)
    bad = buf.copy()
    bad[2] = np.inf
    bad.setflags(write=False)
    with pytest.raises(SchemaError, match=MANIPULATION_JOINTS[2]):
        PayloadState.of_frozen(bad[:n], 0.0, 0.0, dq, effort)


def test_a_command_and_a_twist_of_frozen_vectors_are_the_constructors():
    """``PayloadCommand.of_frozen`` and ``VehicleTwist.of_frozen`` take read-only float64
    vectors as they are, and anything else as the constructors do: the same fields, the
    same refusals (the loop's pipeline and base channel make theirs this way)."""
    n = len(MANIPULATION_JOINTS)
    q = np.random.default_rng(4).normal(size=n)
    q.setflags(write=False)
    made = PayloadCommand.of_frozen(q, 0.02, 1.5)
    built = PayloadCommand(q.copy(), 0.02, 1.5)
    assert made.q is q and made.q.tobytes() == built.q.tobytes()  # taken, not copied
    assert (made.deploy, made.stamp) == (built.deploy, built.stamp)
    loose = PayloadCommand.of_frozen(q.copy(), 0.0, 0.0)  # writeable: copied and frozen
    assert loose.q.tobytes() == q.tobytes() and not loose.q.flags.writeable
    bad = q.copy()
    bad[5] = np.nan
    bad.setflags(write=False)
    with pytest.raises(SchemaError, match=MANIPULATION_JOINTS[5]):
        PayloadCommand.of_frozen(bad, 0.0, 0.0)
    for deploy, stamp in ((np.inf, 0.0), (0.0, np.nan)):
        with pytest.raises(SchemaError, match="not finite"):
            PayloadCommand.of_frozen(q, deploy, stamp)
    with pytest.raises(SchemaError, match=f"expected {n} values"):
        PayloadCommand.of_frozen(q[:-1], 0.0, 0.0)
    single = q.astype(np.float32)  # read-only, another type: converted as the constructor does
    single.setflags(write=False)
    other = PayloadCommand.of_frozen(single, 0.0, 0.0)
    assert other.q is not single and other.q.dtype == np.float64
    assert other.q.tobytes() == single.astype(np.float64).tobytes()

    vel = np.array([0.1, -0.2, 0.3, 0.0, 0.0, 0.05])
    vel.setflags(write=False)
    twist = VehicleTwist.of_frozen(vel[:3], vel[3:], 2.0)
    assert np.shares_memory(twist.linear, vel)  # taken, not copied
    assert twist.linear.tolist() == [0.1, -0.2, 0.3] and twist.angular.tolist() == [0, 0, 0.05]
    assert twist.stamp == 2.0 and not twist.angular.flags.writeable
    ints = np.array([1, 2, 3])
    ints.setflags(write=False)
    converted = VehicleTwist.of_frozen(vel[:3], ints, 0.0)
    assert converted.angular is not ints and converted.angular.dtype == np.float64
    open_ = VehicleTwist.of_frozen(np.array([1.0, 2.0, 3.0]), vel[3:], 0.0)
    assert open_.linear.tolist() == [1.0, 2.0, 3.0] and not open_.linear.flags.writeable
    broken = np.array([0.0, np.inf, 0.0])
    broken.setflags(write=False)
    with pytest.raises(SchemaError, match=r"VehicleTwist\.linear"):
        VehicleTwist.of_frozen(broken, vel[3:], 0.0)
    with pytest.raises(SchemaError, match=r"VehicleTwist\.angular: expected 3"):
        VehicleTwist.of_frozen(vel[:3], vel, 0.0)


def test_benches_read_the_control_period_and_the_flight_mode_not_retyped() -> None:
    """The scripted operator of ``bench sim`` flies at the nominal flight mode's caps (the
    paper's 0.20 m/s; docs/sources.md, "Vehicle": nominal 0.1745 rad/s) and the retargeting bench
    streams at the 50 Hz loop's period, each read from where the fact lives."""
    import inspect

    from payload.design.vehicle import DEFAULT_FLIGHT_MODE, FLIGHT_MODES
    from payload.retarget import bench as retarget_bench
    from payload.schema import CONTROL_DT
    from payload.sim.bench import ScriptedOperator

    params = inspect.signature(ScriptedOperator).parameters
    mode = FLIGHT_MODES[DEFAULT_FLIGHT_MODE]
    assert params["speed"].default == mode.speed == pytest.approx(0.20)
    assert params["omega"].default == mode.omega == pytest.approx(0.1745)
    assert retarget_bench.DT == CONTROL_DT == pytest.approx(1.0 / 50.0)


def test_the_jerk_bounds_reach_the_nominal_accelerations_in_half_a_second() -> None:
    """The controller's default jerk bounds are the nominal flight mode's acceleration
    limits (docs/sources.md, "Vehicle": 0.0175 m/s^2, 0.1745 rad/s^2) reached in 0.5 s, the
    documented assumption: 0.035 m/s^3 and 0.349 rad/s^3."""
    from payload.sim.vehicle import MassProperties, VehicleController

    plant = MassProperties(20.0, np.zeros(3), np.diag([0.3, 0.3, 0.3]))
    ctl = VehicleController(plant, "nominal", propulsion="box")
    assert ctl.jerk[:3] == pytest.approx([0.0175 / 0.5] * 3, rel=1e-12)
    assert ctl.jerk[3:] == pytest.approx([0.1745 / 0.5] * 3, rel=1e-12)
