"""The synthetic operator: a closed-loop virtual person producing hand frames.

It watches the (simulated) vehicle as a real operator watches through the headset, with a
reaction delay, and acts in phases: it follows the calibration prompts; it acquires the
CTB: it looks where the handle is relative to where its pinch closes (late by its
reaction delay, with a seeded misjudgement and frame-to-frame noise), flies the vehicle
slowly to line the handle up, brakes, waits for the vehicle to settle, and flexes both
pinches onto the handle until it sees opposing contact (if the pinch closes on nothing it
re-opens and tries again, and gives up after its last attempt: the trial then fails);
then it flies the route with its left wrist (both wrists move together so the rail
holds), slows into the turn, arrives, and returns both wrists to neutral to brake.
Seeded human variability: hand size, physiological tremor (a few mm at 8 to 12 Hz),
reaction delay, speed preference, small tracking noise, short tracking dropouts, how well
it judges the handle's position and how slowly it creeps while lining up.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from payload.rotations import quat_to_matrix, yaw_matrix
from payload.schema import CONTROL_DT
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.channels import BaseConfig
from payload.teleop.handmodel import HandModel, held_hand
from payload.teleop.hands import JOINTS_SHAPE, Hand, HandFrame, round_to_grid
from payload.teleop.operator_c import compiled_act
from payload.teleop.operator_layout import (
    AIMLESS_M,
    ARRIVAL_M,
    DROPOUT_S,
    FLIGHT_PHASES,
    PINCH_LAG_S,
    REACH_MARGIN_M,
    REST_S,
    REST_SPEED,
    STOP_SHORT_M,
    TURN_ABOVE_RAD,
)
from payload.vecmath import norm, read_only


@dataclass(frozen=True)
class WorldView:
    """What the operator sees at one instant (world frame).

    Attributes:
        t: Time [s].
        astrobee_pos: Vehicle position, shape (3,) [m].
        astrobee_rot: Vehicle body -> world rotation, shape (3, 3).
        astrobee_vel: Vehicle linear velocity (world), shape (3,) [m/s].
        ctb_pos: CTB position, shape (3,) [m].
        contact: The opposing-contact indicator.
        handle_body: Where the CTB's handle centre is, in the vehicle body frame, shape
            (3,) [m] (what a person sees of the handle against the robot); None if not
            visible.
    """

    t: float
    astrobee_pos: np.ndarray
    astrobee_rot: np.ndarray
    astrobee_vel: np.ndarray
    ctb_pos: np.ndarray
    contact: bool
    handle_body: np.ndarray | None = None


@dataclass(frozen=True)
class OperatorTraits:
    """Seeded human variability.

    Attributes:
        hand_size: Hand scale (1 = medium adult).
        tremor_amp: Tremor amplitude per axis [m].
        tremor_freq: Tremor frequency [Hz].
        reaction: Reaction delay [s].
        speed_pref: Fraction of full speed the operator likes to fly at.
        noise: Tracking noise per joint (standard deviation) [m].
        dropout_rate: Tracking dropouts per second (each 30 to 80 ms).
        squeeze: How far past the aperture at which it saw contact the operator closes the
            pinch (aperture units).
        close_rate: How fast the operator closes its pinch onto the handle [1/s].
        grip: The most open aperture the operator holds a firm grip at.
        wrist_lag: Time constant of the operator's arm moving to where it intends [s].
        judge_error: Standard deviation of the operator's fixed misjudgement of the
            handle's position, per axis [m] (depth perception through the headset).
        look_noise: Frame-to-frame noise of its reading of the handle's position [m].
        creep_speed: Speed it lines the vehicle up at [m/s] (fine positioning).
        align_tol: Misalignment it accepts before closing [m].
        attempts: Closing attempts before it gives up.
    """

    hand_size: float = 1.0
    tremor_amp: float = 0.002
    tremor_freq: float = 10.0
    reaction: float = 0.25
    speed_pref: float = 0.85
    noise: float = 0.0008
    dropout_rate: float = 0.05
    squeeze: float = 0.12
    close_rate: float = 0.25
    grip: float = 0.02
    wrist_lag: float = 0.3
    judge_error: float = 0.003
    look_noise: float = 0.002
    creep_speed: float = 0.01
    align_tol: float = 0.005
    attempts: int = 2

    @staticmethod
    def sample(rng: np.random.Generator) -> OperatorTraits:
        base = OperatorTraits._sample_base(rng)
        return OperatorTraits(
            **{
                **vars(base),
                "judge_error": float(rng.uniform(0.001, 0.005)),
                "look_noise": float(rng.uniform(0.001, 0.003)),
                "creep_speed": float(rng.uniform(0.006, 0.015)),
                "align_tol": float(rng.uniform(0.003, 0.008)),
            }
        )

    @staticmethod
    def _sample_base(rng: np.random.Generator) -> OperatorTraits:
        return OperatorTraits(
            hand_size=float(rng.uniform(0.9, 1.1)),
            tremor_amp=float(rng.uniform(0.001, 0.003)),
            tremor_freq=float(rng.uniform(8.0, 12.0)),
            reaction=float(rng.uniform(0.18, 0.35)),
            speed_pref=float(rng.uniform(0.7, 1.0)),
            noise=float(rng.uniform(0.0005, 0.0012)),
            dropout_rate=float(rng.uniform(0.02, 0.08)),
            squeeze=float(rng.uniform(0.08, 0.16)),
            close_rate=float(rng.uniform(0.18, 0.32)),
            grip=float(rng.uniform(0.0, 0.04)),
            wrist_lag=float(rng.uniform(0.2, 0.4)),
        )


@dataclass(frozen=True)
class OperatorPlan:
    """Where the operator works and what the task is.

    Attributes:
        route: World waypoints the vehicle should pass, shape (K, 3) [m]; the last one is
            the arrival point.
        neutral_left: Neutral left-wrist position in the operator frame [m].
        neutral_right: Neutral right-wrist position [m].
        base: The base channel's settings (sphere radius, full-speed offset, top speed),
            which the operator knows from practice.
        brake_accel: Deceleration the operator plans with [m/s^2]: what practice teaches
            about the loaded vehicle (Astrobee's torque bound limits a 26 kg stack with the
            CTB hanging below it to about 0.0026 m/s^2 fore-aft).
        corner_speed: Speed the operator slows to at a turn waypoint [m/s].
        waypoint_radius: Distance at which a waypoint counts as passed [m].
        rail_distance: Inter-wrist distance held during the task [m].
        heading0: World yaw of the operator's forward direction [rad].
        grasp_body: Where its calibrated pinch closes, in the vehicle body frame, shape
            (3,) [m] (learnt in practice); None: the handle is assumed there already and
            the operator closes at once.
    """

    route: np.ndarray
    neutral_left: np.ndarray = field(default_factory=lambda: np.array([0.35, 0.17, 1.05]))
    neutral_right: np.ndarray = field(default_factory=lambda: np.array([0.35, -0.17, 1.05]))
    base: BaseConfig = field(default_factory=BaseConfig)
    brake_accel: float = 0.002
    corner_speed: float = 0.04
    waypoint_radius: float = 0.35
    rail_distance: float = 0.34
    heading0: float = 0.0
    grasp_body: np.ndarray | None = None

    def __post_init__(self) -> None:
        # read-only copies: the compiled flight step copies the route and reads the rest
        # when it is made, the Python reads them at every step
        for name in ("route", "neutral_left", "neutral_right", "grasp_body"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, read_only(value))


class SyntheticOperator:
    """A closed-loop virtual operator (see the module docstring).

    Args:
        plan: Route and working posture.
        seed: Seed of every random choice (traits, tremor phases, noise, dropouts).
        calibration: The calibration procedure whose prompts the operator follows.
        traits: Override the sampled traits.
    """

    def __init__(
        self,
        plan: OperatorPlan,
        seed: int,
        calibration: CalibrationProcedure,
        traits: OperatorTraits | None = None,
    ) -> None:
        self.rng = np.random.default_rng(seed)
        self.traits = traits or OperatorTraits.sample(self.rng)
        self.plan = plan
        self.calibration = calibration
        tr = self.traits
        self.models = {
            "left": HandModel("left", tr.hand_size),
            "right": HandModel("right", tr.hand_size),
        }
        self.phases = {s: self.rng.uniform(0, 2 * math.pi, size=3) for s in ("left", "right")}
        self.wrist = {"left": plan.neutral_left.copy(), "right": plan.neutral_right.copy()}
        self.aperture = 0.5
        self.phase = "calibration"
        self.waypoint = 0
        self.grip_aperture: float | None = None
        self.contact_seen_at: float | None = None
        self.stopped_since: float | None = None
        self.finished = False
        self._seen: deque[WorldView] = deque()
        self._dropout_until = {"left": -1.0, "right": -1.0}
        self._last_t: float | None = None
        # acquisition: approach -> settle -> close (-> reopen -> approach ...), or gave_up
        self.acquisition = "approach" if plan.grasp_body is not None else "close"
        self.attempt = 1
        self._since = 0.0
        self._misjudge = self.rng.normal(0.0, self.traits.judge_error, size=3)

    # ------------------------------------------------------------------ perception
    def _perceive(self, world: WorldView) -> WorldView:
        """The world as the operator sees it: ``reaction`` seconds late."""
        self._seen.append(world)
        while len(self._seen) > 1 and self._seen[1].t <= world.t - self.traits.reaction:
            self._seen.popleft()
        return self._seen[0]

    # ------------------------------------------------------------------ intentions
    def _calibration_intent(self, t: float) -> tuple[dict[str, np.ndarray], float]:
        p = self.plan
        step = self.calibration.step_at(t - self.traits.reaction)
        name = step.name if step is not None else "release"
        left, right = p.neutral_left.copy(), p.neutral_right.copy()
        aperture = 0.5
        if name == "pinch":
            aperture = 0.0
        elif name == "open":
            aperture = 1.0
        elif name in ("together", "apart"):
            centre = 0.5 * (left + right)
            half = 0.5 * (0.22 if name == "together" else 0.52)
            offset = np.array([0.0, half, 0.0])
            left, right = centre + offset, centre - offset
        return {"left": left, "right": right}, aperture

    def _misalignment(self, seen: WorldView) -> np.ndarray | None:
        """How far (world frame) the vehicle must move to put the handle where the pinch
        closes, as the operator judges it; None when it cannot see the handle."""
        if self.plan.grasp_body is None or seen.handle_body is None:
            return None
        look = self.rng.normal(0.0, self.traits.look_noise, size=3)
        judged = np.asarray(seen.handle_body) + self._misjudge + look
        return seen.astrobee_rot @ (judged - self.plan.grasp_body)

    def _creep(self, error: np.ndarray) -> np.ndarray:
        """Wrist offset (operator frame) that creeps the vehicle toward ``error``."""
        p, tr = self.plan, self.traits
        dist = float(norm(error))
        speed = min(tr.creep_speed, math.sqrt(2 * p.brake_accel * max(0.0, dist - tr.align_tol)))
        if speed <= 1e-4:
            return np.zeros(3)
        direction = self._to_operator @ (error / dist)
        margin = tr.tremor_amp + 0.002  # far enough out that tremor keeps it outside
        return direction * (
            p.base.sphere_radius + margin + p.base.full_speed_offset * speed / p.base.max_speed
        )

    def _acquire(self, t: float, seen: WorldView) -> tuple[np.ndarray, float]:
        """The acquisition: returns the wrist offset and the aperture."""
        tr = self.traits
        state = self.acquisition
        offset = np.zeros(3)
        speed = float(norm(seen.astrobee_vel))
        if state in ("approach", "settle"):
            error = self._misalignment(seen)
            far = error is not None and float(norm(error)) > tr.align_tol
            if state == "approach" and far:
                offset = self._creep(error)
            elif state == "approach":
                self.acquisition, self._since = "settle", t
            elif far and float(norm(error)) > 2 * tr.align_tol:
                self.acquisition = "approach"  # drifted off while settling
            elif speed < 0.002 and t - self._since > 1.5:
                self.acquisition, self._since = "close", t
            return offset, 0.5
        if state == "close":
            if seen.contact and self.contact_seen_at is None:
                # contact seen: squeeze firmly, nearly to a full pinch
                self.contact_seen_at = t
                self.grip_aperture = max(0.0, min(self.aperture - tr.squeeze, tr.grip))
            if self.grip_aperture is not None:
                if t - self.contact_seen_at > 2.0:
                    self.phase = "translation"
                return offset, self.grip_aperture
            aperture = max(0.0, self.aperture - tr.close_rate * CONTROL_DT)
            if self.aperture > 0.02:
                self._since = t
            elif t - self._since > 1.5:  # closed on nothing: open up and try again
                self.acquisition, self._since = "reopen", t
            return offset, aperture
        if state == "reopen":
            if self.attempt >= tr.attempts:
                self.acquisition = "gave_up"
                self.finished = True
            elif t - self._since > 2.0:
                self.attempt += 1
                self.acquisition = "approach"
            return offset, 0.5
        return offset, 0.5  # gave up: hands at rest

    @functools.cached_property
    def _posture(self) -> tuple[np.ndarray, np.ndarray]:
        """The wrists' centre and half their separation (the plan is frozen)."""
        p = self.plan
        return 0.5 * (p.neutral_left + p.neutral_right), np.array([0.0, 0.5 * p.rail_distance, 0.0])

    @functools.cached_property
    def _route_left(self) -> list[float]:
        """Per waypoint, the route's length from it to the arrival point [m], summed as the
        task summed it at each step (segment by segment from zero)."""
        route = self.plan.route
        return [
            sum(float(norm(route[k + 1] - route[k])) for k in range(w, len(route) - 1))
            for w in range(len(route))
        ]

    @functools.cached_property
    def _to_operator(self) -> np.ndarray:
        """World -> operator frame rotation (the transpose of the operator's yaw)."""
        return yaw_matrix(self.plan.heading0).T

    def _task_intent(self, t: float, seen: WorldView) -> tuple[dict[str, np.ndarray], float]:
        p, tr = self.plan, self.traits
        centre, half = self._posture
        offset = np.zeros(3)
        if self.phase == "acquisition":
            offset, aperture = self._acquire(t, seen)
            return {"left": centre + half + offset, "right": centre - half + offset}, aperture
        aperture = self.grip_aperture if self.grip_aperture is not None else self.aperture
        route = p.route
        pos = seen.astrobee_pos
        # advance along the route
        while self.waypoint < len(route) - 1 and (
            norm(route[self.waypoint] - pos) < p.waypoint_radius
        ):
            self.waypoint += 1
        target = route[self.waypoint]
        to_target = target - pos
        dist = float(norm(to_target))
        last = self.waypoint == len(route) - 1
        if self.phase in ("translation", "turn"):
            remaining = dist + self._route_left[self.waypoint]
            stop_speed = math.sqrt(2 * p.brake_accel * max(0.0, remaining - STOP_SHORT_M))
            corner = (
                p.base.max_speed
                if last
                else math.sqrt(
                    p.corner_speed**2 + 2 * p.brake_accel * max(0.0, dist - p.waypoint_radius)
                )
            )
            speed = min(p.base.max_speed * tr.speed_pref, stop_speed, corner)
            heading = math.atan2(seen.astrobee_rot[1, 0], seen.astrobee_rot[0, 0])
            desired = math.atan2(to_target[1], to_target[0])
            err = abs((desired - heading + math.pi) % (2 * math.pi) - math.pi)
            self.phase = "turn" if err > TURN_ABOVE_RAD else "translation"
            if last and remaining < ARRIVAL_M:
                self.phase = "arrival"
            if dist > AIMLESS_M and self.phase != "arrival":
                direction = self._to_operator @ (to_target / dist)
                reach = (
                    p.base.sphere_radius
                    + REACH_MARGIN_M
                    + p.base.full_speed_offset * speed / p.base.max_speed
                )
                offset = direction * reach
        if self.phase in ("arrival", "braking"):
            speed_now = float(norm(seen.astrobee_vel))
            self.phase = "braking"
            if speed_now < REST_SPEED:
                self.stopped_since = self.stopped_since if self.stopped_since else t
                if t - self.stopped_since > REST_S:
                    self.finished = True
            else:
                self.stopped_since = None
        return {"left": centre + half + offset, "right": centre - half + offset}, aperture

    # ------------------------------------------------------------------ output
    def act(self, world: WorldView, grid: float | None = None) -> HandFrame:
        """The operator's hands at ``world.t``, given what it has seen until then; with a
        ``grid`` [m], as a headset reporting on that grid gives them (each joint position
        rounded to it: :func:`~payload.teleop.hands.round_to_grid`)."""
        t = world.t
        dt = CONTROL_DT if self._last_t is None else max(1e-3, t - self._last_t)
        self._last_t = t
        seen = self._perceive(world)
        step = self._compiled_act if self.phase in FLIGHT_PHASES else None
        joints = step(t, dt, seen, grid) if step is not None else None
        if joints is None:
            joints = self._act_numpy(t, dt, seen, grid)
        left, right = (Hand.untracked() if j is None else Hand.taking(j) for j in joints)
        return HandFrame(t, left, right)  # each hand's array its own: kept, not copied

    def _act_numpy(
        self, t: float, dt: float, seen: WorldView, grid: float | None = None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """:meth:`act` after the perception, in Python (what the compiled flight steps
        are checked against, :mod:`payload.teleop.operator_c`): the intent, the arm's lags
        and each hand's joints, on the ``grid`` if one is given (None: lost this step)."""
        if self.phase == "calibration":
            intent, aperture = self._calibration_intent(t)
            if self.calibration.done and t - self.reaction_end() > 0:
                self.phase = "acquisition"
        else:
            intent, aperture = self._task_intent(t, seen)
        tr = self.traits
        k = 1.0 - math.exp(-dt / tr.wrist_lag)
        for side in ("left", "right"):
            self.wrist[side] = self.wrist[side] + k * (intent[side] - self.wrist[side])
        self.aperture += (1.0 - math.exp(-dt / PINCH_LAG_S)) * (aperture - self.aperture)
        hands: list[np.ndarray | None] = []
        for side in ("left", "right"):
            if t < self._dropout_until[side]:
                hands.append(None)
                continue
            if self.rng.random() < tr.dropout_rate * dt:
                self._dropout_until[side] = t + self.rng.uniform(*DROPOUT_S)
                hands.append(None)
                continue
            noise = self.rng.normal(0.0, tr.noise, size=JOINTS_SHAPE)
            arg = 2 * math.pi * tr.tremor_freq * t
            model, phases = self.models[side], self.phases[side]
            joints = held_hand(
                model, self.wrist[side], tr.tremor_amp, arg, phases, self.aperture, noise
            )
            hands.append(joints if grid is None else round_to_grid(joints, grid))
        return hands[0], hands[1]

    @functools.cached_property
    def _compiled_act(self) -> Callable[..., Any] | None:
        """:meth:`_act_numpy` in the flight phases, compiled for this operator, or None."""
        kernel = compiled_act(_check_operators, _check_view)
        return None if kernel is None else kernel.stepper(self)

    def reaction_end(self) -> float:
        """Time at which the operator notices the calibration has finished."""
        return self.calibration.t0 + self.calibration.duration + self.traits.reaction


def _check_operators(k: int) -> tuple[SyntheticOperator, SyntheticOperator]:
    """Two like operators in flight for the compiled flight's self-check
    (:func:`payload.teleop.operator_c.compiled_act`): a random route of 1 to 6 waypoints
    and heading, sampled traits (a high dropout rate for some), a random phase, waypoint,
    wrists, aperture, grip, stop time and dropouts, all seeded by ``k``."""
    rng = np.random.default_rng(k)
    n = 1 + k % 6
    route = np.cumsum(rng.normal(scale=1.5, size=(n, 3)), axis=0)
    plan = OperatorPlan(
        route=route,
        heading0=float(rng.uniform(-math.pi, math.pi)),
        corner_speed=(0.04, 0.07)[k % 2],
    )
    traits = OperatorTraits.sample(rng)
    if k % 2:  # hands lost often: dropouts begin and end within the check
        traits = replace(traits, dropout_rate=5.0)
    state = rng.integers(1 << 30)
    pair = []
    for _ in range(2):
        op = SyntheticOperator(plan, k, CalibrationProcedure(), traits)
        draw = np.random.default_rng(state)
        op.phase = FLIGHT_PHASES[int(draw.integers(len(FLIGHT_PHASES)))]
        op.waypoint = int(draw.integers(n))
        op.wrist = {s: draw.normal(scale=0.5, size=3) for s in ("left", "right")}
        op.aperture = float(draw.uniform(0.0, 1.0))
        op.grip_aperture = None if k % 3 == 0 else float(draw.uniform(0.0, 0.04))
        op.stopped_since = (None, 0.0, float(draw.uniform(0.0, 30.0)))[k % 3]
        op._dropout_until = {s: float(draw.uniform(-1.0, 21.0)) for s in ("left", "right")}
        pair.append(op)
    return pair[0], pair[1]


def _check_view(op: SyntheticOperator, rng: np.random.Generator, i: int, t: float) -> WorldView:
    """A random view of the vehicle for the compiled flight's self-check: near one of the
    operator's waypoints (within its radius at times, at the last one at times), turned
    any way, moving or (for three seconds in every six) at rest."""
    route = op.plan.route
    near = route[int(rng.integers(len(route)))] if i % 4 else route[-1]
    pos = near + rng.normal(scale=(0.05, 0.3, 1.0)[i % 3], size=3)
    q = rng.normal(size=4)
    rot = quat_to_matrix(q / np.linalg.norm(q))
    vel = np.zeros(3) if (i // 150) % 2 else rng.normal(scale=(0.001, 0.05)[i % 2], size=3)
    return WorldView(t, pos, rot, vel, pos + 0.3, bool(i % 2), None)
