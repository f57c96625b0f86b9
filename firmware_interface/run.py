"""Teleoperation on the hardware: the 50 Hz loop with the payload on the servo bus.

:class:`HardwareInTheLoop` puts a hardware payload driver (``DynamixelDriver``) behind
the same interface the loop uses for the simulator: the payload commands go to the
servos and the measured payload state comes from them; Astrobee and the cargo bag, which
are not on the bench, stay simulated, and the simulated payload follows the servos'
measured positions so the contacts are those of the real finger postures.
:func:`run_hardware_trial` runs a recorded hand session through it and records the
trial exactly as ``payload trial`` does (``log.mcap``, ``hands.jsonl``, ``metrics.json``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from payload.design.params import load_design
from payload.schema import PayloadCommand, PayloadDriver, PayloadState, VehicleTwist
from payload.sim.driver import SimDriver, WorldState
from payload.teleop.calibration import CalibrationProcedure, Captures
from payload.teleop.loop import ReplaySource, StepContext, run_session
from payload.teleop.pipeline import TeleopConfig, TeleopPipeline, calibrate_operator
from payload.teleop.replay import HandRecordingWriter

log = logging.getLogger(__name__)


class HardwareInTheLoop:
    """A hardware payload with the simulated vehicle and cargo (the loop's driver).

    Args:
        hardware: The payload driver (``DynamixelDriver``).
        sim: The simulator providing Astrobee, the CTB and contacts.
    """

    def __init__(self, hardware: PayloadDriver, sim: SimDriver) -> None:
        self.hardware = hardware
        self.sim = sim
        self.world = sim.world
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
        return self.sim.step(control_steps)

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
    budget: str = "paper",
    collisions: bool = False,
) -> list[PayloadCommand]:
    """Run a recorded hand session through the 50 Hz loop on ``driver``.

    The same code for the simulator (``SimDriver``) and the hardware
    (:class:`HardwareInTheLoop`): calibration, pipeline, loop.

    ``budget`` and ``collisions`` set the pair solves (as ``payload trial``'s flags).

    Returns:
        The payload command sent at every step.
    """
    from payload.trials.runner import retargeting

    retargeters, ranges = retargeting(budget=budget, collisions=collisions)
    for r in retargeters.values():
        r.reset()
    config = TeleopConfig.from_design(load_design())
    q0 = driver.read().q
    commands: list[PayloadCommand] = []

    def make_pipeline(captures: Captures, heading: float) -> TeleopPipeline:
        cal = calibrate_operator(captures, ranges, config.rail_travel, heading)
        return TeleopPipeline(cal, retargeters, config, initial=q0)

    def observe(ctx: StepContext) -> None:
        commands.append(ctx.command)
        if on_step is not None:
            on_step(ctx)

    run_session(
        driver,
        ReplaySource(list(frames)),
        CalibrationProcedure(),
        make_pipeline,
        max_time=max_time,
        on_step=observe,
        pace=pace,
    )
    return commands


def run_hardware_trial(
    hardware: Any,
    replay: Path,
    out_dir: Path,
    *,
    max_time: float = 240.0,
    pace: bool = True,
    controller: tuple[str, list[str]] = ("safe", []),
    budget: str = "paper",
    collisions: bool = True,
) -> dict[str, Any]:
    """Replay a hand recording on the hardware and record the trial like ``payload trial``.

    Args:
        hardware: A brought-up payload driver (``DynamixelDriver``).
        replay: The hand recording (``hands.jsonl``).
        out_dir: The trial folder (``log.mcap``, ``hands.jsonl``, ``metrics.json``).
        max_time: Session length cap [s].
        pace: Pace the loop to wall-clock 50 Hz (the servos move in real time).
        controller: The controller profile's name and the settings overridden
            (:func:`payload.profiles.resolve`), recorded.
        budget: The pair solves' evaluation budget.
        collisions: Self-collision modelled in the pair solves.

    Returns:
        The metrics (as written to ``metrics.json``), with ``steps`` and ``driver``.
    """
    from payload.trials.campaign import finish_trial
    from payload.trials.recorder import TrialRecorder
    from payload.trials.runner import (
        design_hash,
        load_replay,
        module_rects,
        place_ctb_for_teleop,
        retargeting,
        step_record,
    )

    _, frames = load_replay(replay)  # a trial's log.mcap, or a hands.jsonl
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sim = SimDriver()
    retargeters, ranges = retargeting(budget=budget, collisions=collisions)
    place_ctb_for_teleop(sim, retargeters, ranges)
    driver = HardwareInTheLoop(hardware, sim)
    layout = sim.world.layout
    rec_path = out / "log.mcap"
    meta = {
        "seed": 0,
        "operator": "replay",
        "driver": "hardware",
        "design_hash": design_hash(),
        "traits": {"replay": str(replay)},
        "route": layout.route().tolist(),
        "modules": module_rects(layout),
        "retarget_budget": budget,
        "retarget_collisions": collisions,
        "controller": controller[0],
        "controller_overrides": controller[1],
    }
    try:
        with (
            TrialRecorder(rec_path, overwrite=True) as recorder,
            HandRecordingWriter(out / "hands.jsonl", meta={"seed": 0}) as hands_out,
        ):
            recorder.write_meta(meta)

            def on_step(ctx: StepContext) -> None:
                hands_out.write(ctx.frame)
                recorder.write(step_record(ctx, driver, retargeters))
                fault = getattr(hardware, "fault", None)
                if fault is not None:
                    raise fault

            commands = replay_session(driver, frames, max_time=max_time, pace=pace,
                                      on_step=on_step, budget=budget,
                                      collisions=collisions)  # fmt: skip
            recorder.write_meta({"steps": len(commands), "warnings": driver.warnings()})
    finally:
        sim.close()
    result = finish_trial(out, rec_path)
    result["steps"] = len(commands)
    result["driver"] = "hardware"
    (out / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    return result
