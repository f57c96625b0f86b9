"""Where a trial's hand frames come from: the synthetic operator behind a headset that
reports on the recorder's grid, or a replayed recording."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.profiles import PAPER, resolve
from payload.schema import PHYSICS_DT
from payload.sim.vehicle import DEFAULT_PROPULSION
from payload.sim.world import DEFAULT_CTB
from payload.sim.zones import StationZones, ZoneError
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.hands import Hand, HandFrame
from payload.teleop.link import DelayedLink
from payload.teleop.loop import ReplaySource, SyntheticSource
from payload.teleop.operator import OperatorPlan, SyntheticOperator, WorldView
from payload.teleop.replay import read_hand_recording
from payload.trials.jointcodec import quantize_joints

log = logging.getLogger(__name__)


class TrialError(PayloadError):
    """A trial could not be run (bad operator choice, unreadable replay)."""


def trial_setup(
    ctb: str | None = None,
    propulsion: str | None = None,
    retarget_budget: str | None = None,
    retarget_collisions: bool | None = None,
    physics_dt: float | None = None,
    base_filter: bool | None = None,
    link_delay: tuple[float, float] | None = None,
    controller: str | None = None,
) -> dict[str, Any]:
    """A trial's setup with each setting left at ``None`` given its default: the single
    CTB, nozzle propulsion, the paper's 1 kHz physics (``physics_dt`` [s]), no link delay
    (``link_delay``: (delay, jitter) [s]) and the controller profile's
    (:mod:`payload.profiles`; default ``paper``: the paper's retargeting budget,
    self-collision not modelled, no base safety filter).

    ``controller_overrides`` names the profile settings the given flags change (a flag
    equal to the profile's own setting is no override), so the same setup resolved twice
    reads the same.
    """
    prof, overrides = resolve(
        controller,
        PAPER,
        retarget_budget=retarget_budget,
        retarget_collisions=retarget_collisions,
        base_filter=base_filter,
    )
    return {
        "ctb": DEFAULT_CTB if ctb is None else ctb,
        "propulsion": DEFAULT_PROPULSION if propulsion is None else propulsion,
        "retarget_budget": prof.retarget_budget,
        "retarget_collisions": bool(prof.retarget_collisions),
        "physics_dt": PHYSICS_DT if physics_dt is None else float(physics_dt),
        "base_filter": bool(prof.base_filter),
        "link_delay": None if link_delay is None else [float(v) for v in link_delay],
        "controller": prof.name,
        "controller_overrides": overrides,
    }


class HeadsetSource:
    """A hand source whose joint positions are reported on the recorder's grid.

    Args:
        source: The source (the synthetic operator).
        grid: Resolution of the reported positions [m].
    """

    def __init__(self, source: Any, grid: float) -> None:
        self.source = source
        self.grid = grid

    def frame(self, t: float, world: WorldView | None) -> HandFrame | None:
        if type(self.source) is SyntheticSource:  # it draws the hands on the grid itself
            return self.source.frame(t, world, self.grid)
        fr = self.source.frame(t, world)
        if fr is None:
            return None
        hands = [
            Hand.taking(quantize_joints(h.joints, self.grid)) if h.tracked else h
            for h in (fr.left, fr.right)
        ]
        return HandFrame(fr.stamp, hands[0], hands[1], fr.frame)

    @property
    def finished(self) -> bool:
        return self.source.finished

    @property
    def operator(self) -> Any:
        """The synthetic operator behind the headset (``None`` for other sources)."""
        return getattr(self.source, "operator", None)


def load_replay(path: str | Path) -> tuple[dict[str, Any], list[HandFrame]]:
    """``(header, frames)`` to replay: a trial's ``log.mcap`` (its ``/trial/hands``
    channel) or a ``hands.jsonl``; the header's ``meta`` names the source's seed. The
    frames are in the workbench convention, as a trial records them: a live session's
    ``hands.jsonl`` (WebXR's convention) converted as the pipeline converts each frame."""
    from payload.trials.reading import read_hand_frames_of_run
    from payload.trials.recorder import RecordingError

    if Path(path).suffix == ".mcap":
        try:
            meta, frames, unfinished = read_hand_frames_of_run(path)
        except RecordingError as exc:
            raise TrialError(str(exc)) from None
        header = {"meta": meta}
        if unfinished is not None and frames:
            # replayed as asked, but not as if it were a whole run's hands
            header["unfinished"] = unfinished
            log.warning(
                "%s: a run that did not finish, %s; the replay ends where it stopped, %.1f s in",
                path,
                unfinished,
                frames[-1].stamp - frames[0].stamp,
            )
    else:
        header, frames = read_hand_recording(path)
    if not frames:
        where = (
            "its /trial/hands channel holds none, as in a live session's or `payload hw "
            "run`'s recording made before this release: replay the hands.jsonl beside it"
            if Path(path).suffix == ".mcap"
            else "the file holds none"
        )
        raise TrialError(f"{path}: no hand frames to replay ({where})")
    return header, [frame.to_workbench() for frame in frames]


def replay_zones(header: dict[str, Any], replay: Path | None) -> StationZones | None:
    """The base filter's zones a replayed recording ran (``None``: the station's, or a
    recording that does not say).

    Raises:
        TrialError: The recorded zones are not the zone form.
    """
    try:
        return StationZones.recorded(header.get("meta") or {})
    except ZoneError as exc:
        raise TrialError(f"{replay}: recorded {exc}") from None


class _Source:
    """Where a trial's hand frames come from, and what its recording says about it."""

    def __init__(
        self,
        operator: str,
        seed: int,
        replay: Path | None,
        header: dict[str, Any],
        frames: list[Any],
        *,
        ctb: str,
        propulsion: str,
        retarget_budget: str,
        retarget_collisions: bool,
        physics_dt: float,
        base_filter: bool = False,
        link_delay: list[float] | None = None,
        controller: str = PAPER,
        controller_overrides: list[str] | None = None,
    ) -> None:
        self.physics_dt = physics_dt
        self.base_filter = base_filter
        self.link_delay = link_delay
        self.zones: StationZones | None = None  # the filter's zones (None: the station's)
        self.retarget_budget = retarget_budget
        self.retarget_collisions = retarget_collisions
        self.controller = controller
        self.controller_overrides = list(controller_overrides or [])
        self.ctb = ctb
        self.propulsion = propulsion
        self.recorded: dict[str, Any] = header.get("meta") or {}
        self.operator = operator
        self.seed = seed
        self.replay = replay
        self.header = header
        self.frames = frames

    def make(self, plan: OperatorPlan, calibration: CalibrationProcedure) -> tuple[Any, dict]:
        """The hand source and the operator traits to record; behind the delayed link
        when the trial has one (a replay is what the robot received: never delayed again
        unless asked)."""
        if self.operator == "synthetic":
            synthetic = SyntheticOperator(plan, self.seed, calibration)
            from payload.trials.codec import HAND_GRID_M

            source: Any = HeadsetSource(SyntheticSource(synthetic), HAND_GRID_M)
            traits = dict(vars(synthetic.traits))
        else:
            source, traits = ReplaySource(self.frames), {"replay": str(self.replay)}
        if self.link_delay is not None and self.link_delay[0] > 0:
            source = DelayedLink(source, *self.link_delay, seed=self.seed)
        return source, traits

    def meta(self) -> dict[str, Any]:
        """Recording metadata naming a replay's source file and seed."""
        if self.replay is None:
            return {}
        return replay_meta(self.replay, self.header, self.frames)


def replay_meta(replay: str | Path, header: dict[str, Any], frames: list[Any]) -> dict[str, Any]:
    """A replay's recording metadata (``payload trial --replay``, ``hw run``): the source
    file, its hash and seed, its hand frames and their rate, and why the source run did not
    finish (``source_unfinished``, None: it did), which marks the replay as cut short too
    (:func:`payload.trials.reading.cut_reason`)."""
    data = Path(replay).read_bytes()
    return {
        "replay": {
            "file": str(replay),
            "sha256": hashlib.sha256(data).hexdigest(),
            "seed": header.get("meta", {}).get("seed"),
            "frames": len(frames),
            "rate_hz": _rate(frames),
            "source_unfinished": header.get("unfinished"),
        }
    }


def _rate(frames: list[Any]) -> float | None:
    stamps = np.array([f.stamp for f in frames])
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    return float(1.0 / np.median(steps)) if steps.size else None
