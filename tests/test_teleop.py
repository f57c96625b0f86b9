"""Teleoperation pipeline pieces: hands, filters, replay, rail and base channels, safety."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from conftest import ROOT
from hypothesis import given, settings
from hypothesis import strategies as st

from payload.design import vehicle as design_vehicle
from payload.sim import vehicle as sim_vehicle
from payload.teleop.channels import (
    BaseChannel,
    BaseCommand,
    BaseConfig,
    ChannelError,
    JerkLimiter,
    RailConfig,
    rail_command,
)
from payload.teleop.filters import OneEuroConfig, OneEuroFilter
from payload.teleop.handmodel import HandModel
from payload.teleop.hands import (
    WEBXR_TO_WORKBENCH,
    XR_JOINTS,
    Hand,
    HandFrame,
    HandFrameError,
    pinch_points,
    wrist_frame,
)
from payload.teleop.replay import HandRecordingWriter, ReplayError, read_hand_recording
from payload.teleop.safety import Blender, TrackingSupervisor

DT = 0.02

# ---------------------------------------------------------------- hands


def test_xr_joint_list_is_the_webxr_25():
    assert len(XR_JOINTS) == 25
    assert XR_JOINTS[0] == "wrist" and XR_JOINTS[4] == "thumb-tip"
    assert XR_JOINTS[-1] == "pinky-finger-tip"


def test_webxr_to_workbench_maps_axes():
    # WebXR: -Z forward, +Y up, +X right; workbench: +X forward, +Z up, +Y left
    r = WEBXR_TO_WORKBENCH
    np.testing.assert_allclose(r @ [0, 0, -1], [1, 0, 0])
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, 1])
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0])
    assert np.linalg.det(r) == pytest.approx(1.0)
    joints = np.random.default_rng(0).normal(size=(25, 3))
    frame = HandFrame(1.0, Hand(joints), Hand(joints), frame="webxr").to_workbench()
    np.testing.assert_allclose(frame.left.joints[:, 0], -joints[:, 2])
    np.testing.assert_allclose(frame.left.joints[:, 2], joints[:, 1])


def test_bad_hand_input_is_rejected():
    with pytest.raises(HandFrameError, match="shape"):
        Hand(np.zeros((24, 3)))
    with pytest.raises(HandFrameError, match="shape"):
        Hand.taking(np.zeros((len(XR_JOINTS) - 1, 3)))
    for stamp in (float("nan"), float("inf"), np.float32("nan"), np.float64("-inf")):
        with pytest.raises(HandFrameError, match="not finite"):
            HandFrame(stamp, Hand.untracked(), Hand.untracked())


def test_a_hand_taking_its_joints_is_the_constructors():
    """``Hand.taking`` keeps an array of the caller's own (frozen, not copied) and copies
    anything else as the constructor does: the same joints either way."""
    rng = np.random.default_rng(2)
    n = len(XR_JOINTS)
    own = rng.normal(size=(n, 3))
    want = own.copy()
    taken = Hand.taking(own, tracked=False)
    assert taken.joints is own and not own.flags.writeable
    assert taken.joints.tobytes() == want.tobytes() and taken.tracked is False
    assert taken.orientations is None
    assert repr(taken) == repr(Hand(want, False))
    bigger = rng.normal(size=(2 * n, 3))
    for other in (bigger[:n], bigger[::2], want.astype(np.float32), want.tolist(), own):
        hand = Hand.taking(other)  # a view, strided, float32, a list, read-only: copied
        assert hand.joints is not other and not hand.joints.flags.writeable
        assert hand.joints.tobytes() == np.asarray(other, dtype=np.float64).tobytes()


def test_wrist_frame_recovers_a_known_rotation():
    model = HandModel("right")
    rng = np.random.default_rng(1)
    for _ in range(5):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        if np.linalg.det(q) < 0:
            q[:, 0] *= -1
        wrist = rng.normal(size=3)
        hand = Hand(model.joints(wrist, q, 0.5))
        local = Hand(model.local_joints(0.5))
        frame_world = wrist_frame(hand)
        frame_local = wrist_frame(local)
        # the frame is attached to the hand: world frame = q * local frame
        np.testing.assert_allclose(frame_world[:3, :3], q @ frame_local[:3, :3], atol=1e-12)
        p_world = pinch_points(hand, frame_world)
        p_local = pinch_points(local, frame_local)
        for key in p_world:
            np.testing.assert_allclose(p_world[key], p_local[key], atol=1e-12)


def test_hand_model_pinch_opens_monotonically():
    for side in ("left", "right"):
        spans = []
        for s in np.linspace(0, 1, 11):
            hand = Hand(HandModel(side).local_joints(s))
            p = pinch_points(hand)
            spans.append(np.linalg.norm(p["p2"] - p["p1"]))
        assert np.all(np.diff(spans) > 0)
        assert spans[0] < 0.025 and spans[-1] > 0.08


# ---------------------------------------------------------------- One Euro filter


def test_one_euro_with_zero_beta_is_the_closed_form_low_pass():
    cfg = OneEuroConfig(min_cutoff=2.0, beta=0.0, d_cutoff=1.0)
    f = OneEuroFilter(cfg)
    f(np.zeros(3), 0.0)
    tau = 1 / (2 * math.pi * 2.0)
    alpha = 1 / (1 + tau / DT)
    y = np.zeros(3)
    for k in range(1, 50):
        out = f(np.ones(3), k * DT)
        y = alpha * 1.0 + (1 - alpha) * y
        np.testing.assert_allclose(out, y, rtol=1e-12)
    # the step response of the discrete first-order filter: 1 - (1 - alpha)^k
    assert out[0] == pytest.approx(1 - (1 - alpha) ** 49, rel=1e-12)


def test_one_euro_lags_less_when_moving_fast():
    slow = OneEuroFilter(OneEuroConfig(min_cutoff=1.0, beta=0.0))
    fast = OneEuroFilter(OneEuroConfig(min_cutoff=1.0, beta=5.0))
    errs = {"slow": 0.0, "fast": 0.0}
    for k in range(100):
        x = np.array([[0.3 * k * DT, 0.0, 0.0]])
        errs["slow"] = abs(slow(x, k * DT)[0, 0] - x[0, 0])
        errs["fast"] = abs(fast(x, k * DT)[0, 0] - x[0, 0])
    assert errs["fast"] < 0.5 * errs["slow"]


# ---------------------------------------------------------------- replay


def test_replay_round_trips_bit_for_bit(tmp_path):
    rng = np.random.default_rng(2)
    frames = []
    for k in range(30):
        left = Hand(rng.normal(size=(25, 3))) if k % 7 else Hand.untracked()
        frames.append(
            HandFrame(k * DT + rng.uniform(0, 1e-3), left, Hand(rng.normal(size=(25, 3))))
        )
    path = tmp_path / "hands.jsonl"
    with HandRecordingWriter(path, meta={"operator": "test"}) as w:
        for fr in frames:
            w.write(fr)
    header, back = read_hand_recording(path)
    assert header["meta"] == {"operator": "test"}
    assert len(back) == len(frames)
    for a, b in zip(frames, back):
        assert a.stamp == b.stamp
        assert a.left.tracked == b.left.tracked
        np.testing.assert_array_equal(a.right.joints, b.right.joints)
        if a.left.tracked:
            np.testing.assert_array_equal(a.left.joints, b.left.joints)


def test_replay_names_the_bad_line(tmp_path):
    path = tmp_path / "bad.jsonl"
    with HandRecordingWriter(path) as w:
        w.write(HandFrame(0.0, Hand(np.zeros((25, 3))), Hand(np.zeros((25, 3)))))
    with path.open("a") as fh:
        fh.write('{"t": 0.02, "left": {"tracked": true, "joints": [[0, 0, 0]]}, "right": null}\n')
    with pytest.raises(ReplayError, match=r"bad.jsonl:3"):
        read_hand_recording(path)
    with pytest.raises(ReplayError, match="cannot read"):
        read_hand_recording(tmp_path / "missing.jsonl")


# ---------------------------------------------------------------- rail channel


@given(st.lists(st.floats(0.0, 1.5), min_size=2, max_size=50))
def test_rail_stays_in_travel_and_is_monotonic(distances):
    cfg = RailConfig(d_min=0.25, d_max=0.65, travel=0.05)
    ds = sorted(distances)
    rails = [rail_command(cfg, np.zeros(3), np.array([d, 0.0, 0.0])) for d in ds]
    assert all(0.0 <= r <= 0.05 for r in rails)
    assert np.all(np.diff(rails) >= 0)


def test_rail_calibration_endpoints_map_to_the_travel_ends():
    cfg = RailConfig(d_min=0.25, d_max=0.65, travel=0.05)
    assert rail_command(cfg, np.zeros(3), np.array([0.0, 0.25, 0.0])) == 0.0
    assert rail_command(cfg, np.zeros(3), np.array([0.0, 0.65, 0.0])) == pytest.approx(0.05)
    assert rail_command(cfg, np.zeros(3), np.array([0.0, 0.45, 0.0])) == pytest.approx(0.025)
    with pytest.raises(ChannelError, match="must exceed"):
        RailConfig(d_min=0.5, d_max=0.4, travel=0.05)


# ---------------------------------------------------------------- base channel

wrist_paths = st.lists(
    st.tuples(
        st.floats(-0.4, 0.4), st.floats(-0.4, 0.4), st.floats(-0.4, 0.4), st.integers(1, 400)
    ),
    min_size=1,
    max_size=12,
)


def test_base_channel_speed_and_acceleration_are_the_nominal_flight_modes():
    """One source: the simulator's flight-mode table, whose figures docs/sources.md cites."""
    text = (ROOT / "docs" / "sources.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| flight modes |"))
    m = re.search(r"nominal ([0-9.]+) m/s, ([0-9.]+) m/s\^2", row)
    assert m is not None
    cfg = BaseConfig()
    assert (cfg.max_speed, cfg.max_accel) == (float(m.group(1)), float(m.group(2)))
    nominal = sim_vehicle.FLIGHT_MODES[sim_vehicle.DEFAULT_FLIGHT_MODE]
    assert (cfg.max_speed, cfg.max_accel) == (nominal.speed, nominal.accel)
    assert sim_vehicle.FLIGHT_MODES is design_vehicle.FLIGHT_MODES  # one table


@settings(max_examples=150, deadline=None)
@given(wrist_paths, st.floats(-math.pi, math.pi))
def test_base_channel_respects_speed_acceleration_and_jerk_bounds(path, heading):
    cfg = BaseConfig()
    ch = BaseChannel(cfg, np.array([0.3, 0.2, 1.0]), heading0=heading, dt=DT)
    v, w = [np.zeros(3)], [0.0]
    rots, body = [], []
    yaw = heading
    for x, y, z, steps in path:
        wrist = np.array([0.3 + x, 0.2 + y, 1.0 + z])
        for _ in range(steps):
            c, s = math.cos(yaw), math.sin(yaw)
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            out = ch.step(wrist, rot)
            yaw += out.yaw_rate * DT
            v.append(out.v_world)
            w.append(out.yaw_rate)
            rots.append(rot)
            body.append(out.twist.linear)
    v, w = np.array(v), np.array(w)
    # the body twist is the world command seen from the vehicle
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rots, body), v[1:], atol=1e-12)
    if len(v) < 3:
        return
    acc = np.diff(v, axis=0) / DT
    jerk = np.diff(acc, axis=0) / DT
    eps = 1e-9
    assert np.linalg.norm(v, axis=1).max() <= cfg.max_speed + eps
    assert np.linalg.norm(acc, axis=1).max() <= cfg.max_accel + eps
    assert np.linalg.norm(jerk, axis=1).max() <= cfg.max_jerk + eps
    assert np.abs(w).max() <= cfg.max_yaw_rate + eps
    assert np.abs(np.diff(w) / DT).max() <= cfg.max_yaw_accel + eps


@given(st.floats(0.0, 0.0499), st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5))
def test_inside_the_sphere_the_command_is_zero(radius, az, el):
    cfg = BaseConfig(sphere_radius=0.05)
    neutral = np.array([0.1, -0.2, 0.9])
    ch = BaseChannel(cfg, neutral)
    direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    for _ in range(20):
        out = ch.step(neutral + radius * direction)
        assert not out.outside
        np.testing.assert_array_equal(out.v_world, np.zeros(3))
        assert out.yaw_rate == 0.0


def test_base_reaches_full_speed_in_the_closed_form_time_and_brakes_to_rest():
    cfg = BaseConfig()
    ch = BaseChannel(cfg, np.zeros(3))
    far = np.array([1.0, 0.0, 0.0])  # straight ahead: no turning
    speeds = [float(np.linalg.norm(ch.step(far).v_world)) for _ in range(1000)]
    # a jerk-limited ramp cannot be faster than t = v/a + a/j; the limiter lands a little
    # conservatively (it starts easing off the acceleration early)
    t_closed = cfg.max_speed / cfg.max_accel + cfg.max_accel / cfg.max_jerk
    t_reach = (np.argmax(np.array(speeds) > cfg.max_speed * 0.999) + 1) * DT
    assert t_closed - 0.05 <= t_reach <= t_closed + 0.5
    for _ in range(1000):
        out = ch.step(np.zeros(3))
    np.testing.assert_array_equal(out.v_world, np.zeros(3))


def test_vehicle_turns_toward_the_requested_direction():
    ch = BaseChannel(BaseConfig(), np.zeros(3))
    yaw = 0.0
    for _ in range(3000):
        rot = np.array(
            [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
        )
        out = ch.step(np.array([0.0, 0.5, 0.0]), rot)  # left wrist to the left: travel +y
        yaw += out.yaw_rate * DT
    assert yaw == pytest.approx(math.pi / 2, abs=0.02)


def test_jerk_limiter_settles_exactly():
    lim = JerkLimiter(1, 0.1, 0.2)
    for _ in range(2000):
        out = lim.step(np.array([0.37]), DT)
    assert out[0] == 0.37


# ---------------------------------------------------------------- safety


def _frame(t: float, left: Hand | None = None, right: Hand | None = None) -> HandFrame:
    h = Hand(HandModel("right").local_joints(0.5))
    return HandFrame(t, left or h, right or h)


def test_dropout_over_100ms_is_lost_and_recovery_blends():
    sup = TrackingSupervisor()
    t = 0.0
    first = sup.step(_frame(t))
    # the first acquisition blends in like a recovery: no jump at the start of control
    assert first.blend_left == 0.0 and [e.kind for e in first.events] == ["acquired"] * 2
    for _ in range(30):
        t += DT
        out = sup.step(_frame(t))
    t += DT
    assert out.left is not None and out.blend_left == 1.0
    lost_at = None
    for k in range(8):  # 160 ms of dropout on the left hand
        out = sup.step(_frame(t, left=Hand.untracked()))
        if out.left is None and lost_at is None:
            lost_at = k
        t += DT
    # lost at the first frame more than 100 ms after the last valid one (t0 + 120 ms)
    assert lost_at == 5
    assert out.right is not None
    kinds = [e.kind for e in sup.events if e.kind != "acquired"]
    assert kinds == ["invalid", "lost"]
    blends = []
    for _ in range(40):
        out = sup.step(_frame(t))
        blends.append(out.blend_left)
        t += DT
    assert blends[0] == pytest.approx(0.0, abs=1e-12) and blends[-1] == 1.0
    assert np.all(np.diff(blends) >= 0) and np.max(np.diff(blends)) <= DT / 0.5 + 1e-9
    assert [e.kind for e in sup.events][-1] == "regained"


def test_short_dropout_is_bridged_with_the_last_valid_hand():
    sup = TrackingSupervisor()
    sup.step(_frame(0.0))
    out = sup.step(_frame(0.02, left=Hand.untracked()))
    assert out.left is not None  # 20 ms < 100 ms: still the last valid hand


def test_absurd_frames_and_backwards_time_are_rejected():
    sup = TrackingSupervisor(neutral={"left": np.zeros(3), "right": np.zeros(3)})
    sup.step(_frame(0.0))
    far = Hand(HandModel("right").local_joints(0.5) + np.array([5.0, 0.0, 0.0]))
    out = sup.step(_frame(0.02, left=far))
    assert [e.kind for e in out.events] == ["invalid", "lost"]
    assert "from neutral" in out.events[0].detail and out.left is None
    stretched = HandModel("right").local_joints(0.5)
    stretched[4] += 2.0
    out = sup.step(_frame(0.04, right=Hand(stretched)))
    right_events = [e for e in out.events if e.hand == "right"]
    assert "from the wrist" in right_events[0].detail and out.right is None
    sup.step(_frame(0.01))
    assert "time_backwards" in [e.kind for e in sup.events[-3:]]


def test_blender_holds_then_ramps():
    b = Blender()
    assert np.all(b.step(np.ones(2), 1.0) == 1.0)
    assert np.all(b.step(None, 0.0) == 1.0)
    mid = b.step(np.full(2, 3.0), 0.5)
    np.testing.assert_allclose(mid, [2.0, 2.0])
    np.testing.assert_allclose(b.step(np.full(2, 3.0), 1.0), [3.0, 3.0])


def test_blender_keeps_its_anchor_across_a_refused_step_mid_recovery():
    """Recovering from 0 toward a fresh 1, one step without a fresh command (the pair's
    solve refused) holds; the blend then goes on along the line from the command held at
    its start: (1 - w) * 0 + w * 1 = w, each step moving by the weight's own increase
    (before, the refused step became a new anchor and the next step jumped by 0.27)."""
    b = Blender(np.zeros(1))
    b.step(None, 0.0)  # lost: holding 0
    weights = [0.1, 0.3, 0.5, None, 0.54, 0.7, 0.9, 1.0]
    out, w_prev = [], 0.0
    for w in weights:
        q = b.step(None if w is None else np.ones(1), 0.5 if w is None else w)
        out.append(float(q[0]))
        if w is not None:
            assert abs(out[-1] - w) < 1e-12
            assert abs(out[-1] - (out[-2] if len(out) > 1 else 0.0)) <= w - w_prev + 1e-12
            w_prev = w
    assert out[3] == out[2]  # the refused step held


# -- braking: the paper's rule (both wrists back in neutral) ------------------------------
def _cruise(ch: BaseChannel, left: np.ndarray | None, right: np.ndarray, steps: int) -> BaseCommand:
    out = None
    for _ in range(steps):
        out = ch.step(left, None, right)
    assert out is not None
    return out


def test_both_wrists_back_in_neutral_brake_to_rest():
    cfg = BaseConfig()
    nl, nr = np.array([0.35, 0.17, 1.05]), np.array([0.35, -0.17, 1.05])
    ch = BaseChannel(cfg, nl, neutral_right=nr)
    ahead = np.array([0.2, 0.0, 0.0])  # both wrists forward together
    out = _cruise(ch, nl + ahead, nr + ahead, 800)
    assert out.mode == "drive" and np.linalg.norm(out.v_world) > 0.5 * cfg.max_speed
    out = _cruise(ch, nl, nr, 2000)
    assert out.mode == "brake"
    np.testing.assert_array_equal(out.v_world, np.zeros(3))


def test_left_wrist_outside_sets_the_direction_whatever_the_right_does():
    cfg = BaseConfig()
    nl, nr = np.zeros(3), np.array([0.0, -0.34, 0.0])
    a = BaseChannel(cfg, nl, neutral_right=nr)
    b = BaseChannel(cfg, nl, neutral_right=nr)
    left = np.array([0.0, 0.0, 0.3])  # up
    for _ in range(300):
        oa = a.step(left, None, nr)  # right in neutral
        ob = b.step(left, None, nr + np.array([0.3, 0.0, 0.0]))  # right pushed forward
    assert oa.mode == ob.mode == "drive"
    np.testing.assert_array_equal(oa.v_world, ob.v_world)
    assert oa.v_world[2] > 0 and abs(oa.v_world[0]) < 1e-12 and abs(oa.v_world[1]) < 1e-12


def test_only_the_right_wrist_outside_holds_the_velocity():
    """Documented behaviour: left back in neutral, right still out -> no braking, no
    acceleration: the commanded velocity holds (after the acceleration eases off)."""
    cfg = BaseConfig()
    nl, nr = np.array([0.35, 0.17, 1.05]), np.array([0.35, -0.17, 1.05])
    ch = BaseChannel(cfg, nl, neutral_right=nr)
    ahead = np.array([0.2, 0.0, 0.0])
    _cruise(ch, nl + ahead, nr + ahead, 400)  # still accelerating
    out = _cruise(ch, nl, nr + ahead, 1)
    v0 = float(np.linalg.norm(out.v_world))
    out = _cruise(ch, nl, nr + ahead, 1500)
    assert out.mode == "hold" and not out.outside
    v1 = float(np.linalg.norm(out.v_world))
    # the acceleration under way is eased off at the jerk bound: a^2 / (2 j) more speed
    assert v0 < v1 <= v0 + cfg.max_accel**2 / (2 * cfg.max_jerk) + 1e-9
    speeds = [float(np.linalg.norm(_cruise(ch, nl, nr + ahead, 1).v_world)) for _ in range(200)]
    assert max(speeds) - min(speeds) < 1e-12  # held
    out = _cruise(ch, nl, nr, 2000)  # right wrist back too: brake
    assert out.mode == "brake"
    np.testing.assert_array_equal(out.v_world, np.zeros(3))
    # at rest, the right wrist alone does not start the vehicle
    out = _cruise(ch, nl, nr + ahead, 200)
    assert out.mode == "hold"
    np.testing.assert_array_equal(out.v_world, np.zeros(3))


def test_a_lost_hand_brakes_even_with_the_right_wrist_outside():
    cfg = BaseConfig()
    ch = BaseChannel(cfg, np.zeros(3), neutral_right=np.array([0.0, -0.3, 0.0]))
    _cruise(ch, np.array([0.3, 0.0, 0.0]), np.array([0.3, -0.3, 0.0]), 600)
    out = _cruise(ch, None, np.array([0.3, -0.3, 0.0]), 3000)
    assert out.mode == "brake"
    np.testing.assert_array_equal(out.v_world, np.zeros(3))


@pytest.mark.parametrize("max_value", [None, 0.1])
def test_one_dimensional_limiter_gives_the_vector_limiters_bits(max_value):
    """The scalar path of a one-dimensional limiter against the general numpy path:
    random targets (jumps, holds, sign changes, beyond the cap), every value and rate
    bit for bit."""
    rng = np.random.default_rng(7)
    fast = JerkLimiter(1, 0.02, 0.02, max_value)
    ref = JerkLimiter(1, 0.02, 0.02, max_value)
    target = np.zeros(1)
    for k in range(3000):
        if k % 40 == 0:
            target = rng.uniform(-0.3, 0.3, 1) * rng.choice([0.0, 1.0, 3.0])
        out = fast.step(target, 0.02)
        expect = ref._step_vector(target, 0.02)
        assert out.tobytes() == expect.tobytes(), k
        assert fast.rate.tobytes() == np.asarray(ref.rate, float).tobytes(), k


def test_the_base_twist_carries_the_step_stamp_in_both_steps():
    """The stamp given to the step is the twist's (the compiled step and numpy's alike),
    and the twist is the body-frame one of the world velocity and yaw rate."""
    cfg = BaseConfig()
    nl = np.array([0.35, 0.17, 1.05])
    compiled, python = BaseChannel(cfg, nl), BaseChannel(cfg, nl)
    python.__dict__["_compiled_step"] = None  # numpy's step
    assert compiled._compiled_step is not None  # a compiler and numpy's OpenBLAS are here
    yaw = 0.4
    rot = np.array(
        [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
    )
    for k in range(120):
        stamp = 3.0 + 0.02 * k
        a = compiled.step(nl + np.array([0.2, 0.05, 0.0]), rot, None, stamp)
        b = python.step(nl + np.array([0.2, 0.05, 0.0]), rot, None, stamp)
        assert a.twist.stamp == b.twist.stamp == stamp
        assert a.twist.linear.tobytes() == b.twist.linear.tobytes()
        # body frame: the world velocity rotated back by the vehicle's heading
        np.testing.assert_allclose(rot @ a.twist.linear, a.v_world, atol=1e-15)
        np.testing.assert_allclose(a.twist.angular, [0.0, 0.0, a.yaw_rate], atol=1e-15)
    assert compiled.step(nl, rot, None).twist.stamp == 0.0  # the default
