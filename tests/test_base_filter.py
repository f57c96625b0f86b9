"""The base safety filter against scripted base commands (no operator), measured with
MuJoCo's own distance query (mj_geomDistance), independent of the filter's geometry."""

from __future__ import annotations

import json
import math
import time

import mujoco
import numpy as np
import pytest

from payload.schema import CONTROL_DT, VehicleTwist
from payload.sim.driver import SimDriver
from payload.sim.stack import hold_ctb, place_stack
from payload.sim.world import build_world
from payload.sim.zones import StationZones, ZoneError, station_zones
from payload.teleop.base_filter import (
    MARGIN_TOLERANCE,
    BaseSafetyFilter,
    SafetyConfig,
    stop_speed,
)
from payload.teleop.channels import BaseConfig

TOLERANCE = MARGIN_TOLERANCE


@pytest.fixture(scope="module")
def world():
    return build_world()


@pytest.fixture(scope="module")
def grasped_state(world):
    return hold_ctb(world)


def _driver(world, held, pos, velocity) -> SimDriver:
    return place_stack(world, held, pos, velocity)


def _filter(sim: SimDriver, **kw) -> BaseSafetyFilter:
    c = sim.controller
    return BaseSafetyFilter(sim.world, BaseConfig(), c.accel_max, float(c.jerk[0]), **kw)


def _moving_geoms(world) -> list[int]:
    m = world.model
    return [
        g
        for g in range(m.ngeom)
        if (m.body_rootid[m.geom_bodyid[g]] == world.astrobee or m.geom_bodyid[g] == world.ctb)
        and (m.geom_contype[g] or m.geom_conaffinity[g])
    ]


def least_distance(sim: SimDriver, moving: list[int], cap: float = 0.3) -> float:
    """Least distance from any vehicle, payload or CTB geom to the station [m] by
    mj_geomDistance (pairs whose bounding spheres are farther than ``cap`` skipped)."""
    m, d = sim.model, sim.data
    iss = np.asarray(sim.world.iss_geoms)
    moving = np.asarray(moving)
    centres = np.linalg.norm(d.geom_xpos[moving][:, None] - d.geom_xpos[iss][None], axis=2)
    gaps = centres - m.geom_rbound[moving][:, None] - m.geom_rbound[iss][None]
    best = cap
    fromto = np.zeros(6)
    for i, j in zip(*np.nonzero(gaps < cap)):
        best = min(best, mujoco.mj_geomDistance(m, d, int(moving[i]), int(iss[j]), cap, fromto))
    return best


def fly(sim, filt, v_world, yaw_rate, seconds):
    """Request a constant world velocity and yaw rate; returns (least distance [m],
    steps with the filter active, whether the bag stayed in the pinch)."""
    sim.twist_filter = filt
    moving = _moving_geoms(sim.world)
    least, active, held = np.inf, 0, True
    for _ in range(round(seconds * 50)):
        rot = sim.data.xmat[sim.world.astrobee].reshape(3, 3)
        sim.command_twist(
            VehicleTwist(rot.T @ np.asarray(v_world, float), rot.T @ np.array([0, 0, yaw_rate]), 0)
        )
        state = sim.step()
        least = min(least, least_distance(sim, moving))
        status = getattr(filt, "status", None)
        active += bool(status is not None and status.active)
        held &= state.opposing_contact
    return least, active, held


MARGIN = SafetyConfig().margin


@pytest.mark.parametrize(
    "name, pos, v0, wanted, yaw, seconds",
    [
        # straight at Kibo's side wall, the request at full speed
        ("kibo wall", (1.6, 7.0, 0.25), (0.06, 0.0, 0.0), (0.2, 0.0, 0.0), 0.0, 8.0),
        # up and forward into the hatch's upper edge, Astrobee's top above the opening
        ("hatch edge", (1.5, 4.2, 0.55), (0.0, -0.06, 0.015), (0.0, -0.194, 0.0485), 0.0, 10.0),
        # a fast right turn toward Node 2's starboard wall, the bag swinging outward
        ("node2 turn", (1.5, -0.2, 0.25), (-0.08, -0.06, 0.0), (-0.16, -0.12, 0.0), -0.1, 10.0),
    ],
)
def test_filter_keeps_the_margin(world, grasped_state, name, pos, v0, wanted, yaw, seconds):
    sim = _driver(world, grasped_state, pos, v0)
    filt = _filter(sim)
    least, active, held = fly(sim, filt, wanted, yaw, seconds)
    assert active > 0, f"{name}: the filter never acted"
    assert least >= MARGIN - TOLERANCE, f"{name}: {least * 1e3:.1f} mm from the station"
    assert held, f"{name}: the bag left the pinch"


@pytest.mark.parametrize(
    "pos, v0, wanted, yaw",
    [
        ((1.818, 6.404, 0.384), (0.0062, -0.0011, 0.0), (0.197, -0.036, 0.022), 0.0),
        ((1.504, 7.094, 0.292), (0.0467, -0.0163, 0.0), (0.189, -0.066, -0.011), 0.0),
        ((1.504, 7.094, 0.292), (0.0467, -0.0163, 0.0), (0.189, -0.066, -0.011), -0.1),
        ((1.562, 7.827, 0.237), (0.0294, 0.0033, 0.0), (0.199, 0.023, 0.046), 0.1),
        ((1.769, 6.077, 0.202), (0.006, 0.0009, 0.0), (0.198, 0.029, -0.005), -0.1),
    ],
)
def test_turning_buys_no_closer_approach(world, grasped_state, pos, v0, wanted, yaw):
    """Starts inside the filter's safe set (no barrier row at the present velocity), then a
    constant request at Kibo's +x wall, with or without a turn. A turn that swings a
    point away from the wall must not pay for the vehicle closing in: the rotation ends
    (and brings another corner round) long before the loaded stack, at about
    0.004 m/s^2, has stopped. While the QP could trade the one for the other, it turned
    the bag back and forth (unasked) and these runs struck the station or came within
    17 mm of it."""
    sim = _driver(world, grasped_state, pos, v0)
    filt = _filter(sim)
    rot = sim.data.xmat[world.astrobee].reshape(3, 3)
    rows = filt._constraints(sim.data, rot, sim.data.xpos[world.astrobee], np.r_[v0, 0.0])
    assert rows[2] >= 0.0, "the start is outside the safe set"
    least, active, _ = fly(sim, filt, wanted, yaw, 15.0)
    assert active > 0
    assert least >= MARGIN - TOLERANCE, f"{least * 1e3:.1f} mm from the station"


@pytest.mark.parametrize(
    "pos, way, speed",
    [
        ((1.746, 2.602, 0.073), (0.39, -0.86, 0.34), 0.013),
        ((1.298, 1.639, 0.4), (-0.23, -0.49, -0.84), 0.021),
    ],
)
def test_the_chain_stops_within_the_margin(world, grasped_state, pos, way, speed):
    """Starts in the safe set near the hatch, a constant request along the start's motion
    (analyses/filter_sweep.py). The output stage follows the filter's target at the
    channel's 0.0175 m/s^2, faster than the loaded stack (about 0.004 m/s^2), and takes
    0.875 s to ramp its own acceleration down; while the stop model's lag left that ramp
    out, the stack's reference overshot the target and these came 33 and 38 mm from the
    station."""
    way = np.asarray(way) / np.linalg.norm(way)
    sim = _driver(world, grasped_state, pos, speed * way)
    least, active, _ = fly(sim, _filter(sim), BaseConfig().max_speed * way, 0.0, 15.0)
    assert active > 0
    assert least >= MARGIN - TOLERANCE, f"{least * 1e3:.1f} mm from the station"


def test_unfiltered_request_strikes_the_wall(world, grasped_state):
    """The first scenario without the filter: the station is struck (so the test above
    measures something)."""
    sim = _driver(world, grasped_state, (1.6, 7.0, 0.25), (0.06, 0.0, 0.0))
    least, _, _ = fly(sim, lambda t, d: t, (0.2, 0.0, 0.0), 0.0, 8.0)
    assert least <= 1e-3


def test_hatch_stays_passable_with_the_bag(world, grasped_state):
    sim = _driver(world, grasped_state, (1.5, 3.9, 0.25), (0.0, -0.1, 0.0))
    filt = _filter(sim)
    y0 = float(sim.world_state().astrobee_pos[1])
    least, _, held = fly(sim, filt, (0.0, -0.2, 0.0), 0.0, 14.0)
    state = sim.world_state()
    vestibule = world.layout.vestibule
    assert state.astrobee_pos[1] < vestibule.hi[1] - 0.4, "not into the vestibule"
    assert y0 - state.astrobee_pos[1] > 1.1
    assert np.linalg.norm(state.astrobee_linear) > 0.05, "trapped in the hatch"
    assert least >= MARGIN - TOLERANCE and held


def test_far_from_the_walls_the_filter_is_the_identity(world, grasped_state):
    """Mid-Kibo, a slow request: the filter returns the request itself, and a driver
    with the filter steps bit for bit like one without."""
    pos, v0 = (1.5, 7.0, 0.25), (0.0, 0.0, 0.0)
    plain = _driver(world, grasped_state, pos, v0)
    guarded = _driver(world, grasped_state, pos, v0)
    filt = _filter(guarded)
    guarded.twist_filter = filt
    rot = plain.data.xmat[world.astrobee].reshape(3, 3)
    twist = VehicleTwist(rot.T @ np.array([0.0, -0.03, 0.0]), np.zeros(3), 0.0)
    assert filt(twist, guarded.data) is twist
    filt.reset()
    for _ in range(25):
        plain.command_twist(twist)
        guarded.command_twist(twist)
        plain.step()
        guarded.step()
        assert not filt.status.active
    assert np.array_equal(plain.data.qpos, guarded.data.qpos)
    assert np.array_equal(plain.data.qvel, guarded.data.qvel)


def test_filter_respects_the_channel_bounds(world, grasped_state):
    """Braking hard at a wall, the filtered command still moves within the channel's
    speed, acceleration and jerk bounds (finite differences of the output)."""
    sim = _driver(world, grasped_state, (1.6, 7.0, 0.25), (0.06, 0.0, 0.0))
    filt = _filter(sim)
    base = BaseConfig()
    outs = []

    def recording(twist, data):
        out = filt(twist, data)
        rot = data.xmat[world.astrobee].reshape(3, 3)
        outs.append(rot @ out.linear)
        return out

    fly(sim, recording, (0.2, 0.0, 0.0), 0.0, 3.0)
    v = np.array(outs)
    dt = 0.02
    acc = np.diff(v, axis=0) / dt
    jerk = np.diff(acc, axis=0) / dt
    assert np.linalg.norm(v, axis=1).max() <= base.max_speed + 1e-9
    assert np.linalg.norm(acc[1:], axis=1).max() <= base.max_accel * (1 + 1e-6)
    assert np.linalg.norm(jerk[1:], axis=1).max() <= base.max_jerk * (1 + 1e-6) + 1e-9


def test_output_stage_stays_within_the_channel_caps_when_redirected(world, grasped_state):
    """The QP's answer to a request beyond the caps is scaled to them; the output stage
    (the filter's two limiters) then tracks it from the stack's motion along another
    direction. Its speed and yaw rate never exceed the channel's caps (norms of the
    outputs against BaseConfig's numbers; capped at the caps themselves, the limiters'
    discrete landing overshot them by a few um/s and urad/s)."""
    sim = _driver(world, grasped_state, (1.5, 7.0, 0.25), (0.0, 0.0, 0.0))
    base = BaseConfig()
    worst_speed = worst_yaw = 0.0
    for v0, heading in ((0.15, 1.0), (0.19, 0.3), (0.195, 1.5)):
        filt = _filter(sim)
        rows, bounds = np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([-1.0])  # never binding
        # a translation, then a turn, each beyond its cap (scaled together, one at a time)
        go = np.array([0.3 * math.cos(heading), 0.3 * math.sin(heading), 0.0, 0.0])
        linear = filt._solve(go, rows, bounds)[:3]
        turn = filt._solve(np.array([0.0, 0.0, 0.0, 0.3]), rows, bounds)[3:]
        filt.linear.value = np.array([v0, 0.0, 0.0])  # moving along x, not accelerating
        filt.yaw.value = np.array([v0 / 2.0])  # turning, not accelerating
        for _ in range(1500):
            v = filt.linear.step(linear, CONTROL_DT)
            w = filt.yaw.step(turn, CONTROL_DT)[0]
            worst_speed = max(worst_speed, float(np.sqrt(v @ v)))
            worst_yaw = max(worst_yaw, abs(w))
    assert worst_speed > base.max_speed - 1e-3 and worst_yaw > base.max_yaw_rate - 1e-3
    assert worst_speed <= base.max_speed
    assert worst_yaw <= base.max_yaw_rate


def test_behind_the_base_channel_the_filter_keeps_its_bounds_through_engage_and_release(
    world, grasped_state
):
    """The base channel's own stream (a left wrist held toward Kibo's +x wall, then back
    in neutral, then away with a turn) through the filter into the simulator: the filter
    takes over, hands back to the request (the identity again) and takes over once
    more. Finite differences of every output, linear and yaw, including the steps where
    it takes over and hands back, stay within the channel's bounds."""
    from payload.teleop.channels import BaseChannel

    sim = _driver(world, grasped_state, (1.3, 7.0, 0.25), (0.0, 0.0, 0.0))
    filt = _filter(sim)
    cfg = BaseConfig()
    channel = BaseChannel(cfg, np.zeros(3))
    wrists = [np.array([0.3, 0.0, 0.0])] * 1000 + [np.zeros(3)] * 1000
    wrists += [np.array([-0.3, 0.1, 0.0])] * 1000
    v, w, active = [], [], []
    for wrist in wrists:
        rot = sim.data.xmat[world.astrobee].reshape(3, 3).copy()
        out = filt(channel.step(wrist, rot).twist, sim.data)
        v.append(rot @ out.linear)
        w.append(float((rot @ out.angular)[2]))
        active.append(filt.status.active)
        sim.command_twist(out)
        sim.step()
    switches = np.diff(np.array(active, dtype=int))
    assert (switches == 1).sum() >= 2 and (switches == -1).sum() >= 1  # engaged, released
    v, w = np.array(v), np.array(w)
    acc = np.diff(v, axis=0) / CONTROL_DT
    yaw_acc = np.diff(w) / CONTROL_DT
    tol = 1e-6
    assert np.linalg.norm(v, axis=1).max() <= cfg.max_speed
    assert np.linalg.norm(acc, axis=1).max() <= cfg.max_accel * (1 + tol)
    jerk = np.diff(acc, axis=0) / CONTROL_DT
    assert np.linalg.norm(jerk, axis=1).max() <= cfg.max_jerk * (1 + tol)
    assert np.abs(w).max() <= cfg.max_yaw_rate
    assert np.abs(yaw_acc).max() <= cfg.max_yaw_accel * (1 + tol)
    assert np.abs(np.diff(yaw_acc) / CONTROL_DT).max() <= cfg.max_yaw_jerk * (1 + tol)


def test_stop_speed_matches_a_simulated_brake():
    """stop_speed against a brute-force jerk-limited brake from the worst case."""
    accel, jerk, lag, dt = 0.004, 0.02, 0.3, 1e-4
    for dist in (0.05, 0.4, 2.0):
        v0 = float(stop_speed(np.array([dist]), accel, jerk, lag)[0])
        v, a, x, t = v0, accel, 0.0, 0.0
        while v > 0:
            if t >= lag:
                a = max(a - jerk * dt, -accel)
            x += v * dt
            v += a * dt
            t += dt
        assert x <= dist + 1e-3


# -- zones -----------------------------------------------------------------------------------
def test_station_zones_follow_the_simulated_walls(world):
    """The keep-in union holds the route and no ISS geom: every wall and handrail lies
    outside it (sampled on each geom's box), and the obstacles cover the station's geoms."""
    zones = station_zones(world.layout)
    for p in world.layout.route():
        assert zones.contains(p)
    m, d = world.model, mujoco.MjData(world.model)
    mujoco.mj_kinematics(m, d)
    lo, hi, _ = zones.obstacles()
    grid = np.array(np.meshgrid(*[np.linspace(-0.999, 0.999, 5)] * 3)).reshape(3, -1).T
    for g in world.iss_geoms:
        pts = d.geom_xpos[g] + (grid * m.geom_size[g]) @ d.geom_xmat[g].reshape(3, 3).T
        for p in pts:
            assert not zones.contains(p), f"geom {g} reaches into the keep-in set at {p}"
            # open space outside the keep-in union but inside a wall: an obstacle holds it
            assert np.any(np.all((lo <= p + 1e-9) & (p - 1e-9 <= hi), axis=1))


def test_zone_json_round_trip_and_errors(tmp_path):
    zones = StationZones(
        (((0.0, 0.0, 0.0), (1.0, 2.0, 3.0)),), (((0.2, 0.2, 0.2), (0.4, 0.4, 0.4)),)
    )
    path = tmp_path / "zones.json"
    zones.write(path)
    data = json.loads(path.read_text())
    assert data[0] == {"sequence": [[0.0, 0.0, 0.0, 1.0, 2.0, 3.0]], "safe": True}
    back = StationZones.read(path)
    assert back.keepin == zones.keepin and back.keepout == zones.keepout
    assert back.contains((0.5, 0.5, 0.5)) and not back.contains((0.3, 0.3, 0.3))
    one = StationZones.from_json({"sequence": [[0, 0, 0, 1, 1, 1]], "safe": True})
    assert one.keepin == (((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),)
    for bad, words in (
        ({"sequence": [[0, 0, 0, 1, 1]], "safe": True}, "6 numbers"),
        ({"sequence": [[1, 0, 0, 0, 1, 1]], "safe": True}, "below"),
        ({"sequence": [[0, 0, 0, 1, 1, 1]], "safe": "yes"}, "'safe'"),
        ({"sequence": [[0, 0, 0, 1, 1, 1]], "safe": False}, "no keep-in"),
        ([1, 2], "expected"),
    ):
        with pytest.raises(ZoneError, match=words):
            StationZones.from_json(bad)
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ZoneError, match="not JSON"):
        StationZones.read(tmp_path / "bad.json")


def test_a_keepout_box_stops_the_vehicle(world, grasped_state):
    """A loaded zone file's keep-out box in mid-Kibo is kept off like a wall."""
    zones = station_zones(world.layout, keepout=[((1.2, 5.6, -0.9), (1.8, 5.9, 0.9))])
    sim = _driver(world, grasped_state, (1.5, 6.6, 0.25), (0.0, -0.05, 0.0))
    filt = _filter(sim, zones=zones)
    fly(sim, filt, (0.0, -0.2, 0.0), 0.0, 8.0)
    pts = np.vstack([s.points(*s.box(sim.data)) for s in filt.shapes])
    assert pts[:, 1].min() >= 5.9 + MARGIN - TOLERANCE


def test_filter_cost_per_step(world, grasped_state):
    """Indicative on a shared machine: the median step is well under a millisecond."""
    sim = _driver(world, grasped_state, (1.6, 7.0, 0.25), (0.06, 0.0, 0.0))
    filt = _filter(sim)
    rot = sim.data.xmat[world.astrobee].reshape(3, 3)
    twist = VehicleTwist(rot.T @ np.array([0.2, 0.0, 0.0]), np.zeros(3), 0.0)
    times = []
    for _ in range(100):
        t = time.perf_counter()
        filt(twist, sim.data)
        times.append(time.perf_counter() - t)
    assert filt.status.constraints > 0
    assert np.median(times) < 5e-3


def test_station_monitor_sees_the_strike(world, grasped_state):
    """StationMonitor against the unfiltered strike: contact and zero clearance at the
    wall, the cap in mid-module."""
    from payload.sim.station import CLEARANCE_CAP, StationMonitor

    sim = _driver(world, grasped_state, (1.5, 7.0, 0.25), (0.0, 0.0, 0.0))
    monitor = StationMonitor(world)
    assert monitor.read(sim.data) == (False, CLEARANCE_CAP)
    sim = _driver(world, grasped_state, (1.6, 7.0, 0.25), (0.06, 0.0, 0.0))
    moving = _moving_geoms(world)
    touched = False
    for _ in range(400):
        rot = sim.data.xmat[world.astrobee].reshape(3, 3)
        sim.command_twist(VehicleTwist(rot.T @ np.array([0.2, 0.0, 0.0]), np.zeros(3), 0.0))
        sim.step()
        reading = monitor.read(sim.data)
        assert reading.clearance == pytest.approx(least_distance(sim, moving), abs=1e-9)
        touched |= reading.contact
    assert touched


def test_the_station_monitors_quick_bound_never_changes_a_reading(world, grasped_state):
    """StationMonitor first tests a box around every moving geom's box; where that says
    nothing is near it returns the cap without the per-geom boxes. Against the same
    monitor with that bound off, on 600 random poses of the stack (CTB included) over
    the trial's route and off it into the walls: the same reading, bit for bit, both ways of
    answering taken many times."""
    from payload.sim import station

    sim = _driver(world, grasped_state, (1.5, 7.0, 0.25), (0.0, 0.0, 0.0))
    m, d = sim.model, sim.data
    quick, exact = station.StationMonitor(world), station.StationMonitor(world)
    exact._reach[:] = np.inf  # every pose goes on to the per-geom boxes
    quick.read(d)  # its bound, compiled or not, built: count the reads that go on past it
    went_on = []
    kernel = quick._bound_kernel(d)
    if kernel is not None:
        clearance = kernel.clearance
        kernel.clearance = lambda: went_on.append(1) or clearance()
    else:
        numpy_clearance = quick._clearance_numpy
        quick._clearance_numpy = lambda data: went_on.append(1) or numpy_clearance(data)
    rng = np.random.default_rng(4)
    route = np.asarray(world.layout.route(), dtype=float)
    a, c = world.astrobee_qpos, world.ctb_qpos
    held = d.qpos[c : c + 3] - d.qpos[a : a + 3]
    quat0 = d.qpos[a + 3 : a + 7].copy()
    for k in range(600):
        leg = rng.integers(len(route) - 1)
        on_route = route[leg] + rng.uniform() * (route[leg + 1] - route[leg])
        spread = 0.1 if k % 2 else 0.5  # about the route, or out to and past the walls
        pos = on_route + rng.normal(scale=spread, size=3)
        quat = quat0 + rng.normal(scale=0.1 if k % 3 else 1.0, size=4)
        d.qpos[a : a + 3] = pos
        d.qpos[a + 3 : a + 7] = quat / np.linalg.norm(quat)
        d.qpos[c : c + 3] = pos + held + rng.normal(scale=0.05, size=3)
        mujoco.mj_forward(m, d)
        want = exact.read(d)
        got = quick.read(d)
        assert got == want and type(got.clearance) is type(want.clearance)
    assert 50 < len(went_on) < 550, len(went_on)  # both ways of answering, many times


def test_cli_controller_filter_zones_and_delay_reach_the_runner(
    world, tmp_path, monkeypatch, capsys
):
    """``--controller safe`` turns the filter on (``--no-base-filter`` overrides it);
    ``--zones`` and ``--link-delay`` are parsed and passed on; bad values exit 2: among
    them zones with the filter off (they were ignored), and zones whose free space does
    not hold the vehicle where the simulated world starts it (the filter never acted)."""
    import sys
    import types

    from payload.cli import main

    calls = []

    def run_trial(**kw):
        calls.append(kw)
        return {"seed": kw.get("seed", 0), "out_dir": str(tmp_path)}

    module = types.ModuleType("payload.trials.runner")
    module.run_trial = run_trial
    monkeypatch.setitem(sys.modules, "payload.trials.runner", module)
    zones = tmp_path / "zones.json"
    station_zones().write(zones)
    base = ["trial", "--out", str(tmp_path / "t"), "--json"]
    assert (
        main([*base, "--controller", "safe", "--link-delay", "1.0:0.2", "--zones", str(zones)]) == 0
    )
    assert calls[-1]["base_filter"] is True and calls[-1]["retarget_collisions"] is True
    assert calls[-1]["link_delay"] == (1.0, 0.2)
    assert calls[-1]["zones"] == StationZones.read(zones)
    assert main([*base, "--controller", "safe", "--no-base-filter"]) == 0
    assert calls[-1]["base_filter"] is False
    assert main(base) == 0
    assert calls[-1]["base_filter"] is False and "link_delay" not in calls[-1]
    capsys.readouterr()
    assert main([*base, "--link-delay", "soon"]) == 2
    assert "--link-delay" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text('{"sequence": [[0, 0, 0, 1, 1]], "safe": true}')
    safe = [*base, "--controller", "safe"]
    assert main([*safe, "--zones", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "6 numbers" in err[0]
    assert f"{tmp_path / 'bad.json'}: sequence[0]: " in err[0], err  # not "bad.json.sequence"
    n = len(calls)
    for argv in (base, [*safe, "--no-base-filter"]):  # the filter off: the zones refused
        assert main([*argv, "--zones", str(zones)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "the zones are the base filter's, and it is off" in err[0]
    # a keep-in box away from where the world starts the vehicle (a 1 m cube at the origin)
    tiny = tmp_path / "tiny.json"
    tiny.write_text('{"sequence": [[0, 0, 0, 1, 1, 1]], "safe": true}')
    start = world.make_data("home").qpos[world.astrobee_qpos : world.astrobee_qpos + 3]
    assert not np.all((start >= 0) & (start <= 1))  # the test's own premise
    assert main([*safe, "--zones", str(tiny)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    where = "({:.2f}, {:.2f}, {:.2f}) m".format(*start)
    assert len(err) == 1 and f"the vehicle starts at {where}, outside" in err[0], err
    assert len(calls) == n  # no trial ran


def test_summary_aggregates_station_contacts():
    from payload.trials.summary import station_summary

    rows = [
        {
            "seed": 0,
            "station_contacts": 0,
            "min_station_clearance_mm": 120.0,
            "filter_active_s": 3.0,
            "base_filter": True,
        },
        {
            "seed": 1,
            "station_contacts": 4,
            "min_station_clearance_mm": 0.0,
            "filter_active_s": 5.0,
            "base_filter": True,
        },
        {"seed": 2, "error": "boom"},
    ]
    s = station_summary(rows)
    assert s["measured"] == 2 and s["trials_with_contacts"] == 1
    assert s["station_contacts"] == {"total": 4, "max": 4}
    assert s["min_station_clearance_mm"] == 0.0
    assert s["filter_active_s"] == {"median": 4.0, "max": 5.0}


def test_recording_carries_the_filter_channel_and_the_keepin_boxes(world, grasped_state, tmp_path):
    """A recorder with the safety scene: one JSON record per step on /safety/filter (what
    the filter and the station monitor said) and the keep-in boxes on /safety/keepin."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader

    from payload.trials.foxglove import FoxgloveScene
    from payload.trials.recorder import RecordingError, TrialRecorder
    from payload.trials.records import random_step
    from payload.trials.safety import FILTER_TOPIC, KEEPIN_TOPIC, SafetyScene, keepin_boxes

    sim = _driver(world, grasped_state, (1.6, 7.0, 0.25), (0.06, 0.0, 0.0))
    sim.twist_filter = _filter(sim)
    scene = SafetyScene(FoxgloveScene(world), sim)
    rng = np.random.default_rng(0)
    moving = _moving_geoms(world)
    measured, changes = [], []
    with TrialRecorder(tmp_path / "log.mcap", scene=scene) as rec:
        for k in range(60):  # past the recorder's first batch (it writes a second late)
            rot = sim.data.xmat[world.astrobee].reshape(3, 3)
            sim.command_twist(VehicleTwist(rot.T @ np.array([0.2, 0, 0]), np.zeros(3), 0.0))
            sim.step()
            measured.append(least_distance(sim, moving))
            changes.append(sim.twist_filter.status.change)
            scene.observe(0.02 * k)
            rec.write(random_step(rng, 0.02 * k))
        with pytest.raises(RecordingError, match=r"9 safety records .* \(flush the recorder"):
            scene.summary()  # the steps after the last flush (t = 1.0 s) are not counted yet
        rec.flush()
        with pytest.raises(RecordingError, match="not taken"):  # a step without its record
            rec.write(random_step(rng, 2.0))
            rec.flush()
    with open(tmp_path / "log.mcap", "rb") as f:
        msgs = list(make_reader(f).iter_messages(topics=[FILTER_TOPIC, KEEPIN_TOPIC]))
    records = [json.loads(m.data) for _, c, m in msgs if c.topic == FILTER_TOPIC]
    assert [r["t"] for r in records] == [0.02 * k for k in range(60)]
    assert all(r["active"] and r["constraints"] > 0 for r in records)
    # each step's own reading, taken at the step (mj_geomDistance, capped like the monitor)
    np.testing.assert_allclose([r["station_clearance_m"] for r in records], measured, atol=1e-9)
    assert [r["change_mps"] for r in records] == changes
    assert records[-1]["shape"] in ("astrobee", "payload", "ctb")
    boxes = [m for _, c, m in msgs if c.topic == KEEPIN_TOPIC]
    update = SceneUpdate.FromString(boxes[0].data)
    assert len(update.entities[0].cubes) == len(keepin_boxes(layout=world.layout)) == 3
    summary = scene.summary()
    cap = summary.pop("station_clearance_cap_mm")
    assert summary == {
        "station_contacts": 0,
        "min_station_clearance_mm": round(scene.least * 1e3, 1),
        "filter_active_s": 1.2,
    }
    # the cap bounds every step's recorded clearance (read back from the file), in mm
    assert 1e3 * max(r["station_clearance_m"] for r in records) <= cap < 1e4


def test_the_committed_sweeps_closest_run_flies_again(world, grasped_state):
    """analyses/filter_sweep.py's closest run (seed 12, analyses/safety-filter/sweep.md:
    24.6 mm, a full-rate turn), flown again by the script's own function from the report's
    rounded start: the same approach, no contact (the script runs, and the report is what
    it writes)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "analyses" / "filter_sweep.py"
    spec = importlib.util.spec_from_file_location("filter_sweep", path)
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    report = (path.parent / "safety-filter" / "sweep.md").read_text()
    row = "| 12 | node2 | [-0.695, -0.539, 0.291] | [0.59, -0.04, 0.81] | 0.041 | +0.1 | 24.6 |"
    assert row in report
    way = np.array([0.59, -0.04, 0.81])
    way /= np.linalg.norm(way)
    run = sweep.fly(world, grasped_state, np.array([-0.695, -0.539, 0.291]), 0.041 * way,
                    sweep.BASE.max_speed * way, sweep.BASE.max_yaw_rate)  # fmt: skip
    assert run is not None
    least, touching = run
    assert touching == 0 and abs(least - 0.0246) < 0.002, least


def test_zones_on_a_replay_without_the_filter_are_refused_before_any_folder(tmp_path):
    """A replay takes its recording's filter setting (off in a paper trial's), which the
    command line cannot see: the runner refuses the zones it would ignore, before it makes
    a folder (``payload trial --replay F --zones Z`` ran without a word)."""
    from payload.trials.runner import run_trial
    from payload.trials.sources import TrialError

    src = tmp_path / "src"
    run_trial(3, "synthetic", out_dir=src, max_time=1.0)  # a paper trial: no filter
    assert json.loads((src / "metrics.json").read_text())["base_filter"] is False
    out = tmp_path / "out"
    with pytest.raises(TrialError, match="the zones are the base filter's, and it is off"):
        run_trial(None, "replay", src / "log.mcap", out, zones=station_zones())
    assert not out.exists()
