"""The teleoperation pipeline end to end: calibration, finger/rail/base channels, safety,
replay reproducibility, and a synthetic operator flying the CTB in the simulator."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from payload.design import load_design
from payload.retarget.calibration import pair_range
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.errors import RetargetError
from payload.rotations import quat_to_matrix
from payload.schema import CONTROL_DT
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.hands import Hand, HandFrame
from payload.teleop.operator import OperatorPlan, OperatorTraits, SyntheticOperator, WorldView
from payload.teleop.pipeline import (
    TeleopConfig,
    TeleopPipeline,
    TeleopStep,
    calibrate_operator,
    human_features,
)
from payload.teleop.replay import HandRecordingWriter, read_hand_recording

DT = CONTROL_DT
TRAVEL = load_design().rail.travel


@pytest.fixture(scope="module")
def retargeting():
    rts = {p: PairRetargeter(pair=p) for p in ("L", "R")}
    ranges = {p: pair_range(rts[p].kinematics) for p in ("L", "R")}
    return rts, ranges


def _static_world(t: float) -> WorldView:
    return WorldView(t, np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3), False)


def _calibrated(seed: int, retargeting, traits: OperatorTraits | None = None):
    """Run the calibration prompts with a synthetic operator; return pipeline parts."""
    _rts, ranges = retargeting
    proc = CalibrationProcedure()
    plan = OperatorPlan(route=np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]))
    op = SyntheticOperator(plan, seed, proc, traits)
    frames = []
    t = 0.0
    while not proc.done:
        fr = op.act(_static_world(t))
        frames.append(fr)
        proc.step(fr)
        t += DT
    cal = calibrate_operator(proc.captures, ranges, TRAVEL)
    return op, proc, cal, frames, t


def _pipeline(cal, retargeting) -> TeleopPipeline:
    rts, _ = retargeting
    for r in rts.values():
        r.reset()
    return TeleopPipeline(cal, rts, TeleopConfig.from_design())


QUIET = OperatorTraits(tremor_amp=0.0, noise=0.0, dropout_rate=0.0, reaction=0.2)


def test_calibration_maps_pinch_and_open_to_the_robot_span_range(retargeting):
    _, proc, cal, _, _ = _calibrated(3, retargeting, QUIET)
    rts, ranges = retargeting
    for pair, side in (("L", "left"), ("R", "right")):
        pc = cal.pairs[pair]
        for gesture, expected in (
            ("pinch", ranges[pair].span_min),
            ("open", ranges[pair].span_max),
        ):
            hand = proc.captures.get(gesture, side)
            targets, q_ref = pc.command(human_features(hand))
            assert targets.span == pytest.approx(expected, abs=1e-3)
            # and the retargeter, warm-started over a few control steps, gets the robot there
            r = rts[pair]
            r.reset(q_ref)
            for _ in range(10):
                q, _ = r.solve(targets, q_ref=q_ref)
            assert r.features(q).span == pytest.approx(expected, abs=1e-3)


def test_rail_calibration_spans_the_travel(retargeting):
    _, _proc, cal, _, _ = _calibrated(4, retargeting, QUIET)
    assert cal.rail.d_min == pytest.approx(0.22, abs=0.01)
    assert cal.rail.d_max == pytest.approx(0.52, abs=0.01)


def _wrist_shift(frame: HandFrame, shift: np.ndarray) -> HandFrame:
    return HandFrame(
        frame.stamp,
        Hand(frame.left.joints + shift) if frame.left.tracked else frame.left,
        Hand(frame.right.joints + shift) if frame.right.tracked else frame.right,
    )


def test_dropout_brakes_holds_fingers_and_recovers_without_a_jump(retargeting):
    op, _, cal, _, t = _calibrated(5, retargeting, QUIET)
    pipe = _pipeline(cal, retargeting)
    push = np.array([0.15, 0.0, 0.0])  # both wrists forward, well outside the sphere
    outs = []
    for k in range(700):
        fr = _wrist_shift(op.act(_static_world(t)), push)
        if k == 500:
            op.aperture = 0.95  # the hand opens while the tracker has lost it
        if 500 <= k < 508:  # 160 ms without the left hand; the right one moves apart
            apart = np.array([0.0, -0.01 * (k - 499), 0.0])
            fr = HandFrame(fr.stamp, Hand.untracked(), Hand(fr.right.joints + apart))
        outs.append(pipe.step(fr))
        t += DT
    speed = np.array([np.linalg.norm(o.base.v_world) for o in outs])
    q_left = np.array([o.q_left for o in outs])
    rail = np.array([o.command.q[-1] for o in outs])
    assert speed[499] > 0.1  # flying before the dropout
    lost = [k for k, o in enumerate(outs) if any(e.kind == "lost" for e in o.events)]
    assert lost and 500 + 0.1 / DT <= lost[0] <= 500 + 0.1 / DT + 1
    k_lost = lost[0]
    # while lost the request is zero and the jerk-limited command starts braking: the
    # acceleration falls at every step; the left pair holds its command
    for o in outs[k_lost:508]:
        assert np.all(o.base.v_request == 0.0)
    accel = np.diff(speed) / DT
    assert np.all(np.diff(accel[k_lost - 1 : 507]) < 0)
    held = q_left[k_lost:508]
    assert np.all(held == held[0])
    assert np.all(rail[k_lost:508] == rail[k_lost])  # the rail holds too
    # base command stays smooth through loss and recovery: jerk bounded everywhere
    v = np.array([o.base.v_world for o in outs])
    jerk = np.diff(v, n=2, axis=0) / DT**2
    assert np.linalg.norm(jerk, axis=1).max() <= TeleopConfig.from_design().base.max_jerk + 1e-9
    # recovery: the left pair's command moves a long way (the hand opened meanwhile), but
    # blended over the recovery time instead of in one jump
    change = np.abs(q_left[560] - q_left[507]).max()
    biggest_step = np.abs(np.diff(q_left[507:560], axis=0)).max()
    assert change > 0.05
    assert biggest_step < 0.2 * change
    regained = [k for k, o in enumerate(outs) if any(e.kind == "regained" for e in o.events)]
    assert regained and regained[0] == 508


def test_nan_frame_is_rejected_and_nothing_jumps(retargeting):
    op, _, cal, _, t = _calibrated(6, retargeting, QUIET)
    pipe = _pipeline(cal, retargeting)
    last = None
    for k in range(60):
        fr = op.act(_static_world(t))
        if k == 40:
            bad = fr.left.joints.copy()
            bad[4, 0] = np.nan
            fr = HandFrame(fr.stamp, Hand(bad), fr.right)
        out = pipe.step(fr)
        if k == 40:
            assert {"invalid", "lost"} <= {e.kind for e in out.events}
            np.testing.assert_array_equal(out.q_left, last.q_left)
            assert np.all(out.base.v_request == 0.0)
        last = out
        t += DT


def test_replayed_recording_reproduces_the_command_stream_bit_for_bit(retargeting, tmp_path):
    op, _, _cal, frames, t = _calibrated(7, retargeting)
    for _ in range(250):
        frames.append(op.act(_static_world(t)))
        t += DT
    path = tmp_path / "hands.jsonl"
    with HandRecordingWriter(path) as w:
        for fr in frames:
            w.write(fr)
    _, replayed = read_hand_recording(path)

    def stream(source):
        proc = CalibrationProcedure()
        pipe = None
        out = []
        for fr in source:
            if not proc.done:
                proc.step(fr)
                if proc.done:
                    _, ranges = retargeting
                    pipe = _pipeline(calibrate_operator(proc.captures, ranges, TRAVEL), retargeting)
                continue
            s = pipe.step(fr)
            out.append(np.concatenate([s.command.q, s.twist.linear, s.twist.angular]))
        return np.array(out)

    live = stream(frames)
    again = stream(replayed)
    assert live.shape == again.shape and len(live) > 100
    assert np.array_equal(live, again)


def test_inside_the_sphere_the_vehicle_command_is_zero(retargeting):
    op, _, cal, _, t = _calibrated(8, retargeting, QUIET)
    pipe = _pipeline(cal, retargeting)
    for _ in range(100):
        out = pipe.step(op.act(_static_world(t)))
        t += DT
        assert np.all(out.twist.linear == 0.0) and np.all(out.twist.angular == 0.0)
        assert 0.0 <= out.rail <= TRAVEL


@pytest.mark.slow
def test_synthetic_operator_carries_the_ctb_through_a_turn_in_the_simulator():
    """Calibrate, acquire the CTB, fly >= 2 m with a turn; contact holds through the flight."""
    from payload.rotations import quat_to_matrix
    from payload.sim.driver import SimDriver
    from payload.teleop.loop import SyntheticSource, run_session
    from payload.trials import runner

    driver = SimDriver()
    # the converged budget: with the paper's 20 evaluations per pair solve this scripted
    # flight (seed 11, a turn after 2 m) loses opposing contact for a moment (issue 14)
    rts, ranges = runner.retargeting(budget="converged")
    runner.place_ctb_for_teleop(driver, rts, ranges)
    start = driver.world_state().astrobee_pos.copy()
    heading = driver.world.layout.start_yaw()
    fwd = np.array([math.cos(heading), math.sin(heading), 0.0])
    right = np.array([math.sin(heading), -math.cos(heading), 0.0])
    route = np.array([start, start + 2.0 * fwd, start + 2.6 * fwd + 0.5 * right])
    proc = CalibrationProcedure()
    op = SyntheticOperator(OperatorPlan(route=route, heading0=heading), 11, proc)
    q0 = driver.read().q

    def make(captures, h):
        return TeleopPipeline(calibrate_operator(captures, ranges, TRAVEL, h), rts, initial=q0)

    def view(st, t):
        rot = quat_to_matrix(st.astrobee_quat)
        return WorldView(
            t, st.astrobee_pos, rot, rot @ st.astrobee_linear, st.ctb_pos, st.opposing_contact
        )

    log = []

    def on_step(ctx):
        rot = quat_to_matrix(ctx.state.astrobee_quat)
        yaw = math.atan2(rot[1, 0], rot[0, 0])
        log.append((ctx.phase, ctx.state.opposing_contact, ctx.state.astrobee_pos.copy(), yaw))

    run_session(
        driver, SyntheticSource(op), proc, make, max_time=150, on_step=on_step, world_view=view
    )
    phases = np.array([p for p, *_ in log])
    contact = np.array([c for _, c, *_ in log])
    pos = np.array([p for *_, p, _ in log])
    yaw = np.array([y for *_, y in log])
    flying = np.isin(phases, ["translation", "turn", "braking"])
    assert flying.any()
    first, last = np.flatnonzero(flying)[[0, -1]]
    assert np.all(contact[first : last + 1]), "opposing contact lost during the flight"
    assert np.linalg.norm(pos[last] - pos[first]) >= 2.0
    turned = abs((yaw[last] - yaw[first] + math.pi) % (2 * math.pi) - math.pi)
    assert turned > math.radians(10)


def test_live_pacing_counts_overruns(retargeting):
    """With a live source the loop paces to the wall clock and counts late steps."""
    import time

    from payload.sim.driver import SimDriver
    from payload.teleop.loop import ReplaySource, run_session

    _, _, _, frames, _ = _calibrated(9, retargeting, QUIET)
    frames = frames[:30]  # still calibrating: the loop holds the payload
    driver = SimDriver()
    slow = ReplaySource(list(frames))
    t0 = time.perf_counter()
    stats = run_session(
        driver,
        slow,
        CalibrationProcedure(),
        lambda captures, heading: None,
        pace=True,
        on_step=lambda ctx: time.sleep(0.03),  # every step takes longer than 20 ms
    )
    assert stats.steps == 30
    assert stats.overruns == 30
    assert time.perf_counter() - t0 >= 30 * 0.03
    t1 = time.perf_counter()
    quick = run_session(
        driver, ReplaySource(list(frames)), CalibrationProcedure(), lambda c, h: None, pace=True
    )
    # paced: a 30-step session lasts at least its 0.6 s of control time
    assert quick.steps == 30
    assert time.perf_counter() - t1 >= 30 * 0.02 - 1e-3


def test_the_compiled_targets_are_numpys(retargeting, refused_kernel):
    """Both pairs' calibrated targets through the compiled kernel and through numpy's
    code on 2,000 random features (inside, below and beyond the calibrated spans): the
    same bits; a non-finite feature raises numpy's error; a kernel that forms the robot
    centre as pinch + alpha (open - pinch) (the same in exact arithmetic) is refused."""
    from payload.retarget import targets_c

    _, _proc, cal, _, _ = _calibrated(3, retargeting, QUIET)
    rng = np.random.default_rng(5)
    for pc in cal.pairs.values():
        assert pc._kernel is not None
        lo, hi = pc.human_pinch.span, pc.human_open.span
        for _ in range(1000):
            h = np.concatenate(
                [[rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo))], rng.normal(size=12)]
            )
            got, want = pc.to_targets(h), pc._to_targets_numpy(h)
            for g, w in zip(got, want):
                assert np.asarray(g).tobytes() == np.asarray(w).tobytes()
        h[5] = np.nan
        with pytest.raises(RetargetError) as numpy_error:
            pc._to_targets_numpy(h)
        with pytest.raises(RetargetError) as error:
            pc.to_targets(h)
        assert str(error.value) == str(numpy_error.value)
    pc = cal.pairs["L"]
    with refused_kernel(
        targets_c,
        "c_robot[i] = (1.0 - alpha) * c[4 + i] + alpha * c[7 + i];",
        "c_robot[i] = c[4 + i] + alpha * (c[7 + i] - c[4 + i]);",
    ):
        assert targets_c.compiled_targets(pc, pc._to_targets_numpy) is None


def test_the_operators_route_lengths_are_the_routes_remaining_length() -> None:
    """What the operator keeps of its plan: from each waypoint, the route's remaining
    length (against numpy's segment norms), and the wrists' centre and half span."""
    rng = np.random.default_rng(4)
    route = np.cumsum(rng.normal(size=(6, 3)), axis=0)
    left, right = np.array([0.3, 0.2, 1.0]), np.array([0.4, -0.1, 1.1])
    plan = OperatorPlan(
        route=route, heading0=0.7, rail_distance=0.3, neutral_left=left, neutral_right=right
    )
    op = SyntheticOperator(plan, 3, CalibrationProcedure())
    segments = np.linalg.norm(np.diff(route, axis=0), axis=1)
    for w in range(len(route)):
        assert op._route_left[w] == pytest.approx(segments[w:].sum(), rel=1e-12, abs=0.0)
    centre, half = op._posture
    np.testing.assert_allclose(centre + half, [0.35, 0.05 + 0.15, 1.05], rtol=1e-15)
    np.testing.assert_allclose(centre - half, [0.35, 0.05 - 0.15, 1.05], rtol=1e-15)
    forward = op._to_operator @ [math.cos(0.7), math.sin(0.7), 0.0]  # the operator's forward
    np.testing.assert_allclose(forward, [1.0, 0.0, 0.0], atol=1e-15)


def _solver_state(rt) -> list[bytes]:
    """A retargeter's held command and its compiled solver's inputs (the anchor among
    them), as bytes."""
    _, inputs = rt.step_entry()
    return [rt.held_command.tobytes(), *(a.tobytes() for a in inputs)]


def test_the_finger_chain_is_the_python_path(retargeting, refused_kernel):
    """Each pair's compiled finger chain (features, targets, posture, solve in one C call)
    against the pipeline's Python path, one call each, from the same solver state on 300
    random hands (degenerate and non-finite ones among them) and an operator's hands: the
    same command, report, held command and solver inputs in every bit, or both refuse (the
    chain then leaves the held command and the anchor as they were). A chain whose
    posture is interpolated as p0 + w (p1 - p0) (the same in exact arithmetic) is refused."""
    from payload.teleop import pair_c
    from payload.teleop.hand_c import random_hands
    from payload.teleop.pipeline import TRACKING_FAULTS

    op, _proc, cal, _, t = _calibrated(3, retargeting, QUIET)
    pipe = _pipeline(cal, retargeting)
    hands = list(random_hands(300, seed=11))
    for _ in range(60):
        fr = op.act(_static_world(t))
        hands += [fr.left.joints, fr.right.joints]
        t += DT
    solved = refused = 0
    for pair, rt in pipe.retargeters.items():
        chain = pipe._make_chain(pair)
        assert chain is not None
        for joints in hands:
            before, restore = _solver_state(rt), rt.checkpoint()
            try:
                want = pipe._finger_python(pair, Hand(joints, True))
            except TRACKING_FAULTS:
                want = None
            after_python = _solver_state(rt)
            restore()
            assert _solver_state(rt) == before  # every bit back, by the bytes taken before
            with np.errstate(all="ignore"):
                got = chain(joints)
            if want is None:
                assert got is None
                anchor = _solver_state(rt)[0:1] + _solver_state(rt)[4:]
                assert anchor == before[0:1] + before[4:]
                refused += 1
                continue
            solved += 1
            assert got[0].tobytes() == want[0].tobytes()
            assert repr(tuple(got[1])) == repr(tuple(want[1]))
            assert _solver_state(rt) == after_python
    assert solved > 300 and refused > 5
    with refused_kernel(
        pair_c,
        "c->r_in[j] = (1.0 - w) * p0[j] + w * p1[j];",
        "c->r_in[j] = p0[j] + w * (p1[j] - p0[j]);",
    ):
        assert pipe._make_chain("L") is None


def _set_chain(pipe: TeleopPipeline, pair: str, chain: Any) -> None:
    """Give ``pipe`` ``chain`` as pair ``pair``'s finger chain (None: the Python path), made
    for its calibration and retargeter as they are."""
    pipe._chains[pair] = (pipe.calibration.pairs[pair], pipe.retargeters[pair], chain)


def _count_intake(pipe: TeleopPipeline, taken: list[bool], steady: list | None = None) -> None:
    """Make ``pipe`` note in ``taken``, at each step, whether its compiled intake took the
    hands in (and in ``steady`` whether its call ran the channels too)."""
    step = pipe._intake_step

    def counted(frame, t, *rest):
        out = step(frame, t, *rest)
        taken.append(out is not None)
        if steady is not None:
            steady.append(isinstance(out, TeleopStep))
        return out

    pipe._intake_step = counted


def _channel_state(pipe: TeleopPipeline) -> list[bytes]:
    """What the channels keep between steps: each pair's held command and blend, the
    rail's blend, the base channel's limiters."""
    out = []
    for blend in (pipe.blend["L"], pipe.blend["R"], pipe.rail_blend):
        for a in (blend.held, blend._anchor):
            out.append(b"-" if a is None else np.asarray(a, float).tobytes())
    for pair in ("L", "R"):
        out.append(pipe.retargeters[pair].held_command.tobytes())
    for lim in (pipe.base.linear, pipe.base.yaw):
        out.append(np.asarray(lim.value, float).tobytes() + np.asarray(lim.rate, float).tobytes())
    return out


def test_a_pipeline_with_its_finger_chains_commands_as_one_without(retargeting):
    """Two pipelines on the same calibration and hands, one with its pairs' finger chains
    and one on the Python path alone: the same commands, twists and solve reports, bit for
    bit, step after step."""
    op, _, cal, _, t = _calibrated(9, retargeting)
    frames = []
    for _ in range(300):
        frames.append(op.act(_static_world(t)))
        t += DT

    taken = []

    def stream(chains: bool) -> list[bytes]:
        pipe = _pipeline(cal, retargeting)
        if not chains:
            for pair in ("L", "R"):
                _set_chain(pipe, pair, None)
        else:
            for pair in ("L", "R"):
                chain = pipe._make_chain(pair)
                assert chain is not None

                def counted(joints, chain=chain):
                    out = chain(joints)
                    taken.append(out is not None)
                    return out

                _set_chain(pipe, pair, counted)
        out = []
        for fr in frames:
            s = pipe.step(fr)
            out.append(s.command.q.tobytes() + s.twist.linear.tobytes())
            out.append(repr(sorted(s.solves.items())).encode())
        return out

    assert stream(True) == stream(False)
    assert sum(taken) > 400  # the chains solved (nearly) every step of both pairs


def test_the_compiled_hand_intake_steps_as_the_python_path(retargeting):
    """Two pipelines on the same calibration and hands, one taking the hands in through
    the compiled intake (:mod:`payload.teleop.intake_c`) and one on the Python path alone,
    over hands that drop out (bridged, then lost and blended back in), turn invalid (a NaN
    joint, a wrist jump), come back in time or repeat it, a hand that moved while the other
    was away, and a hand a pair's chain refuses: the same commands, twists, solve reports
    and safety events, and the same supervisor and filter state, bit for bit, step after
    step."""
    op, _, cal, _, t = _calibrated(9, retargeting)
    config = TeleopConfig.from_design()
    allowed = config.safety.max_wrist_speed * DT  # a step's move, at most
    base = config.base
    frames = []
    push_from, push_steps = 150, 40
    lost = range(120, 140)  # the steps the right hand is lost
    for k in range(420):
        fr = op.act(_static_world(t))
        left, right, stamp = fr.left, fr.right, t
        if k >= push_from:  # the left wrist pushed out of its sphere, then held: drive
            push = base.sphere_radius + base.full_speed_offset
            step = push * min(k - push_from + 1, push_steps) / push_steps
            left = Hand(left.joints + np.array([step, 0.0, 0.0]))
        if 60 <= k < 64:
            left = Hand.untracked()  # a dropout, bridged
        if k >= 60:  # meanwhile the right hand moves 0.6 of that a step, 3 times it in all
            moved = 0.6 * allowed * min(k - 59, 5)
            right = Hand(right.joints + np.array([moved, 0.0, 0.0]))
        if k in lost:
            right = Hand.untracked()  # lost, then blended back in
        if k == 200:
            joints = left.joints.copy()
            joints[3, 1] = np.nan
            left = Hand(joints)
        if k == 240:
            right = Hand(right.joints + np.array([3 * allowed, 0.0, 0.0]))  # the wrist jumps
        if k == 300:
            stamp = t - 2 * DT  # back in time
        if k == 301:
            stamp = frames[-2].stamp  # the same time again
        if k == 330:
            stamp = frames[-1].stamp  # the same time again, on a steady step
        frames.append(HandFrame(stamp, left, right))
        t += DT

    taken = []
    steady: list[bool] = []
    modes: list[str] = []
    seen = []
    fell_back = []
    rots = _rotations(len(frames), 3)  # the vehicle turning

    def stream(intake: bool) -> list[bytes]:
        pipe = _pipeline(cal, retargeting)
        if intake:
            _count_intake(pipe, taken, steady)
        else:
            pipe._intake_kernel = lambda: None
        python = pipe._finger_python

        def solved(pair, hand):
            fell_back.append((intake, k, pair))
            return python(pair, hand)

        pipe._finger_python = solved
        out = []
        for k, fr in enumerate(frames):
            chain = pipe._chain("R")
            if k == 350:  # pair R's chain refuses any hand (no thumb axis is that long)
                chain._chain.eps, eps = 1e9, chain._chain.eps
            s = pipe.step(fr, rots[k])
            if k == 350:
                chain._chain.eps = eps
            if intake:
                modes.append(s.base.mode)
            out += _record(s)
            out.append(repr(s.events).encode())
            out.append(s.q_left.tobytes() + s.q_right.tobytes() + repr(s.command.stamp).encode())
            b = s.base
            out.append(b.v_request.tobytes() + b.v_world.tobytes())
            out.append(repr((b.yaw_rate, b.outside, b.mode, b.twist.stamp)).encode())
            out += _channel_state(pipe)
            sup = pipe.supervisor
            out.append(repr(sup.last_stamp).encode())
            for side in ("left", "right"):
                st, f = sup.status[side], pipe.filters[side]
                kept = (st.last_valid_stamp, st.lost, st.lost_since, st.recovering_until)
                out.append(repr((*kept, st.was_invalid, f._t)).encode())
                out.append(b"-" if st.last_valid is None else st.last_valid.joints.tobytes())
                out.append(b"-" if f._x is None else f._x.tobytes() + f._dx.tobytes())
        if intake:
            seen.extend(pipe.events)
        return out

    assert stream(True) == stream(False)
    assert taken.count(True) > 300 and taken.count(False) > 20
    # the channels ran in the intake's call on most steps, the right hand's blend back in
    # among them (from the third step back to the end of the recovery time), with the base
    # channel in each of its modes
    blending = round(config.safety.recovery_time / DT)
    assert steady.count(True) > 250 and all(steady[lost.stop + 2 : lost.stop + blending])
    assert {m for m, fast in zip(modes, steady) if fast} == {"brake", "drive", "hold"}
    # every case above happened: each kind of event, and the refused chain at step 350
    kinds = {(e.hand, e.kind) for e in seen}
    assert {("left", "invalid"), ("right", "lost"), ("right", "regained")} <= kinds
    assert ("both", "time_backwards") in kinds
    # step 64: the right wrist 3 allowed moves from where the intake last took it in (step
    # 59), 0.6 of one from where the Python path took it last (step 63): valid, taken in
    assert taken[59] is taken[64] is True and not any(taken[60:64])
    assert not any(e.stamp == frames[64].stamp for e in seen)
    assert taken[330] is False  # the same time again: the Python path
    # step 350: taken in by the intake, the refused pair solved by the Python path
    assert taken[350] is True
    assert [f for f in fell_back if f[1] >= 340] == [(True, 350, "R"), (False, 350, "R")]


def test_the_compiled_rail_command_is_the_channels_on_any_wrists(retargeting):
    """The rail command the intake's tail computes (:meth:`HandIntake.rail_command`) is
    :func:`~payload.teleop.channels.rail_command`'s, bit for bit, on 3,000 random wrist
    pairs (inside the range, at its ends, beyond both), and both refuse a wrist that is
    not finite."""
    from payload.teleop.channels import ChannelError, rail_command

    op, _, cal, _, t = _calibrated(9, retargeting)
    pipe = _pipeline(cal, retargeting)
    for k in range(60):  # past the first commands' blend
        pipe.step(op.act(_static_world(t + k * DT)))
    intake = pipe._intake_kernel()
    assert intake is not None and pipe._tail is not None and pipe._tail[-1]
    rail = cal.rail
    rng = np.random.default_rng(11)
    for k in range(3000):
        left = rng.normal(scale=0.4, size=3)
        d = (rail.d_min, rail.d_max)[k % 2] if k < 40 else rng.uniform(0.0, 2 * rail.d_max)
        u = rng.normal(size=3)
        right = left + d * u / np.linalg.norm(u)
        want = rail_command(rail, left, right)
        assert np.float64(intake.rail_command(left, right)).tobytes() == np.float64(want).tobytes()
    bad = np.array([0.1, np.inf, 0.0])
    with pytest.raises(ChannelError):
        rail_command(rail, np.zeros(3), bad)
    assert intake.rail_command(np.zeros(3), bad) is None


def _rotations(n: int, seed: int) -> list[np.ndarray]:
    """``n`` random vehicle rotations, as the loop hands the pipeline its vehicle's."""
    quats = np.random.default_rng(seed).normal(size=(n, 4))
    return [quat_to_matrix(q / np.linalg.norm(q)) for q in quats]


def _record(s: TeleopStep) -> list[bytes]:
    """A step's commands, twist, rail, solve reports and base mode, as bytes."""
    return [
        s.command.q.tobytes() + s.twist.linear.tobytes() + s.twist.angular.tobytes(),
        repr((s.rail, sorted(s.solves.items()), s.base.mode)).encode(),
    ]


def _tail_stream(cal, retargeting, frames, rots, tail: bool, before=None):
    """A pipeline's steps over ``frames`` (with the vehicle rotations ``rots``), its
    channels in the intake's call where they can be (``tail``) or always in Python: per
    step its commands, twists, rail, solve reports, base mode and channel states, and
    whether the intake took the step's hands in and whether its channels ran compiled.
    ``before(pipe, k)`` runs before step k."""
    pipe = _pipeline(cal, retargeting)
    if not tail:
        pipe._tail_ready = lambda *args: False
    taken: list[bool] = []
    steady: list[bool] = []
    _count_intake(pipe, taken, steady)
    out = []
    for k, fr in enumerate(frames):
        if before is not None:
            before(pipe, k)
        out += _record(pipe.step(fr, rots[k])) + _channel_state(pipe)
    return out, taken, steady


def _operator_frames(retargeting, n: int):
    """A calibration and ``n`` frames of its operator after it, with ``n`` random vehicle
    rotations."""
    op, _, cal, _, t = _calibrated(9, retargeting)
    frames = [op.act(_static_world(t + k * DT)) for k in range(n)]
    return cal, frames, _rotations(n, 4)


def test_a_tail_that_refuses_after_the_intake_leaves_the_step_to_python(retargeting):
    """When the channels' C refuses after the intake already took the hands in (here: a
    pair's solved command read as not finite on every third step, by pointing the tail at
    an array of NaN), nothing it keeps has changed and the Python path makes the step
    from the intake's results: the same commands, twists and channel states as a pipeline
    whose channels always run in Python, bit for bit."""
    cal, frames, rots = _operator_frames(retargeting, 150)
    nans = {}

    def refuse(pipe, k):
        intake = pipe._intake
        bound = None if intake is None else intake[1]._tail
        if bound is not None:  # the left hand's pair's command, as the C reads it
            real = pipe.retargeters["L"].step_output
            nan = nans.setdefault(id(real), np.full_like(real, np.nan))
            bound.fresh0 = (nan if k % 3 == 0 else real).ctypes.data

    refused, _, steady = _tail_stream(cal, retargeting, frames, rots, True, refuse)
    assert refused == _tail_stream(cal, retargeting, frames, rots, False)[0]
    fast = [k for k, f in enumerate(steady) if f]
    assert len(fast) > 60 and all(k % 3 for k in fast)  # every third step refused


def test_a_tail_that_cannot_be_bound_leaves_the_channels_to_python(retargeting):
    """Rail settings that are not floats (integers pass the calibration's checks) are
    not taken by the intake's tail: every step's channels run in Python, and the commands
    and twists are those of a pipeline that never tried, bit for bit."""
    cal, frames, rots = _operator_frames(retargeting, 120)
    ints = dataclasses.replace(cal, rail=dataclasses.replace(cal.rail, d_min=0, travel=1))
    tried, taken, steady = _tail_stream(ints, retargeting, frames, rots, True)
    assert not any(steady) and _tail_stream(ints, retargeting, frames, rots, False)[0] == tried
    assert sum(taken) > 100  # the intake took the hands in all the same
    # the same with float settings: the channels run compiled on most steps
    assert sum(_tail_stream(cal, retargeting, frames, rots, True)[2]) > 100


def test_a_calibration_or_retargeter_replaced_mid_session_is_followed_as_in_python(retargeting):
    """``calibration`` and ``retargeters`` are the pipeline's public parts: one replaced
    between steps (another operator's calibration, a fresh retargeter for a pair) is what
    the next steps use, through the compiled chains and intake as on the Python path alone,
    bit for bit (the chains bind the calibration's and the retargeter's buffers, so they
    are made again for the new ones)."""
    rts, _ = retargeting
    op, _, cal_a, _, t = _calibrated(9, retargeting)
    _, _, cal_b, _, _ = _calibrated(4, retargeting)
    frames = []
    for _ in range(90):
        frames.append(op.act(_static_world(t)))
        t += DT
    taken: list[bool] = []

    def stream(compiled: bool, swap: bool) -> list[bytes]:
        for r in rts.values():
            r.reset()
        pipe = TeleopPipeline(cal_a, dict(rts), TeleopConfig.from_design())
        if compiled:
            _count_intake(pipe, taken)
        else:
            pipe._intake_kernel = lambda: None
            for pair in ("L", "R"):
                _set_chain(pipe, pair, None)
        out = []
        for k, fr in enumerate(frames):
            if swap and k == 30:
                pipe.calibration = cal_b
            if swap and k == 60:
                fresh = PairRetargeter(pair="L")
                fresh.reset(pipe.retargeters["L"].held_command)
                pipe.retargeters["L"] = fresh
            if not compiled and k in (30, 60):
                for pair in ("L", "R"):
                    _set_chain(pipe, pair, None)  # the Python path stays the Python path
            s = pipe.step(fr)
            out.append(s.command.q.tobytes() + repr(sorted(s.solves.items())).encode())
        return out

    python = stream(False, True)
    compiled = stream(True, True)
    assert compiled == python
    assert sum(taken[-25:]) >= 20  # the compiled intake ran again after both swaps
    assert stream(True, False)[31:] != python[31:]  # the swaps changed the commands


def test_calibrations_ranges_and_plans_keep_their_arrays_to_themselves(retargeting):
    """The arrays a compiled kernel copies or reads in place when it is made (a pair
    calibration's rotation and features, a pair range's table and features, an operator
    plan's route and wrists) are read-only copies: a write would reach the Python path and
    not the kernel, or the other way round, so it raises; the arrays they were made from
    stay the caller's to write."""
    _, _, cal, _, _ = _calibrated(9, retargeting)
    pair = cal.pairs["L"]
    arrays = [pair.rotation, pair.human_pinch.centre, pair.human_open.direction]
    arrays += [pair.range.spans, pair.range.postures, pair.range.pinch.distal]
    route = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    plan = OperatorPlan(route=route, grasp_body=np.zeros(3))
    arrays += [plan.route, plan.neutral_left, plan.grasp_body]
    for a in arrays:
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 1.0
    rotation = pair.rotation.copy()
    again = dataclasses.replace(pair, rotation=rotation)
    rotation[0, 0], route[1, 0] = 2.0, 6.0  # the caller's, still writeable
    assert again.rotation[0, 0] == pair.rotation[0, 0] and plan.route[1, 0] == 5.0


def test_a_refused_calibration_says_what_the_operator_did(retargeting):
    """A calibration whose wrists did not move apart for 'apart', or whose hand did not
    open for 'open', is refused in the operator's terms (the distances they held, what to
    do), not the channel's ("open distance 0.418 m must exceed closed distance 0.418 m"),
    the restart reason the live page shows."""
    from payload.teleop.calibration import CalibrationError

    _, proc, _, _, _ = _calibrated(3, retargeting, QUIET)
    _, ranges = retargeting
    hands = {step: dict(sides) for step, sides in proc.captures.hands.items()}
    same = type(proc.captures)({**hands, "apart": hands["together"]})
    gap = np.linalg.norm(hands["together"]["left"][0] - hands["together"]["right"][0])
    with pytest.raises(CalibrationError) as info:
        calibrate_operator(same, ranges, TRAVEL)
    cm = f"{100 * gap:.1f} cm"  # the wrists' distance (joint 0 of each hand), both times
    assert str(info.value) == (
        f"calibration 'together'/'apart': the wrists were {cm} apart for 'apart' and {cm} "
        "for 'together': hold them wider apart for 'apart'"
    )
    closed = type(proc.captures)(
        {**hands, "open": {**hands["open"], "left": hands["pinch"]["left"]}}
    )
    with pytest.raises(CalibrationError) as info:
        calibrate_operator(closed, ranges, TRAVEL)
    said = str(info.value)
    assert said.startswith("calibration of the left hand: its thumb and index were "), said
    assert said.endswith("open them wide for 'open' and pinch them for 'pinch'"), said
