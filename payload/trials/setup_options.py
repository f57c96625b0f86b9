"""The trial setup options shared by ``payload trial``, ``trials run`` and ``bench trial``
(CTB, propulsion, controller profile and its overrides, physics step, base filter, zones,
link delay), their checks and the seeds', and the resolution of the ones left out
(:func:`payload.trials.sources.trial_setup`)."""

from __future__ import annotations

import argparse
import math
from typing import Any

from payload.cliutil import warn
from payload.errors import PayloadError
from payload.rates import CONTROL_DT, PHYSICS_DT

MAX_TRIAL_S = 240.0
"""A trial session's default length cap [s] (``--max-time``)."""

MAX_SEED = 2**63 - 1
"""The largest trial seed: seeds are 64-bit signed integers, as the LeRobot export's seed
column (Parquet's int64) stores them."""


def seed_problem(seed: int, count: int = 1) -> str | None:
    """What is wrong with the ``count`` trial seeds ``seed, seed + 1, ...``, or None: each
    must be an integer from 0 to :data:`MAX_SEED`."""
    if seed < 0:
        return f"must be >= 0, got {seed}"
    if seed + count - 1 > MAX_SEED:
        if count == 1:
            return f"must be at most {MAX_SEED} (2^63 - 1), got {seed}"
        return (
            f"must be at most {MAX_SEED - count + 1} for {count} trials (their seeds run to "
            f"{seed + count - 1}, past 2^63 - 1), got {seed}"
        )
    return None


def _seconds_argument(p: argparse.ArgumentParser, flag: str, text: str) -> None:
    """An optional ``flag S`` option in seconds (None when left out)."""
    p.add_argument(flag, type=float, default=None, metavar="S", help=text)


def _max_time_argument(p: argparse.ArgumentParser, what: str = "session") -> None:
    """``--max-time S``: a cap on each trial's session (``payload trial``, ``trials run``)."""
    _seconds_argument(
        p,
        "--max-time",
        f"cap on {what} length [s] (default {MAX_TRIAL_S:g}; a capped trial is recorded "
        "as stopped by the cap)",
    )


def cap_before_teleoperation(max_time: float | None) -> None:
    """Warn when ``--max-time`` ends each session before its operator's calibration does
    (the default calibration's prompts): such a trial records no teleoperation at all.
    Said after the run, so that no bad input's one line follows it."""
    if max_time is None:
        return
    from payload.teleop.calibration import CalibrationProcedure

    calibration = CalibrationProcedure().duration
    if max_time <= calibration:
        warn(
            f"--max-time {max_time:g} s ends each session before the operator's calibration "
            f"does ({calibration:g} s): no teleoperation is recorded"
        )


class TrialsCliError(PayloadError):
    """Bad arguments to a trials command, or the trial runner is not available."""


RUN_SETTINGS = (
    "ctb",
    "propulsion",
    "retarget_budget",
    "retarget_collisions",
    "physics_dt",
    "base_filter",
    "link_delay",
    "controller",
)
"""The settings of :func:`payload.trials.sources.trial_setup` a trial runs with
(``run_trial``'s keywords); the rest (``controller_overrides``) is what its record says of
them."""

_SETUP = tuple(name for name in RUN_SETTINGS if name != "link_delay")
"""The trial setup flags' attribute names (the link delay's is parsed apart)."""


def _setup_arguments(p: argparse.ArgumentParser, *, replay: bool = False) -> None:
    """The trial setup flags; with ``replay`` each left out means "the recording's" for a
    replay (``None`` here, resolved by the runner)."""
    from payload.profiles import PAPER, PROFILES
    from payload.sim.vehicle import DEFAULT_PROPULSION, PROPULSION_MODELS

    mine = "; a replay: its recording's unless given" if replay else ""
    p.add_argument(
        "--controller",
        choices=tuple(PROFILES),
        default=None,
        help=f"controller profile (default {PAPER}{mine}): 'paper' is the paper's "
        "controller (20-evaluation pair solves, no self-collision model); 'safe' adds the "
        "contact-aware self-collision model and the base safety filter; "
        "--retarget-budget, --[no-]retarget-collisions and --[no-]base-filter override it",
    )
    p.add_argument(
        "--ctb",
        default=None,
        help="CTB model: single (NASA's loaded single bag) or rigid (the rigid bag of "
        f"Morton et al.); default single{mine}",
    )
    p.add_argument(
        "--propulsion",
        choices=PROPULSION_MODELS,
        default=None,
        help=f"vehicle propulsion model (default {DEFAULT_PROPULSION}{mine})",
    )
    p.add_argument(
        "--retarget-budget",
        choices=("paper", "converged"),
        default=None,
        help="retargeting budget per pair solve: 'paper' (at most 20 residual evaluations, "
        "the paper's controller) or 'converged' (each start run to convergence); default: "
        f"the --controller profile's{mine}",
    )
    p.add_argument(
        "--retarget-collisions",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="model self-collision in the pair solves: no command closer than the design's "
        "margin (the pads of a pair excepted), the operator's opening mapped to the "
        f"collision-free span range (default: the --controller profile's{mine})",
    )
    _physics_dt_argument(p, mine)
    p.add_argument(
        "--base-filter",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the base safety filter between the base channel and the vehicle (default: "
        f"the profile's; off in 'paper'{mine})",
    )
    p.add_argument(
        "--zones",
        default=None,
        metavar="FILE",
        help="keep-in/keep-out boxes of the base filter, Astrobee zone JSON (default: the "
        "station's, from the simulator's ISS layout)",
    )
    p.add_argument(
        "--link-delay",
        default=None,
        metavar="S[:JITTER]",
        help="a delayed ground link: hand frames reach the robot and its state reaches the "
        "operator S seconds late (each message +-JITTER, uniform); default none",
    )


def _physics_dt_argument(p: argparse.ArgumentParser, mine: str = "") -> None:
    _seconds_argument(
        p,
        "--physics-dt",
        f"physics time step [s]: {PHYSICS_DT:g} (default, the paper's "
        f"{1e-3 / PHYSICS_DT:g} kHz{mine}) or an opt-in faster step that divides the "
        f"{1e3 * CONTROL_DT:g} ms control period, e.g. {2 * PHYSICS_DT:g} (the pad contact "
        "is derived from the step; results differ from the default)",
    )


VALIDATED_PHYSICS_DT = 2 * PHYSICS_DT
"""The largest step validated against the paper's (``make validate-physics-dt``,
``analyses/physics-dt/compare.md``)."""


def physics_dt_note(dt: float) -> str | None:
    """What a user should know of a usable step that is not one of the two validated ones
    (None: the paper's or the validated faster one): a smaller one only costs time, any
    other larger one was never checked against the paper's."""
    if dt < PHYSICS_DT:
        return (
            f"--physics-dt {dt:g}: {PHYSICS_DT / dt:g} times the paper's {1e-3 / PHYSICS_DT:g} "
            "kHz steps, so the physics takes about as many times longer"
        )
    if not (math.isclose(dt, PHYSICS_DT) or math.isclose(dt, VALIDATED_PHYSICS_DT)):
        return (
            f"--physics-dt {dt:g}: not validated (only {VALIDATED_PHYSICS_DT:g} s was, "
            "analyses/physics-dt/compare.md); contact and the trial's results may differ "
            "from the paper's step by more than that table shows"
        )
    return None


def _check_physics_dt(dt: float | None) -> None:
    from payload.sim.config import check_physics_dt

    problem = None if dt is None else check_physics_dt(dt)
    if problem is not None:
        raise TrialsCliError(f"--physics-dt: {problem}")
    note = None if dt is None else physics_dt_note(dt)
    if note is not None:
        warn(note)


ZONES_WITHOUT_FILTER = (
    "the zones are the base filter's, and it is off in this run (the profile's setting, or "
    "a replayed recording's): add --base-filter (or --controller safe), or leave --zones out"
)
"""Why ``--zones`` is refused with the base filter off (the command line's check, and the
runner's for a replay, whose setting only its recording says)."""


def _link_and_zones(args: argparse.Namespace) -> dict[str, Any]:
    """The parsed ``--link-delay`` and ``--zones`` as run_trial arguments (bad input: one
    line, exit 2). The zones are the base filter's: refused with the filter off (a
    replay's setting, None here, is its recording's), and when the vehicle's start is not
    in their free space (the filter would keep it from nothing)."""
    from payload.sim.iss import IssLayout
    from payload.sim.zones import StationZones
    from payload.teleop.link import parse_link_delay

    extra: dict[str, Any] = {}
    if args.link_delay is not None:
        extra["link_delay"] = parse_link_delay(args.link_delay)
    if args.zones is not None:
        if args.base_filter is False:
            raise TrialsCliError(f"--zones {args.zones}: {ZONES_WITHOUT_FILTER}")
        try:
            zones = StationZones.read(args.zones)
        except PayloadError as exc:  # the file's own line, naming the option it came from
            raise TrialsCliError(f"--zones: {exc}") from None
        start = IssLayout().start()
        if not zones.contains(start):
            x, y, z = start.tolist()
            raise TrialsCliError(
                f"--zones {args.zones}: the vehicle starts at ({x:.2f}, {y:.2f}, {z:.2f}) m, "
                "outside the file's keep-in boxes or inside a keep-out box: the base filter "
                "would keep it from nothing"
            )
        extra["zones"] = zones
    return extra


def _setup_defaults(args: argparse.Namespace) -> None:
    """Fill the setup flags left out with the defaults (synthetic trials, campaigns)."""
    from payload.trials.sources import trial_setup

    try:
        setup = trial_setup(**{n: getattr(args, n) for n in _SETUP})
    except PayloadError as exc:
        raise TrialsCliError(str(exc)) from None
    for name, value in setup.items():
        if name in _SETUP:
            setattr(args, name, value)


def _check_ctb(ctb: str) -> None:
    from payload.errors import closest
    from payload.sim.world import CTB_MODELS

    if ctb not in CTB_MODELS:
        near = closest(ctb, CTB_MODELS)  # as argparse's choices get it
        hint = f" (did you mean {near!r}?)" if near else ""
        raise TrialsCliError(f"--ctb: expected one of {', '.join(CTB_MODELS)}, got {ctb!r}{hint}")
