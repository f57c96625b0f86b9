"""One ISS cargo-transport trial: simulator + teleoperation pipeline + recorder + metrics.

``run_trial(seed, operator, replay, out_dir)`` builds the default world (Astrobee with
the deployed payload at the start of the route in Kibo, a single CTB under the fingers),
lets the operator (synthetic, or a replayed hand recording) calibrate, acquire the CTB
and fly it to Node 2, records every 50 Hz step into ``log.mcap`` and the raw hand frames
into ``hands.jsonl`` (so any trial can be replayed bit for bit), then scores it.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from payload.errors import PayloadError, RunAborted
from payload.folders import (
    CAMPAIGN_FILES,
    HANDS,
    RECORDING,
    SCORED,
    TRIAL_FILES,
    held,
    trial_dir,
)
from payload.native import environment
from payload.profiles import PROFILE_SETTINGS
from payload.project import Project, current_project, provenance
from payload.safeio import OverwriteError, check_new, new_folder
from payload.sim.config import check_physics_dt
from payload.sim.vehicle import PROPULSION_MODELS
from payload.sim.world import CTB_MODELS, WorldConfig
from payload.teleop.calibration import Captures
from payload.teleop.loop import (
    LoopStats,
    StepContext,
    run_session,
)
from payload.teleop.pipeline import (
    TeleopPipeline,
    calibrate_operator,
)
from payload.trials.acquisition import place_ctb_for_teleop
from payload.trials.preparation import (
    TrialSetup,
    base_filter_for,
    closing_meta,
    design_hash,
    module_rects,
    set_up_trial,
    trial_meta,
)
from payload.trials.retargeters import retargeting, single_threaded_numerics
from payload.trials.setup_options import MAX_TRIAL_S, RUN_SETTINGS, ZONES_WITHOUT_FILTER
from payload.trials.sources import (
    HeadsetSource,
    TrialError,
    _Source,
    load_replay,
    replay_zones,
    trial_setup,
)
from payload.trials.stepobserver import MODULE_NAMES, step_record, world_view

if TYPE_CHECKING:
    from payload.trials.reading import Recording

log = logging.getLogger(__name__)


class TrialAborted(RunAborted):
    """The trial was aborted by an unexpected error; what it recorded is kept."""


def run_trial(
    seed: int | None = None,
    operator: str = "synthetic",
    replay: Path | None = None,
    out_dir: Path | None = None,
    *,
    max_time: float = MAX_TRIAL_S,
    progress: bool = False,
    force: bool = False,
    project: Project | None = None,
    ctb: str | None = None,
    propulsion: str | None = None,
    retarget_budget: str | None = None,
    retarget_collisions: bool | None = None,
    physics_dt: float | None = None,
    base_filter: bool | None = None,
    link_delay: tuple[float, float] | None = None,
    zones: Any = None,
    controller: str | None = None,
) -> dict[str, Any]:
    """Run one trial and write its folder (reproducible: see :func:`_run_trial`).

    The numerical libraries run single-threaded during the trial: multi-threaded BLAS
    sums in a different order, and the contact dynamics amplify the last-bit
    differences, so the same seed would otherwise give slightly different trials in a
    campaign worker and in a terminal.

    Args:
        seed: Seed of the synthetic operator (default 0). A replay records its source's
            seed; a seed given with a replay is only a label.
        operator: ``synthetic`` or ``replay``.
        replay: The hand recording (``hands.jsonl``) to replay.
        out_dir: Trial folder (default: a new ``runs/trial-<seed>[-k]``). It must not
            hold a trial already unless ``force``; a replay never writes into the folder
            it reads from.
        max_time: Cap on the session length [s].
        progress: Show a progress bar.
        project: The design project whose models and design the trial runs on (default:
            the current project).
        ctb: CTB model (:data:`~payload.sim.world.CTB_MODELS`).
        propulsion: ``nozzles`` or ``box``.
        retarget_budget: Evaluation budget of the pair solves (``paper``: at most 20
            residual evaluations each; ``converged``), recorded with the trial.
        retarget_collisions: Self-collision modelled in the pair solves (off: the
            paper's controller), recorded with the trial.
        physics_dt: Physics time step [s] (default 0.001, the paper's 1 kHz; an opt-in
            0.002 is faster), recorded with the trial.
        controller: The controller profile (:mod:`payload.profiles`, default ``paper``)
            the two settings above override, recorded with the trial and the settings
            it overrides.

            Each of these five left at ``None`` is the default (single CTB, nozzles,
            ``paper``, off) or, for a replay, its recording's setting (the default where
            the recording has none); a value given replays the recorded hands on that
            setup instead.
        base_filter: The base safety filter between the base channel and the vehicle
            (``None``: off, or a replay's recorded setting).
        link_delay: (delay, jitter) [s] of a delayed ground link between the operator
            and the robot (:mod:`payload.teleop.link`); never taken from a replay (its
            recorded frames are what the robot received).
        zones: Keep-in and keep-out boxes of the filter
            (:class:`~payload.sim.zones.StationZones`; default: the station's, or for a
            replay with the filter on, the zones its recording ran), recorded with the trial.
        force: Replace the trial in ``out_dir`` (each file through a temporary file and a
            rename, after the new trial has run).

    Returns:
        The metrics (as written to ``metrics.json``).

    Raises:
        TrialError: Bad arguments, an unreadable replay, or ``out_dir`` holds a trial.
        TrialAborted: An unexpected error ended the session; the recording is kept,
            marked aborted, and not scored.
    """
    if operator not in ("synthetic", "replay"):
        raise TrialError(f"operator must be 'synthetic' or 'replay', got {operator!r}")
    project = project or current_project()
    header: dict[str, Any] = {}
    frames: list[Any] = []
    named: list[str] = []
    if operator == "replay":
        if replay is None:
            raise TrialError("operator 'replay' needs a hand recording file")
        if out_dir is not None and Path(out_dir).resolve() == Path(replay).resolve().parent:
            # before the recording is read: its warnings (a run that did not finish) would
            # come before this refusal
            raise TrialError(f"{out_dir}: a replay never writes into the folder it reads from")
        header, frames = load_replay(replay)
        recorded = header.get("meta") or {}
        # the settings the replayed recording names (a bare hands.jsonl: none)
        # (the link delay is never taken from it: a replay is what the robot received)
        named = [name for name in RUN_SETTINGS if name in recorded and name != "link_delay"]
        if controller is not None:  # the given profile's settings are its own
            named = [name for name in named if name not in PROFILE_SETTINGS]
        ctb = recorded.get("ctb") if ctb is None else ctb
        propulsion = recorded.get("propulsion") if propulsion is None else propulsion
        # a controller given replays the hands on that profile's settings (those of its
        # settings given as well aside); none given: the recording's profile and settings
        profile_given = controller is not None  # (so named leaves its settings out)
        if controller is None and isinstance(recorded.get("controller"), str):
            controller = recorded["controller"]
        if retarget_budget is None and not profile_given:
            retarget_budget = recorded.get("retarget_budget")
        if retarget_collisions is None and not profile_given:
            # not recorded (a bare hands.jsonl): the controller profile's default
            retarget_collisions = recorded.get("retarget_collisions")
            if retarget_collisions is not None and not isinstance(retarget_collisions, bool):
                raise TrialError(
                    f"{replay}: retarget_collisions must be true or false, "
                    f"got {retarget_collisions!r}"
                )
        if physics_dt is None:
            physics_dt = recorded.get("physics_dt")
            if physics_dt is not None and (
                isinstance(physics_dt, bool) or not isinstance(physics_dt, (int, float))
            ):
                raise TrialError(f"{replay}: physics_dt must be a number, got {physics_dt!r}")
        if base_filter is None and "base_filter" in recorded and not profile_given:
            base_filter = bool(recorded["base_filter"])
        if seed is None:
            source_seed = header.get("meta", {}).get("seed")
            seed = source_seed if isinstance(source_seed, int) and source_seed >= 0 else 0
    seed = 0 if seed is None else int(seed)
    try:
        setup = trial_setup(
            ctb,
            propulsion,
            retarget_budget,
            retarget_collisions,
            physics_dt,
            base_filter=base_filter,
            link_delay=link_delay,
            controller=controller,
        )
    except PayloadError as exc:
        raise TrialError(str(exc)) from None
    if zones is not None and not setup["base_filter"]:  # a replay's setting is known here
        raise TrialError(f"--zones: {ZONES_WITHOUT_FILTER}")
    if zones is None and setup["base_filter"]:  # a replay's recorded zones (None: the station's)
        zones = replay_zones(header, replay)
    if "zones" in (header.get("meta") or {}):  # the recording says which zones it ran
        named.append("zones")
    problem = check_physics_dt(setup["physics_dt"])
    if problem is not None:
        raise TrialError(f"physics_dt: {problem}")
    ctb, propulsion = setup["ctb"], setup["propulsion"]
    if ctb not in CTB_MODELS:
        raise TrialError(f"ctb must be one of {', '.join(CTB_MODELS)}, got {ctb!r}")
    if propulsion not in PROPULSION_MODELS:
        raise TrialError(
            f"propulsion must be one of {', '.join(PROPULSION_MODELS)}, got {propulsion!r}"
        )
    stem = trial_dir("", seed).name if operator == "synthetic" else f"replay-{seed:04d}"
    out = Path(out_dir) if out_dir is not None else new_folder(project.runs_dir, stem)
    campaign = held(out, CAMPAIGN_FILES)
    if campaign:  # --force replaces a trial, never a campaign
        raise TrialError(
            f"{out}: holds a campaign ({', '.join(campaign)}); a trial goes in a folder of its own "
            "(choose another --out)"
        )
    if force and (out / HANDS).exists() and not _older_trial(out):
        raise TrialError(
            f"{out}: holds a live session's or a hardware run's hands ({HANDS}); --force "
            "replaces only a trial (choose another --out)"
        )
    existing = [out / name for name in TRIAL_FILES]
    try:
        check_new(existing, force=force, what="trial")
    except OverwriteError as exc:
        raise TrialError(str(exc)) from None
    out.mkdir(parents=True, exist_ok=True)
    source = _Source(
        operator,
        seed,
        replay,
        header,
        frames,
        **setup,
    )
    source.zones = zones
    replayed = {"replay_setup_recorded": named} if operator == "replay" else {}
    with single_threaded_numerics():
        if not force:
            result = _run_trial(
                seed, source, out, max_time=max_time, progress=progress, project=project
            )
            return {**result, "out_dir": str(out), **replayed}
        staging = Path(tempfile.mkdtemp(prefix=".trial-", dir=out))
        made = False  # whether the new trial replaces the old one
        try:
            result = _run_trial(
                seed, source, staging, max_time=max_time, progress=progress, project=project
            )
            made = True
            return {**result, "out_dir": str(out), **replayed}
        except TrialAborted as exc:  # its recording (marked aborted) is this run's record
            made = _recorded_steps(staging / RECORDING)
            if made:  # the recording's path once it is in place
                moved = str(exc).replace(str(staging / RECORDING), str(out / RECORDING))
                raise TrialAborted(moved) from exc.__cause__
            what = str(exc).split("; recording kept")[0]  # before its first step
            raise TrialAborted(
                f"{what}; nothing recorded, the trial already in {out} is kept"
            ) from exc.__cause__
        except Exception:
            made = _recorded_steps(staging / RECORDING)
            raise
        except KeyboardInterrupt as exc:  # the interrupted run's recording goes with staging
            exc.__notes__ = [
                f"nothing recorded: the trial already in {out} is kept whole"
                if any(p.exists() for p in existing)
                else "nothing recorded (an interrupted --force run keeps no partial recording)"
            ]
            raise
        finally:  # replaced file by file; an interrupt (Ctrl-C) keeps the old trial whole
            if made:
                from payload.trials.scoring import rescorings

                for name in TRIAL_FILES:
                    if (staging / name).exists():
                        os.replace(staging / name, out / name)
                    else:
                        (out / name).unlink(missing_ok=True)
                for stale in rescorings(out, SCORED):  # they scored the old recording
                    stale.unlink()
            shutil.rmtree(staging, ignore_errors=True)


def _older_trial(out: Path) -> bool:
    """Whether the ``hands.jsonl`` in ``out`` is an older trial's (schema version 1 wrote
    its hands there: its ``log.mcap`` is of that version, or was converted and kept it as
    its backup), not a live session's or a hardware run's (which record them beside a
    current recording)."""
    from payload.trials.convert import BACKUP_NAME
    from payload.trials.reading import RecordingError, recording_version

    if (out / BACKUP_NAME).exists():
        return True
    try:
        return recording_version(out / RECORDING) == 1
    except (OSError, RecordingError):
        return False  # unreadable: not known to be a trial, so not replaced


def _recorded_steps(path: Path) -> bool:
    """Whether the recording at ``path`` holds a step (a recorder opened for a trial that
    failed before its first step holds none, and the reader refuses it)."""
    from payload.trials.reading import RecordingError, recording_version

    try:
        recording_version(path)
    except (OSError, RecordingError):
        return False
    return True


def _record_session(
    driver: Any,
    seed: int,
    source: Any,
    setup: TrialSetup,
    make_pipeline: Callable[[Captures, float], TeleopPipeline],
    rec_path: Path,
    meta: dict[str, Any],
    *,
    max_time: float,
    progress: bool,
    replayed: dict[str, Any],
) -> tuple[LoopStats, Recording | None]:
    """Run the teleoperation session, recording every step into ``rec_path``; returns the
    session's statistics and the recording as the reader reads it back (``None`` when no
    step was recorded). An unexpected error marks the recording aborted."""
    from payload.trials.recorder import RecordingError, TrialRecorder
    from payload.trials.safety import recording_scene

    layout = driver.world.layout
    bar = None
    if progress:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        # simulated time against the --max-time cap: a trial ends when its task is done,
        # most of them well before the cap, so the bar's end is the cap's, not the trial's
        bar = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.0f} s simulated, the cap {task.total:.0f} s"),
            TimeElapsedColumn(),
            transient=True,
        )
        task = bar.add_task(f"seed {seed}", total=max_time)
        bar.start()
    try:
        scene = recording_scene(driver, module_rects(layout))
        with TrialRecorder(rec_path, scene=scene, keep=True) as recorder:
            recorder.write_meta(meta)

            def on_step(ctx: StepContext) -> None:
                recorder.write_hands(ctx.frame)
                scene.observe(ctx.t)
                # the step record is made at the recorder's next flush, with its batch
                recorder.write_later(ctx.t, step_record, ctx, driver, setup.retargeters)
                if bar is not None:
                    bar.update(task, completed=ctx.t)

            try:
                stats = run_session(
                    driver,
                    source,
                    setup.calibration,
                    make_pipeline,
                    max_time=max_time,
                    on_step=on_step,
                    world_view=world_view(driver),
                )
                recorder.flush()  # every step made and written: the scene's figures count all
            except Exception as exc:
                what, at = recorder.mark_aborted(exc)
                # the traceback is in the recording; a command says the one line raised below
                log.info("trial %s aborted at t = %.2f s", seed, at, exc_info=True)
                raise TrialAborted(
                    f"trial {seed} aborted at t = {at:.2f} s by {what}; recording "
                    f"kept (marked aborted, not scored): {rec_path}"
                ) from exc
            recorder.write_meta(closing_meta(driver, source, stats, scene, replayed))
    finally:
        if bar is not None:
            bar.stop()
        driver.close()
    try:
        return stats, recorder.recording()
    except RecordingError:  # no step recorded: scoring reads the file, and says what is wrong
        return stats, None


def _run_trial(
    seed: int,
    source_spec: _Source,
    out: Path,
    *,
    max_time: float = MAX_TRIAL_S,
    progress: bool = False,
    project: Project,
) -> dict[str, Any]:
    """Run one trial and write its folder ``out`` (arguments: :func:`run_trial`): set up
    the world and the operator, record the session, score the recording."""
    from payload.sim.driver import SimDriver
    from payload.trials.scoring import finish_trial, write_metrics

    driver = SimDriver(
        WorldConfig.for_project(project, ctb=source_spec.ctb, physics_dt=source_spec.physics_dt),
        propulsion=source_spec.propulsion,
    )
    setup = set_up_trial(driver, seed, source_spec, project)
    if source_spec.base_filter:
        driver.twist_filter = base_filter_for(driver, setup.config.base, source_spec.zones)
    source, traits = source_spec.make(setup.plan, setup.calibration)
    q0 = driver.read().q

    def make_pipeline(captures: Captures, heading: float) -> TeleopPipeline:
        cal = calibrate_operator(captures, setup.ranges, setup.config.rail_travel, heading)
        return TeleopPipeline(cal, setup.retargeters, setup.config, initial=q0)

    prov = {**provenance(project, driver.world.config.design), "environment": environment()}
    rec_path = out / RECORDING
    meta = trial_meta(seed, source_spec, traits, prov, driver.world.layout, setup)
    stats, recording = _record_session(
        driver,
        seed,
        source,
        setup,
        make_pipeline,
        rec_path,
        meta,
        max_time=max_time,
        progress=progress,
        replayed=source_spec.recorded,
    )
    # scored with the contact definition it recorded, from what was written (the arrays
    # the file reads back as, without reading it)
    result = finish_trial(out, rec_path, recording=recording)
    result["steps"] = stats.steps
    result["provenance"] = prov
    write_metrics(out, result)
    return result


__all__ = [
    "MAX_TRIAL_S",
    "MODULE_NAMES",
    "TRIAL_FILES",
    "HeadsetSource",
    "TrialAborted",
    "TrialError",
    "base_filter_for",
    "design_hash",
    "load_replay",
    "module_rects",
    "place_ctb_for_teleop",
    "retargeting",
    "run_trial",
    "single_threaded_numerics",
    "step_record",
]
