"""The fixed-rate teleoperation loop: a hand source, the pipeline, a payload driver, a vehicle.

In simulation the loop steps deterministically (one control step = 20 physics steps of
the :class:`~payload.sim.driver.SimDriver`); with a live source it paces itself to
wall-clock time and counts overruns. The first part of every session is the calibration
procedure; the pipeline starts when it is done.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from payload.rotations import quat_to_matrix, yaw_of_matrix
from payload.schema import CONTROL_DT, ENDED_BY_CAP, ENDED_BY_SOURCE, PayloadCommand, VehicleTwist
from payload.teleop.calibration import CalibrationProcedure, Captures
from payload.teleop.hands import HandFrame
from payload.teleop.operator import SyntheticOperator, WorldView
from payload.teleop.pipeline import TeleopPipeline, TeleopStep
from payload.vecmath import norm

log = logging.getLogger(__name__)

ARM_AFTER_STEPS = 25
"""A hardware payload's Bus Watchdog is armed this many loop steps (half a second) after
a session starts, and again this many steps after the calibration has built the
teleoperation pipeline (disarmed meanwhile): the session's first steps, and the
pipeline's first step (its compiled kernels' self-checks), build what they use once
(measured on the emulator rig: the session's third step ~0.4 s under load; the
pipeline's first step 85 to 290 ms at load 2), longer than the watchdog's 100 ms, which
would trip it on a healthy session. The payload holds one command while the pipeline is
built, as a tripped watchdog would hold it."""


class WatchdogArming:
    """When a hardware payload's Bus Watchdog is on: armed :data:`ARM_AFTER_STEPS` steps
    into a session, and again that many steps after each :meth:`hold_off` (off
    meanwhile). One count for ``hw run`` and ``teleop serve --driver hardware``.

    Args:
        set_watchdog: The payload's ``set_watchdog(on)`` (None: a payload without one).
    """

    def __init__(self, set_watchdog: Callable[[bool], None] | None) -> None:
        self._set = set_watchdog
        self.steps = 0
        self._arm_at = ARM_AFTER_STEPS

    def hold_off(self) -> None:
        """Off now, on again :data:`ARM_AFTER_STEPS` steps from here (the pipeline's
        first steps, or no step at all until the next attempt)."""
        self._arm_at = self.steps + ARM_AFTER_STEPS
        if self._set is not None:
            self._set(False)

    def step(self) -> None:
        """One more step (a command sent): armed when its step comes."""
        self.steps += 1
        if self.steps == self._arm_at and self._set is not None:
            self._set(True)


class HandSource(Protocol):
    """Where hand frames come from (synthetic operator, replay, live headset)."""

    def frame(self, t: float, world: WorldView | None) -> HandFrame | None:
        """The frame for control time ``t`` (None: the source has ended)."""

    @property
    def finished(self) -> bool:
        """Whether the source has nothing more to do."""


class SyntheticSource:
    """The synthetic operator as a hand source."""

    def __init__(self, operator: SyntheticOperator) -> None:
        self.operator = operator

    def frame(
        self, t: float, world: WorldView | None, grid: float | None = None
    ) -> HandFrame | None:
        """The operator's hands (``grid``: as a headset reporting on it gives them)."""
        if world is None:
            raise ValueError("the synthetic operator needs to see the world")
        return self.operator.act(world, grid)

    @property
    def finished(self) -> bool:
        return self.operator.finished


class ReplaySource:
    """Recorded frames resampled to the control rate by their recorded timestamps.

    Control time ``t`` is matched to recorded time ``stamp_0 + t``: the source gives the
    latest frame stamped at or before it (sample and hold). A 72 or 90 Hz session thus
    replays at its own speed (frames between two control steps are skipped; a slower one
    repeats frames), and a 50 Hz recording gives back every frame once. Frames are used
    in file order, so a stamp going backwards still reaches the safety supervisor. The
    source ends with its last frame.

    Args:
        frames: The recorded frames, in file order.
        tolerance: Slack [s] on "at or before", for stamps rounded when recorded.
    """

    def __init__(self, frames: list[HandFrame], tolerance: float = 1e-6) -> None:
        self.frames = frames
        self.tolerance = tolerance
        self.index = -1  # the frame given last
        self.t0 = float(frames[0].stamp) if frames else 0.0

    def frame(self, t: float, world: WorldView | None) -> HandFrame | None:
        if not self.frames or self.finished:
            return None
        target = self.t0 + t + self.tolerance
        nxt = self.index + 1
        while nxt < len(self.frames) and (nxt == 0 or self.frames[nxt].stamp <= target):
            self.index = nxt
            nxt += 1
        return self.frames[self.index]

    @property
    def finished(self) -> bool:
        return self.index >= len(self.frames) - 1


class PhaseTracker:
    """Labels each control step from what the pipeline does, for any source.

    calibration -> acquisition (until the base first moves after the first opposing
    contact, when the contact is given) -> translation / turn (moving,
    turn while the yaw-rate command exceeds ``turn_rate``) -> braking (request zero while
    still moving) -> arrival (at rest after having moved).
    """

    def __init__(self, turn_rate: float = 0.03, rest_speed: float = 0.005) -> None:
        self.turn_rate = turn_rate
        self.rest_speed = rest_speed
        self.moved = False
        self.held = False

    def label(
        self, calibrating: bool, step: TeleopStep | None, speed: float, contact: bool | None = None
    ) -> str:
        """The phase of this step; with ``contact`` (the opposing-contact indicator) given,
        moving the base before the first opposing contact (lining up) is acquisition."""
        if calibrating or step is None:
            return "calibration"
        self.held = self.held or contact is None or bool(contact)
        requesting = np.count_nonzero(step.base.v_request) > 0  # np.any's answer, sooner
        if requesting and not self.held:
            return "acquisition"
        if requesting:
            self.moved = True
            return "turn" if abs(step.base.yaw_rate) > self.turn_rate else "translation"
        if not self.moved:
            return "acquisition"
        if speed > self.rest_speed or float(norm(step.base.v_world)) > 1e-4:
            return "braking"
        return "arrival"


@dataclass
class LoopStats:
    """Timing of a session.

    Attributes:
        steps: Control steps run.
        pipeline_us: Per-step pipeline time [us].
        overruns: Steps whose work took longer than the period (live pacing only).
        ended_by: What ended the session: ``"source"`` (the hand source finished: the
            synthetic operator's route, a replay's last frame) or ``"max_time"`` (the
            session-length cap); empty while it runs or when an exception ended it.
    """

    steps: int = 0
    pipeline_us: list[float] = field(default_factory=list)
    overruns: int = 0
    ended_by: str = ""


@dataclass
class StepContext:
    """What the loop hands to its per-step observer (recorder).

    Attributes:
        t: Control time [s].
        phase: Phase label.
        frame: The raw hand frame.
        step: The pipeline output (None while calibrating).
        command: The payload command sent.
        twist: The vehicle twist sent.
        state: The world state after the step (driver specific).
        payload: The measured payload state after the step.
    """

    t: float
    phase: str
    frame: HandFrame
    step: TeleopStep | None
    command: PayloadCommand
    twist: VehicleTwist
    state: object
    payload: object


def run_session(
    driver: object,
    source: HandSource,
    calibration: CalibrationProcedure,
    make_pipeline: Callable[[Captures, float], TeleopPipeline],
    *,
    max_time: float = 300.0,
    on_step: Callable[[StepContext], None] | None = None,
    pace: bool = False,
    world_view: Callable[[object, float], WorldView] | None = None,
) -> LoopStats:
    """Run one teleoperation session at 50 Hz until the source finishes or ``max_time``.

    Args:
        driver: A :class:`~payload.sim.driver.SimDriver` (``send``, ``read``,
            ``command_twist``, ``step``, ``world_state``).
        source: Hand frames.
        calibration: The calibration procedure (run first, on the same frames).
        make_pipeline: Builds the pipeline from the captures and the vehicle heading.
        max_time: Session length cap [s].
        on_step: Observer called after every step (the recorder).
        pace: Pace to wall-clock time (live sources).
        world_view: Converts the driver's world state to what the operator sees.
    """
    stats = LoopStats()
    state = driver.world_state()
    hold = driver.read()
    command = PayloadCommand(hold.q, hold.deploy, 0.0)
    twist = VehicleTwist.zero()
    driver.command_twist(twist)
    pipeline: TeleopPipeline | None = None
    phases = PhaseTracker()
    t0_wall = time.perf_counter()
    k = 0
    try:
        while True:
            t = k * CONTROL_DT
            if t > max_time + 1e-9:
                stats.ended_by = ENDED_BY_CAP
                break
            view = world_view(state, t) if world_view is not None else None
            frame = source.frame(t, view)
            if frame is None:
                stats.ended_by = ENDED_BY_SOURCE
                break
            step: TeleopStep | None = None
            calibrating = not calibration.done
            if calibrating:
                calibration.step(frame)
                if calibration.done:
                    heading = yaw_of_matrix(quat_to_matrix(state.astrobee_quat))
                    pipeline = make_pipeline(calibration.captures, heading)
            if pipeline is not None and not calibrating:
                a = time.perf_counter()
                step = pipeline.step(frame, quat_to_matrix(state.astrobee_quat))
                stats.pipeline_us.append((time.perf_counter() - a) * 1e6)
                command, twist = step.command, step.twist
            driver.send(command)
            driver.command_twist(twist)
            state = driver.step(1)
            payload = driver.read()
            speed = float(norm(state.astrobee_linear))
            phase = phases.label(
                calibrating, step, speed, bool(getattr(state, "opposing_contact", True))
            )
            if on_step is not None:
                on_step(StepContext(t, phase, frame, step, command, twist, state, payload))
            k += 1
            stats.steps = k
            if pace:
                lag = time.perf_counter() - t0_wall - k * CONTROL_DT
                if lag > 0:
                    stats.overruns += 1
                else:
                    time.sleep(-lag)
            if source.finished:
                stats.ended_by = ENDED_BY_SOURCE
                break
    finally:
        # whatever ended the session (source finished, time cap, an exception), leave the
        # vehicle braking and the payload holding its last command
        driver.command_twist(VehicleTwist.zero())
        driver.send(command)
    return stats
