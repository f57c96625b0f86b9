"""A live teleoperation session: the Quest page drives the ISS cargo scene, recorded as a trial.

``LiveSession`` wires the pieces that already exist: the default trial world
(:class:`~payload.sim.driver.SimDriver` with the CTB placed under the pinch), the
operator calibration procedure, the production pipeline and the 50 Hz loop
(:func:`~payload.teleop.loop.run_session`, paced to the wall clock), and, with a record
folder, the trial recorder (``log.mcap``) and the hand recording (``hands.jsonl``), scored
at the end by the same code as any trial (``metrics.json``).

A session attempt starts when a page connects; if the page goes away before the
calibration is done, or the calibration captures are unusable, the attempt is dropped
and calibration starts again with the next page (the state messages'
``calibration_failure`` says why the last attempt was refused, while the next one runs).
Once calibrated, a dropped page brakes the vehicle and holds the fingers; the page coming
back resumes control, blended in.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from payload.design.params import load_design
from payload.errors import PayloadError, RunAborted
from payload.folders import HANDS, RECORDING
from payload.rotations import quat_to_matrix, yaw_of_matrix
from payload.schema import CONTROL_DT
from payload.teleop.calibration import (
    DEFAULT_STEPS,
    CalibrationError,
    CalibrationProcedure,
    Captures,
    Step,
)
from payload.teleop.link import DelayedLink, DelayLine
from payload.teleop.live import HOLDER, LiveHub, LiveSource, TimedDriver
from payload.teleop.loop import StepContext, WatchdogArming, run_session
from payload.teleop.pipeline import TeleopConfig, TeleopPipeline, calibrate_operator
from payload.teleop.replay import HandRecordingWriter
from payload.trials.acquisition import place_ctb_for_teleop
from payload.trials.preparation import base_filter_for, design_hash, module_rects
from payload.trials.recorder import RecordingError, StepRecord, TrialRecorder
from payload.trials.records import MODULE_NAMES
from payload.trials.retargeters import retargeting
from payload.trials.safety import recording_scene

log = logging.getLogger(__name__)

IDLE_CHECK_S = 1.0
"""How often the hardware payload's health is read while no page drives it [s]
(:meth:`PayloadRig.check`): a lost bus is said within about this long."""

FINGERS = ("A", "B", "C", "D")
SESSION_CAP_S = 24 * 3600.0


def scene_of(driver: Any) -> dict[str, Any]:
    """What the page needs to draw the world: module volumes, vehicle and CTB sizes."""
    w = driver.world
    size = w.config.ctb_size
    return {
        "modules": [
            {
                "name": MODULE_NAMES.get(z.module.value, z.module.value),
                "title": z.module.title,
                "lo": z.lo,
                "hi": z.hi,
            }
            for z in w.layout.zones()
        ],
        "vehicle_size": float(w.vehicle.body_size[0]),  # the first field: a cube's edge
        "vehicle_body_size": [float(v) for v in w.vehicle.body_size],
        "ctb_size": None if size is None else [size.length, size.width, size.height],
        "route": w.layout.route().tolist(),
    }


def _v(a: Any) -> list[float]:
    return [round(float(x), 5) for x in np.asarray(a).ravel()]


class PayloadRig:
    """The simulated scene with another payload driver beside it (``--driver hardware``).

    The operator flies the simulated vehicle and sees the simulated world; every payload
    command also goes to ``payload`` (the Dynamixel payload on the bench), and the
    measured payload state is the real one. Anything else (vehicle, world) is the
    simulator's.
    """

    def __init__(self, sim: Any, payload: Any) -> None:
        self._sim = sim
        self.payload = payload
        # a payload whose Bus Watchdog was left disarmed while the session set up (see
        # ``payload teleop serve --driver hardware``) has it armed once the loop runs
        self._watchdog = WatchdogArming(getattr(payload, "set_watchdog", None))

    def pipeline_built(self) -> None:
        """The calibration built the teleoperation pipeline: the payload's Bus Watchdog is
        disarmed over the pipeline's first steps (:data:`~payload.teleop.loop.
        ARM_AFTER_STEPS`), which build what they use once."""
        self._watchdog.hold_off()

    def idle(self) -> None:
        """The loop stopped sending (an attempt ended: the page went away before its
        calibration was done): the Bus Watchdog is disarmed until the next attempt's loop
        has run :data:`~payload.teleop.loop.ARM_AFTER_STEPS` steps. The servos hold their
        last goal either way (a tripped watchdog holds them too); this spares a trip, and
        its warning, each time a page leaves."""
        self._watchdog.hold_off()

    def check(self) -> None:
        """Read the payload's health while no page drives it (between attempts), as the
        loop's reads do during one: a bus that stopped answering raises (``CommError``)
        instead of the status saying the hardware waits, and a servo's hardware error
        stops the payload safely (its log line)."""
        check = getattr(self.payload, "check_health", None)
        if check is not None:
            check()

    def send(self, command: Any) -> None:
        self._sim.send(command)
        self._watchdog.step()
        self.payload.send(command)

    def read(self) -> Any:
        return self.payload.read()

    def close(self) -> None:
        try:
            self.payload.close()
        finally:
            self._sim.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sim, name)


class LiveSession:
    """The simulator driven by the live page (see the module docstring).

    Args:
        hub: Shared with the server.
        record: Trial folder to record into (None: no recording).
        steps: The calibration prompts.
        payload: A payload driver to command besides the simulator (the hardware), or
            None for the simulator alone.
        collisions: Model self-collision in the pair solves (no command closer than the
            design's margin, the pads of a pair excepted); recorded with the session.
        budget: The pair solves' evaluation budget (``paper``, ``converged``).
        controller: The controller profile these settings come from, and the settings
            the command line overrides (:func:`payload.profiles.resolve`), recorded.
        base_filter: The base safety filter on the robot's side, between the base channel
            and the vehicle; recorded with the session.
        link_delay: (delay, jitter) [s] of a delayed ground link: the page's hand frames
            reach the loop, and the loop's state reaches the page, that late
            (:mod:`payload.teleop.link`); None: no delay.
    """

    def __init__(
        self,
        hub: LiveHub,
        record: Path | None = None,
        steps: tuple[Step, ...] = DEFAULT_STEPS,
        payload: Any = None,
        collisions: bool = False,
        budget: str = "paper",
        controller: tuple[str, list[str]] | None = None,
        base_filter: bool = False,
        link_delay: tuple[float, float] | None = None,
    ) -> None:
        from payload.sim.driver import SimDriver

        self.hub = hub
        self.record = record
        self.calibration_steps = steps
        self.driver = SimDriver()
        self.collisions = bool(collisions)
        self.controller = controller
        self.retargeters, self.ranges = retargeting(budget=budget, collisions=self.collisions)
        place_ctb_for_teleop(self.driver, self.retargeters, self.ranges)
        self.config = TeleopConfig.from_design(load_design(self.driver.world.config.design))
        self.base_filter = bool(base_filter)
        if self.base_filter:
            self.driver.twist_filter = base_filter_for(self.driver, self.config.base)
        self.link_delay = link_delay if link_delay and link_delay[0] > 0 else None
        if payload is not None:
            self.driver = PayloadRig(self.driver, payload)
        self.q0 = self.driver.read().q
        self.scene = scene_of(self.driver)
        self.calibrated = False
        self.notice = ""
        self.notice_to = ""
        """Whose page the notice is for: ``holder`` (the operator's instruction) or ``""``
        (every page)."""
        self.calibration_failure = ""
        """Why the last calibration attempt was refused (its captures unusable), "" when it
        was not: kept while the next attempt runs, so every page says why it restarted."""
        self.steps = 0
        self.source: LiveSource | None = None
        self._closed = False
        self._pending: list[tuple[StepRecord, Any]] = []
        self._recorder: TrialRecorder | None = None
        self._hands: HandRecordingWriter | None = None
        self._provenance: dict[str, Any] = {}  # the recording's, once it is opened
        # the trial's Foxglove and safety channels (the filter's record, station contacts)
        self._scene = (
            None
            if record is None
            else recording_scene(self.driver, module_rects(self.driver.world.layout))
        )

    # -- recording -------------------------------------------------------------------------
    def _open_recording(self) -> None:
        if self.record is None:
            return
        out = self.record
        out.mkdir(parents=True, exist_ok=True)
        # the recording's file claimed first (created only if absent): a session that finds
        # another's recording in its folder (two servers on one --record folder) refuses
        # and takes nothing of it, the hands' file included
        try:
            recorder = TrialRecorder(out / RECORDING, scene=self._scene).open()
        except RecordingError:
            if not (out / RECORDING).exists():
                raise
            raise RecordingError(
                f"--record {out}: {RECORDING} already exists (another session recorded "
                "there since this one started?); not replaced: record into a new folder"
            ) from None
        budget = self.retargeters["L"].config.budget
        setup: dict[str, Any] = {
            "retarget_budget": budget,
            "retarget_collisions": self.collisions,
            "base_filter": self.base_filter,
            "link_delay": None if self.link_delay is None else list(self.link_delay),
        }
        if self.controller is not None:
            setup["controller"], setup["controller_overrides"] = self.controller
        try:
            hands = HandRecordingWriter(
                out / HANDS, frame="webxr", meta={"operator": "live", **setup}
            )
        except BaseException:
            recorder.close()
            (out / RECORDING).unlink()  # this session's own file, with no step
            raise
        self._recorder, self._hands = recorder, hands
        from payload.native import environment
        from payload.project import ProjectError, current_project, provenance
        from payload.trials.metrics import confirmed_definition

        design = self.driver.world.config.design
        try:  # the served project (teleop serve resolves it); a library caller may have none
            project = current_project()
        except ProjectError:
            project = None
        prov = {**provenance(project, design), "environment": environment()}
        self._provenance = prov
        self._recorder.write_meta(
            {
                "seed": 0,
                "operator": "live",
                "design_hash": design_hash(),
                "provenance": prov,
                "traits": {"live": True},
                **setup,
                "route": self.scene["route"],
                "modules": module_rects(self.driver.world.layout),
                "contact_definition": confirmed_definition(),  # scored as a trial is
            }
        )

    def _record(self, ctx: StepContext) -> None:
        if self.record is None:
            return
        from payload.trials.stepobserver import step_record

        fr = ctx.frame
        self._scene.observe(ctx.t)
        rec = step_record(ctx, self.driver, self.retargeters)
        if not self.calibrated:
            # kept until the calibration succeeds: a dropped attempt is a rehearsal
            self._pending.append((rec, fr))
            return
        if self._recorder is None:
            self._open_recording()
        for r, f in [*self._pending, (rec, fr)]:
            self._recorder.write_hands(f.to_workbench())  # as a trial's: its log.mcap replays
            self._recorder.write(r)
            self._hands.write(f)
        self._pending.clear()

    # -- state for the page ----------------------------------------------------------------
    def _world(self, st: Any, rail: float, heading0: float | None = None) -> dict[str, Any]:
        """What the page draws of the world: the vehicle, the CTB, the fingertips;
        ``heading0`` the calibration's (None: the vehicle's own yaw, before one)."""
        if heading0 is None:
            heading0 = float(yaw_of_matrix(quat_to_matrix(st.astrobee_quat)))
        data = self.driver.data
        return {
            "vehicle": {
                "pos": _v(st.astrobee_pos),
                "quat": _v(st.astrobee_quat),
                "speed": round(float(np.linalg.norm(st.astrobee_linear)), 4),
            },
            "ctb": {"pos": _v(st.ctb_pos), "quat": _v(st.ctb_quat)},
            "fingers": {f: _v(data.site(f"payload/{f}_tip").xpos) for f in FINGERS},
            "heading0": round(heading0, 5),
            "rail": round(float(rail), 4),
            "contact": bool(st.opposing_contact),
        }

    def waiting_snapshot(self) -> dict[str, Any]:
        """The snapshot before any page drives the session: the world as it stands, so a
        page shows the vehicle and the CTB from its first moment (it showed the modules'
        walls alone until a calibration began)."""
        st = self.driver.world_state()
        return {
            "t": 0.0, "phase": "waiting", "prompt": "", "step": "", "remaining": 0.0,
            **self._world(st, self.q0[-1]),
            "safe_stop": None, "calibrated": False, "events": [], "notice": "",
            "notice_to": "", "calibration_failure": self.calibration_failure,
        }  # fmt: skip

    def _snapshot(self, ctx: StepContext, source: LiveSource, calibration: Any) -> dict:
        st = ctx.state
        prompt, step_name, remaining = "", "", 0.0
        if not calibration.done and calibration.current is not None:
            step = calibration.current
            prompt, step_name = step.prompt, step.name
            i = calibration.steps.index(step)
            end = calibration.t0 + sum(s.hold for s in calibration.steps[: i + 1])
            remaining = max(0.0, end - ctx.t)
        events = [] if ctx.step is None else [e.detail for e in ctx.step.events]
        pipeline = source.pipeline
        heading0 = None if pipeline is None else float(pipeline.calibration.heading0)
        return {
            "t": round(ctx.t, 3),
            "phase": ctx.phase,
            "prompt": prompt,
            "step": step_name,
            "remaining": round(remaining, 2),
            **self._world(st, ctx.command.q[-1], heading0),
            "safe_stop": source.lost_reason if self.calibrated else None,
            # the next holder drives with this calibration (a page says so, not "calibrate")
            "calibrated": self.calibrated,
            "events": events,
            "notice": self.notice,
            "notice_to": self.notice_to,
            "calibration_failure": self.calibration_failure,
        }

    # -- running ---------------------------------------------------------------------------
    def _attempt(self) -> None:
        calibration = CalibrationProcedure(self.calibration_steps)
        source = LiveSource(self.hub, calibration)
        self.source = source
        driver = TimedDriver(self.driver, source, self.hub)
        t0_wall = time.perf_counter()
        hands: Any = source
        states = None
        if self.link_delay is not None:  # hands up, state down, each that late
            hands = DelayedLink(source, *self.link_delay)
            states = DelayLine(*self.link_delay, np.random.default_rng(1))

        def make_pipeline(captures: Captures, heading: float) -> TeleopPipeline:
            cal = calibrate_operator(captures, self.ranges, self.config.rail_travel, heading)
            pipeline = TeleopPipeline(cal, self.retargeters, self.config, initial=self.q0)
            if isinstance(self.driver, PayloadRig):
                self.driver.pipeline_built()
            source.pipeline = pipeline
            self.calibrated = True
            self.calibration_failure = ""
            self.notice = "calibrated: fly with your left wrist"
            self.notice_to = HOLDER  # the operator's instruction, not the watchers'
            return pipeline

        def on_step(ctx: StepContext) -> None:
            k = round(ctx.t / CONTROL_DT) + 1
            lag = time.perf_counter() - t0_wall - k * CONTROL_DT
            self._record(ctx)
            snap = self._snapshot(ctx, source, calibration)
            # the state follows the snapshot's own safe-stop reason, and both change under
            # one lock: a reader never sees "safe_stop" beside a snapshot without its reason
            if not self.calibrated:
                state = "calibrating"
            else:
                state = "safe_stop" if snap["safe_stop"] else "teleop"
            if lag > CONTROL_DT:  # this step ended more than a period late
                with self.hub.lock:
                    self.hub.loop_overruns += 1
            if states is not None:  # the page sees the state sent a delay ago
                states.put(ctx.t, (snap, state))
                snap, state = states.take(ctx.t)
            self.hub.publish(snap, state=state)
            self.steps += 1

        try:
            run_session(
                driver,
                hands,
                calibration,
                make_pipeline,
                max_time=SESSION_CAP_S,
                on_step=on_step,
                pace=True,
            )
        except CalibrationError as exc:
            # said on every page while the next attempt's prompts run (the notice is
            # cleared when it starts), and in the terminal, in the same words
            self.calibration_failure = str(exc)
            log.warning("teleop: calibration restarted: %s", exc)
        else:
            if not self.calibrated:  # the page went away: the last attempt was not refused
                self.calibration_failure = ""
        if isinstance(self.driver, PayloadRig):  # nothing is sent until the next attempt
            self.driver.idle()
        if not self.calibrated:
            self._pending.clear()
            if self._scene is not None:
                self._scene.discard()

    def run(self) -> None:
        """Serve attempts until ``hub.stop`` is set (Ctrl-C in the terminal)."""
        if not self.hub.snapshot.get("vehicle"):  # nothing drawn yet
            self.hub.publish(self.waiting_snapshot(), state="waiting")
        checked = time.monotonic()
        try:
            while not self.hub.stop.is_set():
                with self.hub.lock:
                    self.hub.state = "waiting" if not self.calibrated else self.hub.state
                    connected = self.hub.latest is not None
                if not connected:
                    if isinstance(self.driver, PayloadRig) and (
                        time.monotonic() - checked >= IDLE_CHECK_S
                    ):
                        try:  # the bench's payload is still there
                            self.driver.check()
                        except PayloadError as exc:
                            raise RunAborted(
                                f"teleop serve stopped: the payload failed while no page "
                                f"drove it: {exc}"
                            ) from exc
                        checked = time.monotonic()
                    time.sleep(0.05)
                    continue
                if not self.calibrated:
                    self.notice, self.notice_to = "", ""
                self._attempt()
        finally:
            with self.hub.lock:
                self.hub.state = "stopped"

    def close(self) -> dict[str, Any] | None:
        """Close the recording and score it (None without a recording, or if closed)."""
        if self._closed:
            return None
        self._closed = True
        result = None
        try:  # the driver is closed (the servos' torque off) however far this gets
            self.driver.command_twist(None)
            if self._recorder is not None:
                try:
                    self._recorder.flush()  # every step written: the figures count them all
                    self._recorder.write_meta(
                        {
                            "steps": self.steps,
                            "warnings": self.driver.warnings(),
                            **self._scene.summary(),
                        }
                    )
                finally:  # a stop here leaves the files closed, not cut short
                    self._recorder.close()
                    self._hands.close()
                from payload.trials.campaign import finish_trial
                from payload.trials.scoring import write_metrics

                out = self.record
                result = finish_trial(out, out / RECORDING)
                result["steps"] = self.steps
                result["provenance"] = self._provenance  # as a trial's metrics.json has it
                write_metrics(out, result)
        finally:
            self.driver.close()
        return result
