"""Teleoperation on the hardware: the 50 Hz loop with the payload on the servo bus.

:class:`HardwareInTheLoop` puts a hardware payload driver (``DynamixelDriver``) behind
the same interface the loop uses for the simulator: the payload commands go to the
servos and the measured payload state comes from them; Astrobee and the cargo bag, which
are not on the bench, stay simulated, and the simulated payload follows the servos'
measured positions so the contacts are those of the real finger postures.
:func:`run_hardware_trial` runs a recorded hand session through it and records the
trial as ``payload trial`` does (``log.mcap``, ``metrics.json``), with the raw hand
frames as they came beside it (``hands.jsonl``, as a live session's).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from firmware_interface.deployment import (
    RAIL,
    deployment_cleared,
    move_to_home,
    stow_after_session,
)
from firmware_interface.errors import DynamixelError
from payload.design.params import load_design
from payload.errors import RunAborted
from payload.folders import HANDS, RECORDING
from payload.schema import (
    CONTROL_DT,
    PayloadCommand,
    PayloadDriver,
    PayloadState,
    VehicleTwist,
)
from payload.sim.driver import SimDriver, WorldState
from payload.teleop.calibration import CalibrationProcedure, Captures
from payload.teleop.loop import ReplaySource, StepContext, WatchdogArming, run_session
from payload.teleop.pipeline import TeleopConfig, TeleopPipeline, calibrate_operator
from payload.teleop.replay import HandRecordingWriter

log = logging.getLogger(__name__)


PROGRESS_LINE_S = 10.0
"""``hw run`` without a terminal says how far the session is this often [s of session]."""


def ready_at_home(hardware: Any, say: Callable[[str], None] | None = None) -> None:
    """Bring the payload up (the rail and the stage homed) unless it is, drive it to the
    design's home posture (:func:`move_to_home`) and disarm its Bus Watchdog until a 50 Hz
    loop runs (what comes before the loop takes seconds). ``say`` is called with a line
    before each stage: the servos move, and whoever is beside them is told so first."""
    from firmware_interface.driver import bring_up_notice, failed_start

    with failed_start(hardware.device):
        deployment_cleared(hardware.design)  # before anything moves (the homing too)
        if not getattr(hardware, "homed", None):
            if say is not None:
                say(bring_up_notice(hardware.device))
            hardware.bring_up()
        if say is not None:
            say("moving to the design's home posture")
        move_to_home(hardware, cleared=True)
    hardware.set_watchdog(False)


def _finger_dofs(sim: SimDriver) -> np.ndarray:
    """The simulator's DOF addresses of the 16 finger joints (the servo map's order)."""
    import mujoco

    from payload.design.tree import MANIPULATION_JOINTS
    from payload.sim.world import PAYLOAD_PREFIX

    m = sim.model
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, PAYLOAD_PREFIX + j)
           for j in MANIPULATION_JOINTS if j != "rail"]  # fmt: skip
    return np.array([m.jnt_dofadr[i] for i in ids])


class HardwareInTheLoop:
    """A hardware payload with the simulated vehicle and cargo (the loop's driver).

    Args:
        hardware: The payload driver (``DynamixelDriver``).
        sim: The simulator providing Astrobee, the CTB and contacts.
        emulator: The emulator's control handle, when the far end is one: each step, the
            simulated contact torque on each finger joint is put on its servo as load
            (so a finger blocked by the cargo stalls on the bus as it would on the payload).
    """

    def __init__(self, hardware: PayloadDriver, sim: SimDriver, emulator: Any = None) -> None:
        self.hardware = hardware
        self.sim = sim
        self.emulator = emulator
        self.world = sim.world
        self._dofs = _finger_dofs(sim)
        self._measured: PayloadState = hardware.read()
        self._follow(self._measured)

    def _follow(self, m: PayloadState) -> None:
        self.sim.send(PayloadCommand(m.q, m.deploy, m.stamp))

    def send(self, command: PayloadCommand) -> None:
        self.hardware.send(command)

    def read(self) -> PayloadState:
        return self._measured

    def command_twist(self, twist: VehicleTwist | None) -> None:
        self.sim.command_twist(twist)

    def step(self, control_steps: int = 1) -> WorldState:
        """Read the servos, let the simulated payload follow them, step the world."""
        self._measured = self.hardware.read()
        self._follow(self._measured)
        state = self.sim.step(control_steps)
        if self.emulator is not None:
            self.emulator.load(self.finger_loads())
        return state

    def finger_loads(self) -> dict[int, float]:
        """The simulated contact torque on each finger joint as its servo's holding
        current, ID -> mA, signed in the servo's tick direction."""
        tau = self.sim.data.qfrc_constraint[self._dofs]  # [N m], joint direction
        hw = self.hardware
        kt = hw.design.servo.kt  # [N m / A], the servo model's (the emulator's, the driver's)
        specs = hw.map.servos[: len(self._dofs)]
        return {sp.id: float(sp.direction * t / kt * 1e3) for sp, t in zip(specs, tau)}

    def world_state(self) -> WorldState:
        return self.sim.world_state()

    def module_at(self, point: np.ndarray) -> Any:
        return self.sim.module_at(point)

    def warnings(self) -> dict[str, int]:
        return self.sim.warnings()

    def close(self) -> None:
        try:
            self.hardware.close()
        finally:
            self.sim.close()

    def __enter__(self) -> HardwareInTheLoop:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def replay_session(
    driver: Any,
    frames: list,
    *,
    max_time: float = 240.0,
    pace: bool = False,
    on_step: Any = None,
    rt: tuple[dict, dict] | None = None,
    on_pipeline: Any = None,
    on_end: Any = None,
) -> list[PayloadCommand]:
    """Run a recorded hand session through the 50 Hz loop on ``driver``.

    The same code for the simulator (``SimDriver``) and the hardware
    (:class:`HardwareInTheLoop`): calibration, pipeline, loop. ``rt``: the retargeters
    and pair ranges to use (default: the paper's). ``on_pipeline()`` is called once the
    calibration has built the teleoperation pipeline, before its first step;
    ``on_end(stats)`` with the session's :class:`~payload.teleop.loop.LoopStats` when it
    ends (``ended_by``: the source finished, or the ``max_time`` cap).

    ``budget`` and ``collisions`` set the pair solves (as ``payload trial``'s flags).

    Returns:
        The payload command sent at every step.
    """
    from payload.trials.runner import retargeting

    retargeters, ranges = rt if rt is not None else retargeting()
    for r in retargeters.values():
        r.reset()
    config = TeleopConfig.from_design(load_design())
    q0 = driver.read().q
    commands: list[PayloadCommand] = []

    def make_pipeline(captures: Captures, heading: float) -> TeleopPipeline:
        cal = calibrate_operator(captures, ranges, config.rail_travel, heading)
        pipeline = TeleopPipeline(cal, retargeters, config, initial=q0)
        if on_pipeline is not None:
            on_pipeline()
        return pipeline

    def observe(ctx: StepContext) -> None:
        commands.append(ctx.command)
        if on_step is not None:
            on_step(ctx)

    stats = run_session(
        driver,
        ReplaySource(list(frames)),
        CalibrationProcedure(),
        make_pipeline,
        max_time=max_time,
        on_step=observe,
        pace=pace,
    )
    if on_end is not None:
        on_end(stats)
    return commands


def _replay_setup(sim_project: Any, recorded: dict[str, Any]) -> tuple[Any, dict, Any]:
    """The simulated world, retargeting and CTB placement of the replayed recording's
    source trial (its CTB model, propulsion, retargeting budget, acquisition offset and
    yaw); a bare hand session (no set-up recorded) gets the defaults and no offset.

    Returns:
        ``(sim, retargeting, recorded_setup)``.
    """
    from payload.sim.config import WorldConfig
    from payload.trials.acquisition import place_offset
    from payload.trials.retargeters import retargeting
    from payload.trials.runner import place_ctb_for_teleop
    from payload.trials.sources import trial_setup

    setup = trial_setup(
        recorded.get("ctb"),
        recorded.get("propulsion"),
        recorded.get("retarget_budget"),
        recorded.get("retarget_collisions"),
        recorded.get("physics_dt"),
    )
    sim = SimDriver(
        WorldConfig.for_project(sim_project, ctb=setup["ctb"], physics_dt=setup["physics_dt"]),
        propulsion=setup["propulsion"],
    )
    rt = retargeting(sim_project, setup["retarget_budget"], setup["retarget_collisions"])
    grasp_body = place_ctb_for_teleop(sim, *rt)
    offset = recorded.get("ctb_offset_m")
    yaw = recorded.get("ctb_yaw_deg")
    if offset is None or yaw is None:  # no acquisition offset recorded: none applied
        offset, yaw = [0.0, 0.0, 0.0], 0.0
    off, yaw = place_offset(sim, int(recorded.get("seed") or 0), np.asarray(offset), yaw)
    setup.update(ctb_offset_m=[float(v) for v in off], ctb_yaw_deg=float(yaw),
                 grasp_body_m=[float(v) for v in grasp_body])  # fmt: skip
    return sim, rt, setup


def run_hardware_trial(
    hardware: Any,
    replay: Path,
    out_dir: Path,
    *,
    max_time: float = 240.0,
    pace: bool = True,
    emulator: Any = None,
    base_filter: bool = True,
    controller: tuple[str, list[str]] = ("safe", []),
    budget: str = "paper",
    collisions: bool = True,
    progress: bool = False,
    say: Callable[[str], None] | None = None,
    stow_after: bool = True,
) -> dict[str, Any]:
    """Replay a hand recording on the hardware and record the trial like ``payload trial``.

    The simulated world is set up as the recording's source trial was (CTB model and
    placement, propulsion, retargeting); the hardware is brought up (homing the rail and
    the stage) after that set-up, so the Bus Watchdog is armed only once the 50 Hz loop
    is about to run, and driven to the design's home posture where the session starts.

    Args:
        hardware: An open payload driver (``DynamixelDriver``), brought up here if not yet.
        replay: The hand recording (a trial's ``log.mcap`` or a ``hands.jsonl``).
        out_dir: The trial folder (``log.mcap``, ``hands.jsonl``, ``metrics.json``).
        max_time: Session length cap [s].
        pace: Pace the loop to wall-clock 50 Hz (the servos move in real time).
        emulator: The emulator's control handle (``EmulatorProcess``) when the far end is
            one started here: the grasp's load is fed to its servos.
        base_filter: The base safety filter on the simulated vehicle (default on: the
            ``safe`` profile, real servos being in the loop).
        controller: The controller profile's name and the settings overridden
            (:func:`payload.profiles.resolve`), recorded.
        budget: The pair solves' evaluation budget.
        collisions: Self-collision modelled in the pair solves.
        progress: Show a progress bar over the session's recorded time (a paced session
            runs in real time, minutes for a whole trial's replay).
        say: Called with a line before each set-up stage that takes seconds (the
            bring-up and homing, the move to the home posture, the stowing), or None.
        stow_after: Stow the payload when the session has run to its end
            (:func:`~firmware_interface.deployment.stow`: the deployment's reverse); a
            session that stops on a fault leaves it where the fault stopped it.

    Returns:
        The metrics (as written to ``metrics.json``) with ``steps``, ``driver``,
        ``device``, ``emulator``, ``provenance``, the set-up, ``watchdog`` and
        ``stowed`` (None with ``stow_after`` off; False: stowing stopped, the warning
        says why).
    """
    from payload.native import environment
    from payload.project import current_project, provenance
    from payload.sim.zones import zones_record
    from payload.trials.metrics import confirmed_definition
    from payload.trials.preparation import base_filter_for, module_rects
    from payload.trials.recorder import TrialRecorder
    from payload.trials.safety import recording_scene
    from payload.trials.scoring import finish_trial, write_metrics
    from payload.trials.sources import load_replay, replay_meta, replay_zones
    from payload.trials.stepobserver import step_record

    header, frames = load_replay(replay)  # a trial's log.mcap, or a hands.jsonl
    recorded = header.get("meta") or {}
    # the filter keeps the vehicle in the zones its source trial ran (None: the station's)
    zones = replay_zones(header, replay) if base_filter else None
    project = current_project()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sim, rt_source, setup = _replay_setup(project, recorded)
    if (budget, collisions) == (setup["retarget_budget"], setup["retarget_collisions"]):
        retargeters, ranges = rt_source
    else:  # the CTB placed as the source trial's retargeting placed it; the session's own
        from payload.trials.retargeters import retargeting

        retargeters, ranges = retargeting(project, budget, collisions)
    if base_filter:
        sim.twist_filter = base_filter_for(sim, TeleopConfig.from_design(load_design()).base, zones)
    prov = {**provenance(project, sim.world.config.design), "environment": environment()}
    ready_at_home(hardware, say)  # the watchdog armed again once the loop runs (on_step)
    driver = HardwareInTheLoop(hardware, sim, emulator=emulator)
    layout = sim.world.layout
    rec_path = out / RECORDING
    far_end = {"device": hardware.device, "emulator": bool(hardware.emulated)}
    meta = {
        "seed": int(recorded.get("seed") or 0),
        "operator": "replay",
        "driver": "hardware",
        **far_end,
        "design_hash": prov["design_sha256"][:16],
        "provenance": prov,
        "traits": {"replay": str(replay)},
        # what it replays (a cut-short source marks this run as cut short too)
        **replay_meta(replay, header, frames),
        "route": layout.route().tolist(),
        "modules": module_rects(layout),
        # scored as its source was, a source that stored none (a hands.jsonl) as a trial is
        "contact_definition": recorded.get("contact_definition") or confirmed_definition(),
        **setup,
        "retarget_budget": budget,
        "retarget_collisions": collisions,
        "base_filter": bool(base_filter),
        **zones_record(zones),
        "controller": controller[0],
        "controller_overrides": controller[1],
    }  # fmt: skip
    trips0 = len(hardware.watchdog_trips)
    ended: list[Any] = []  # the session's LoopStats, when it ends (replay_session's on_end)
    # the trial's Foxglove and safety channels (the filter's record, station contacts)
    scene = recording_scene(sim, module_rects(layout))
    bar = None
    span = float(frames[-1].stamp) - float(frames[0].stamp) if frames else 0.0
    total = max(min(max_time, span), CONTROL_DT)  # the session's length [s]
    if progress and frames:
        from rich.progress import Progress

        bar = Progress(transient=True)
        task = bar.add_task("hw run", total=total)
        bar.start()
    # without a bar (no terminal: a log, a pipe), a line every PROGRESS_LINE_S instead
    said = {"next": PROGRESS_LINE_S if bar is None and say is not None else math.inf}
    try:
        with (
            TrialRecorder(rec_path, scene=scene) as recorder,  # never over another run's
            HandRecordingWriter(out / HANDS, meta={"seed": meta["seed"]}) as hands_out,
        ):
            recorder.write_meta(meta)
            # off while the pipeline's first steps build what they use once
            arming = WatchdogArming(hardware.set_watchdog)

            def on_step(ctx: StepContext) -> None:
                hands_out.write(ctx.frame)
                recorder.write_hands(ctx.frame)  # as a trial's: its log.mcap replays too
                scene.observe(ctx.t)
                recorder.write(step_record(ctx, driver, retargeters))
                for trip in hardware.watchdog_trips[trips0:]:  # when, in the session's time
                    trip.setdefault("session_t", round(ctx.t, 3))
                arming.step()
                if bar is not None:
                    bar.update(task, completed=ctx.t)
                elif ctx.t >= said["next"] and say is not None:
                    said["next"] += PROGRESS_LINE_S
                    say(f"hw run: {ctx.t:.0f} of {total:.0f} s of the session run")
                fault = getattr(hardware, "fault", None)
                if fault is not None:
                    raise fault

            try:
                commands = replay_session(driver, frames, max_time=max_time, pace=pace,
                                          on_step=on_step, rt=(retargeters, ranges),
                                          on_pipeline=arming.hold_off,
                                          on_end=ended.append)  # fmt: skip
            except Exception as exc:  # a fault, the bus lost: a failed run, not bad input
                what, at = recorder.mark_aborted(exc)
                raise HardwareRunAborted(
                    f"hw run aborted at t = {at:.2f} s by {what}; recording kept (marked "
                    f"aborted, not scored): {rec_path}"
                ) from exc
            for trip in hardware.watchdog_trips[trips0:]:  # re-armed by the last command,
                trip.setdefault("session_t", round(arming.steps * CONTROL_DT, 3))  # at the end
            watchdog = watchdog_report(hardware.watchdog_trips[trips0:])
            if stow_after:  # the 50 Hz traffic has ended: the stowing follows at its pace
                with contextlib.suppress(DynamixelError):  # a bus lost: the stow says so
                    hardware.set_watchdog(False)
            recorder.flush()  # every step written: the scene's figures count them all
            # "max_time": the session-length cap ended it, as a trial's closing metadata says
            recorder.write_meta({"steps": len(commands), "warnings": driver.warnings(),
                                 "watchdog": watchdog, **scene.summary(),
                                 "ended_by": ended[0].ended_by or None})  # fmt: skip
    finally:
        if bar is not None:
            bar.stop()
        sim.close()
    if emulator is not None:  # the simulated cargo's grasp ended with the session
        try:
            emulator.load({sp.id: 0.0 for sp in hardware.map.servos[:RAIL]})
        except Exception as exc:  # the emulator gone: the stow says what follows
            log.warning("could not release the emulated grasp's load: %s", exc)
    stowed = stow_after_session(hardware, say) if stow_after else None
    try:
        result = finish_trial(out, rec_path)
    except KeyboardInterrupt as exc:  # while scoring: the session itself was whole
        exc.add_note(f"the session's recording is kept whole, not scored: {rec_path}")
        raise
    # the steps that ended later than their 20 ms period (paced only: unpaced, none is due)
    overruns = ended[0].overruns if pace and ended else None
    result.update(steps=len(commands), driver="hardware", **far_end, provenance=prov,
                  watchdog=watchdog, replay=str(Path(replay).resolve()),
                  loop_overruns=overruns, stowed=stowed)  # fmt: skip
    write_metrics(out, result)
    return result


class HardwareRunAborted(RunAborted):
    """``hw run``'s session stopped mid-way (a hardware fault, the bus lost): exit 1, the
    message names the recording kept (marked aborted, as a trial's)."""


def watchdog_report(trips: list[dict[str, Any]]) -> dict[str, Any]:
    """What Bus Watchdog trips did to a session (each: the servos stopped and held until
    re-armed by the next command; the host's silence that caused it)."""
    if not trips:
        return {"trips": 0, "effect": "never tripped"}
    host = [t["silence_s"] for t in trips if t.get("host_silent_long_enough", True)]
    other = [t["silence_s"] for t in trips if not t.get("host_silent_long_enough", True)]
    causes = []
    if host:
        causes.append(f"{len(host)} after host silences up to {max(host) * 1e3:.0f} ms")
    if other:
        causes.append(
            f"{len(other)} with the host silent for less than the watchdog's time (at most "
            f"{max(other) * 1e3:.0f} ms: packets missed or delayed on the bus)"
        )
    cause = " and ".join(causes)
    return {
        "trips": len(trips),
        "events": trips,
        "effect": (
            f"the servos stopped and held where they were {len(trips)} time(s), {cause}, "
            "until the next command re-armed them; the session continued"
        ),
    }
