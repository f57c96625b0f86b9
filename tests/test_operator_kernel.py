"""The synthetic operator's compiled flight steps (payload.teleop.operator_c) against its
Python, and the synthetic headset's frames drawn on the grid by the operator."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from payload.rotations import yaw_matrix
from payload.teleop import operator as operator_mod
from payload.teleop import operator_c
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.channels import BaseConfig
from payload.teleop.loop import SyntheticSource
from payload.teleop.operator import OperatorPlan, SyntheticOperator, WorldView
from payload.trials.jointcodec import HAND_GRID_M, quantize_joints
from payload.trials.sources import HeadsetSource

ROUTE = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 2.5, 0.2]])


def _kernel() -> operator_c.CompiledAct:
    kernel = operator_c.compiled_act(operator_mod._check_operators, operator_mod._check_view)
    assert kernel is not None  # a compiler is here
    return kernel


def _fly(monkeypatch: pytest.MonkeyPatch, compiled: bool, grid: float | None) -> tuple:
    """An operator past calibration, grasping at once, flying ROUTE in a kinematic world
    (the vehicle goes where the operator's left wrist pushes, turning toward it, and stops
    at the end) until it finishes: every frame's hands and the operator's state at every
    step, and how many steps the kernel took."""
    if not compiled:
        monkeypatch.setattr(operator_mod, "compiled_act", lambda *args: None)
    op = SyntheticOperator(OperatorPlan(route=ROUTE, heading0=0.3), 5, CalibrationProcedure())
    op.phase = "acquisition"  # past calibration; no grasp point: it closes at once
    taken = 0
    if op._compiled_act is not None:
        step = op._compiled_act

        def counted(*args: object) -> object:
            nonlocal taken
            hands = step(*args)
            taken += hands is not None
            return hands

        op._compiled_act = counted
    pos, yaw, vel = np.zeros(3), 0.0, np.zeros(3)
    out = []
    centre = 0.5 * (op.plan.neutral_left + op.plan.neutral_right)
    for k in range(4000):
        t = 5.0 + 0.02 * k
        fr = op.act(WorldView(t, pos.copy(), yaw_matrix(yaw), vel.copy(), pos + 0.4, True), grid)
        out.append([h.joints.tobytes() if h.tracked else None for h in (fr.left, fr.right)])
        out.append((op.phase, op.waypoint, op.stopped_since, op.finished, op.aperture))
        out.append(op.wrist["left"].tobytes() + op.wrist["right"].tobytes())
        if op.finished:
            break
        push = yaw_matrix(op.plan.heading0) @ (op.wrist["left"] - centre - [0, 0.17, 0])
        want = 1.5 * push if np.linalg.norm(push) > 0.06 else np.zeros(3)
        vel = vel + 0.2 * (want - vel)
        pos = pos + 0.02 * vel
        if np.linalg.norm(want[:2]) > 1e-3:
            yaw += 0.1 * (math.atan2(want[1], want[0]) - yaw)
    return out, taken, op.rng.bit_generator.state


@pytest.mark.parametrize("grid", [None, HAND_GRID_M])
def test_the_compiled_operator_is_pythons(monkeypatch, grid):
    """An operator that grasps, flies a three-waypoint route, turns, arrives and brakes
    with the kernel draws the same hands (every joint's bits, the same hands lost), wrists,
    aperture and state at every step, and leaves its generator in the same state, as the
    same operator in Python; the kernel took most of the steps."""
    compiled, taken, state = _fly(monkeypatch, True, grid)
    python, none, python_state = _fly(monkeypatch, False, grid)
    assert none == 0
    assert compiled == python
    assert state == python_state
    states = [item for item in python if isinstance(item, tuple)]
    assert {"translation", "turn", "braking"} <= {s[0] for s in states}
    assert states[-1][3]  # it finished: at rest for two seconds at the end
    assert taken > 0.8 * len(states)
    hands = [h for item in python if isinstance(item, list) for h in item]
    assert None in hands  # the tracker lost a hand at times
    if grid is not None:  # on the grid: integers times the grid, as the headset rounds
        joints = np.frombuffer(next(h for h in hands if h is not None)).reshape(25, 3)
        assert np.array_equal(joints, quantize_joints(joints, grid))


def test_the_self_check_reaches_every_phase_and_event():
    """The self-check's operators and views reach every flight phase, advance waypoints,
    start the stop timer and finish, lose hands and find them again, on every grid; the
    kernel agrees with the Python at each step."""
    kernel = _kernel()
    seen: set = set()
    for k in range(operator_c.CHECK_OPERATORS):
        mine, theirs = operator_mod._check_operators(k)
        step = kernel.stepper(mine)
        rng = np.random.default_rng(7 + k)
        for i in range(600):
            if i % 200 == 0:
                for op in (mine, theirs):
                    op.phase, op.waypoint = "translation", 0
            t = 1.0 + 0.02 * i
            view = operator_mod._check_view(mine, rng, i, t)
            grid = operator_c.CHECK_GRIDS[i % len(operator_c.CHECK_GRIDS)]
            before = (mine.phase, mine.waypoint, mine.stopped_since, mine.finished)
            hands = step(t, 0.02, view, grid)
            assert hands is not None
            want = theirs._act_numpy(t, 0.02, view, grid)
            assert operator_c._same(mine, theirs) and operator_c._same_hands(hands, want)
            after = (mine.phase, mine.waypoint, mine.stopped_since, mine.finished)
            seen.add((before[0], after[0]))
            seen.add("advanced" if after[1] > before[1] else "")
            seen.add("stopped" if before[2] is None and after[2] is not None else "")
            seen.add("finished" if after[3] and not before[3] else "")
            seen.add(("lost", grid) if any(h is None for h in hands) else ("drawn", grid))
    assert {("translation", "turn"), ("turn", "translation"), ("turn", "braking")} <= seen
    assert {"advanced", "stopped", "finished"} <= seen
    assert {(what, g) for what in ("lost", "drawn") for g in operator_c.CHECK_GRIDS} <= seen


def test_what_the_kernel_does_not_take_goes_to_python():
    """The acquisition, an operator whose plan or hand model was replaced, a grid that is
    not a positive float, a wrist of another type and a trembling wrist the held hand
    leaves to numpy (an infinite tremor) run the Python: the step says None and changes
    nothing (not the wrist arrays either), nothing drawn."""
    kernel = _kernel()
    op, _ = operator_mod._check_operators(2)
    step = kernel.stepper(op)
    view = operator_mod._check_view(op, np.random.default_rng(0), 1, 3.0)
    wrists = (op.wrist["left"], op.wrist["right"])

    def state() -> tuple:
        return (op.phase, op.waypoint, op.aperture, op.stopped_since, op.finished,
                dict(op._dropout_until), op.wrist["left"].tobytes(),
                op.rng.bit_generator.state)  # fmt: skip

    before = state()
    for grid in (0.0, -1e-5, 1):
        assert step(3.0, 0.02, view, grid) is None
    op.phase = "acquisition"
    assert step(3.0, 0.02, view, None) is None
    op.phase = before[0]
    plan, models = op.plan, op.models["left"]
    op.plan = OperatorPlan(route=plan.route.copy())
    assert step(3.0, 0.02, view, None) is None
    op.plan = plan
    op.models["left"] = dataclasses.replace(models)
    assert step(3.0, 0.02, view, None) is None
    op.models["left"] = models
    op.wrist["left"] = wrists[0].astype(np.float32)
    assert step(3.0, 0.02, view, None) is None
    op.wrist["left"] = wrists[0]
    assert state() == before
    assert op.wrist["left"] is wrists[0] and op.wrist["right"] is wrists[1]
    shaky, _ = operator_mod._check_operators(2)
    shaky.traits = dataclasses.replace(shaky.traits, tremor_amp=math.inf)
    drawn = shaky.rng.bit_generator.state
    assert kernel.stepper(shaky)(3.0, 0.02, view, None) is None
    assert shaky.rng.bit_generator.state == drawn


@pytest.mark.parametrize(
    ("traits", "plan", "error"),
    [
        ({"wrist_lag": 0.0}, {}, ZeroDivisionError),
        ({"noise": -0.0}, {}, ValueError),
        ({}, {"brake_accel": -0.001}, ValueError),
        ({}, {"base": BaseConfig(max_speed=0.0)}, ZeroDivisionError),
    ],
)
def test_settings_the_python_refuses_are_not_compiled(traits, plan, error):
    """An operator whose Python raises at a flight step (a zero arm lag or top speed, a
    negative braking or noise) gets no compiled step, and its Python raises as before
    (translating 3 m short of the route's end, both hands in view)."""
    op, _ = operator_mod._check_operators(0)
    op.traits = dataclasses.replace(op.traits, **traits)
    op.plan = dataclasses.replace(op.plan, **plan)
    assert _kernel().stepper(op) is None
    op.phase, op.waypoint = "translation", len(op.plan.route) - 1
    op._dropout_until = {"left": -1.0, "right": -1.0}
    pos = op.plan.route[-1] + [3.0, 0.0, 0.0]
    with pytest.raises(error):
        op._act_numpy(5.0, 0.02, WorldView(5.0, pos, np.eye(3), np.zeros(3), pos, True), None)


def test_the_kernel_follows_what_the_operator_is_told_between_steps(monkeypatch):
    """State set on the operator between two compiled steps (it is told it has not
    finished, it is put back on the first waypoint, its grip is released, it loses a hand
    until later) is what the next compiled step starts from, as the Python's does."""
    pair = operator_mod._check_operators(3)
    steps = [_kernel().stepper(op) for op in pair]
    rng = np.random.default_rng(5)
    for i in range(400):
        t = 2.0 + 0.02 * i
        view = operator_mod._check_view(pair[0], rng, i, t)
        got = steps[0](t, 0.02, view, None)
        want = pair[1]._act_numpy(t, 0.02, view, None)
        assert got is not None
        assert operator_c._same(*pair) and operator_c._same_hands(got, want)
        for op in pair:
            if i % 10 == 9:  # alone: nothing else tells the kernel to look again
                op.finished = False
            if i % 50 == 49:
                op.waypoint = 0
                op.phase = "translation"
                op.grip_aperture = None if i % 100 == 49 else 0.01
                op._dropout_until["right"] = t + 0.1
    assert pair[0].finished is pair[1].finished


def test_the_headset_draws_the_operators_hands_on_its_grid():
    """The synthetic headset's frames (the operator drawing them on the grid) are the
    operator's frames rounded to the grid afterwards, step by step, in every phase."""
    plan = OperatorPlan(route=ROUTE)
    a = SyntheticOperator(plan, 9, CalibrationProcedure())
    b = SyntheticOperator(plan, 9, CalibrationProcedure())
    headset = HeadsetSource(SyntheticSource(a), HAND_GRID_M)
    for op in (a, b):
        op.phase = "translation"
    for k in range(300):
        t = 0.02 * k
        view = WorldView(
            t, np.array([0.01 * k, 0.0, 0.0]), np.eye(3), np.zeros(3), np.zeros(3), True
        )
        got, want = headset.frame(t, view), b.act(view)
        for g, w in ((got.left, want.left), (got.right, want.right)):
            assert g.tracked == w.tracked
            if w.tracked:
                assert g.joints.tobytes() == quantize_joints(w.joints, HAND_GRID_M).tobytes()


def test_an_operator_kernel_with_other_bits_is_refused(refused_kernel):
    """A wrist lag written as (1 - k) w + k i (the same in exact arithmetic) is refused."""
    with refused_kernel(
        operator_c,
        "wl[k] = wrists[0][k] + kw * (il - wrists[0][k]);",
        "wl[k] = (1.0 - kw) * wrists[0][k] + kw * il;",
        forget=operator_c.compiled_act,
    ):
        kernel = operator_c.compiled_act(operator_mod._check_operators, operator_mod._check_view)
        assert kernel is None
