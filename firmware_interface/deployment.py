"""The payload out of its bays and back: the deployment ``payload report envelope``
checks, its reverse, and a payload that powers up out of its bays.

The deployment (:func:`move_to_home`): from the stowed posture the stage goes down with
the fingers and the rail held, then the fingers and the rail go straight in joint space
to home. Stowing (:func:`stow`) is its reverse: the fingers and the rail to home (guarded),
straight to the stowed posture, then the stage up. Homing drives the rail and the stage
to their stowed stops whatever the fingers do, so a payload that powers up with its
fingers out (a session ended by a fault or a power loss, stowing skipped) has them
folded first (:func:`fold_before_homing`), along a straight line checked as the
envelope check checks the deployment, the rail at each position its one-turn reading
allows; then the rail is homed, then the stage.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from firmware_interface.control_table import RAD_PER_TICK, TICKS_PER_REV
from firmware_interface.errors import DynamixelError, HomingError
from firmware_interface.servo_map import ServoSpec, posture_command
from payload.design.params import posture_values
from payload.design.tree import ALL_JOINTS
from payload.errors import Terminated
from payload.schema import CONTROL_DT, PayloadCommand, PayloadState

log = logging.getLogger(__name__)

RAIL, STAGE = ALL_JOINTS.index("rail"), ALL_JOINTS.index("stage")
"""The rail's and the stage's places in a servo map (``ALL_JOINTS`` order): the finger
servos are the ones before the rail."""
DEPLOY_SPEED = 0.5
"""The share of each servo's no-load speed at which the payload's goals are stepped at
their fastest (mid-way on :func:`smooth_share`'s profile) while it unfolds, stows or
folds before homing: the joint with the farthest to go sets the motion's time."""
DEPLOY_LAG_RAD = 0.3
"""The most a servo may trail the goal it was sent a control period before while the
payload unfolds, stows or folds [rad of the servo's shaft]: more, and it is held back (a
finger against the bay's wall, a blocked rail), so the motion stops there, naming it."""
STOWED_TOL_RAD = 0.1
"""How far a finger joint may be from the design's stowed posture and still count as
stowed [rad; the rail: the same at its pinion's shaft]: :func:`move_to_home` deploys as
checked from there, and :func:`fold_before_homing` leaves it be."""


def shaft_per_rad(specs: Sequence[ServoSpec]) -> np.ndarray:
    """Joint units per radian of each servo's shaft (the rail: its pinion's gear in)."""
    return np.array([sp.units_per_tick / RAD_PER_TICK for sp in specs])


def farthest_from(
    specs: Sequence[ServoSpec], q: np.ndarray, target: np.ndarray
) -> tuple[str, float]:
    """The joint of ``specs`` farthest from ``target`` at ``q``, and how far [rad of the
    servo's shaft]."""
    off = np.abs(np.asarray(q) - np.asarray(target)) / shaft_per_rad(specs)
    i = int(np.argmax(off))
    return specs[i].joint, float(off[i])


# -- the deployment ---------------------------------------------------------------------------
def move_to_home(hardware: Any, timeout: float = 6.0, cleared: bool = False) -> PayloadState:
    """Drive the brought-up (homed) payload to the design's home posture, where every
    simulated trial starts, and wait until every servo has stopped there.

    From the stowed posture (how the payload powers up in its bays; homing leaves the rail
    and the stage there) it deploys as ``payload report envelope`` checked the deployment:
    the stage down with the fingers and the rail held, then the fingers and the rail
    straight in joint space to home, goals stepped at 50 Hz on :func:`smooth_share`'s
    profile, at most :data:`DEPLOY_SPEED` of the servos' speed (a servo trailing its goal by
    more than :data:`DEPLOY_LAG_RAD` stops it there). Those goals bypass the command guard,
    whose capsule margins flag the stowed posture itself: the envelope check has cleared the
    path with the exact meshes, and a design whose check fails is refused before anything
    moves (``cleared``: the caller has asked, before the bring-up, as ``ready_at_home``
    does). With the stage up and a finger or the rail more than :data:`STOWED_TOL_RAD` from
    stowed, or the stage already down, the goal is home at once, guarded, as it always was
    (the first with a warning).

    A servo with no I gain stops anywhere inside its friction dead band around the goal
    (:func:`payload.design.servo.dead_band_ticks`, 8.5 ticks at P 600): "there" is
    within that band plus one tick (half a tick of the goal's rounding to a whole tick,
    half of Present Position's).

    Returns:
        The measured state at home, every joint at rest.

    Raises:
        DynamixelError: A posture was not reached within ``timeout`` [s], a servo fell
            behind its goal as the payload unfolded, or the design's deployment is not
            clear.
    """
    home = posture_command(hardware.design, "home")
    stowed = posture_command(hardware.design, "stowed")
    if not cleared:
        deployment_cleared(hardware.design)
    start = hardware.read()
    tol = tolerance(hardware)
    if abs(start.deploy - home.deploy) <= tol[-1]:  # the stage down already: out of the bays
        return settle(hardware, home, tol, timeout, "home posture")
    joint, off = farthest_from(hardware.map.servos[:-1], start.q, stowed.q)
    if off > STOWED_TOL_RAD:  # not how the checked deployment starts: as before
        log.warning(
            "%s is %.2f rad from the stowed posture with the stage up (over %s): not the "
            "deployment `payload report envelope` checks, so home at once, guarded, each servo "
            "at its own pace",
            joint,
            off,
            STOWED_TOL_RAD,
        )
        return settle(hardware, home, tol, timeout, "home posture")
    with _unguarded(hardware):
        down = settle(hardware, PayloadCommand(start.q, home.deploy, 0.0), tol, timeout, "stage")
        _ramp_payload(hardware, down.q, home.q, home.deploy, "as the payload unfolds")
        return settle(hardware, home, tol, timeout, "home posture")


def stow(hardware: Any, timeout: float = 6.0) -> PayloadState:
    """The deployment's reverse, from wherever a session left the payload (the stage down):
    the fingers and the rail straight to home under the command guard (as a session's
    goals are checked), then straight in joint space to the stowed posture and the stage
    up with the fingers and the rail held, the path ``payload report envelope`` checked
    (the guard set aside: its capsule margins flag the stowed posture), goals stepped at
    50 Hz as :func:`ramp` steps them (:data:`DEPLOY_LAG_RAD` stops it). First every servo
    comes to rest where it is (the stage down, lowered if it is not, the fingers held).
    The Bus Watchdog is disarmed: the motion is paced by the host, not a session's 50 Hz.

    Returns:
        The measured state stowed, every joint at rest.

    Raises:
        DynamixelError: The design's deployment is not clear (the payload stays where it
            is), a servo fell behind its goal, or a posture was not reached in ``timeout``.
    """
    home = posture_command(hardware.design, "home")
    stowed = posture_command(hardware.design, "stowed")
    hardware.set_watchdog(False)  # the check takes longer than the Bus Watchdog's time
    deployment_cleared(hardware.design)
    tol = tolerance(hardware)
    start = hardware.read()  # at rest where it is first (the stage down, if partway)
    start = settle(hardware, PayloadCommand(start.q, home.deploy, 0.0), tol, timeout, "posture")
    _ramp_payload(hardware, start.q, home.q, home.deploy, "on its way home to stow")
    settle(hardware, home, tol, timeout, "home posture")
    with _unguarded(hardware):
        now = hardware.read()
        _ramp_payload(hardware, now.q, stowed.q, home.deploy, "as the payload folds")
        folded = settle(hardware, PayloadCommand(stowed.q, home.deploy, 0.0), tol, timeout,
                        "stowed posture")  # fmt: skip
        return settle(hardware, PayloadCommand(folded.q, stowed.deploy, 0.0), tol, timeout,
                      "stowed stage")  # fmt: skip


def stow_after_session(hardware: Any, say: Callable[[str], None] | None = None) -> bool:
    """Stow the payload after a session that ran to its end (``hw run``, ``teleop serve
    --driver hardware``): :func:`stow`, ``say`` told first. A payload stopped by a hardware
    fault stays where it stopped, and a stow that stops (a servo held back, a design whose
    deployment is no longer clear, the bus lost, a Ctrl-C: the payload holds where it is)
    is a warning, not a failed run: the session is recorded whole. Whether it is stowed."""
    if getattr(hardware, "fault", None) is not None:
        log.warning("the payload is not stowed: stopped by %s", hardware.fault)
        return False
    if say is not None:
        say("stowing the payload (the deployment's reverse)")
    try:
        stow(hardware)
    except DynamixelError as exc:
        log.warning("the payload is not stowed: %s", exc)
        return False
    except KeyboardInterrupt as exc:  # the motion stops; after a Ctrl-C, scored still
        try:
            now = hardware.read()
            hardware.send(PayloadCommand(now.q, now.deploy, 0.0))
        except DynamixelError:
            pass
        if isinstance(exc, Terminated):  # a SIGTERM or SIGHUP: the command stops
            raise
        log.warning(
            "stowing interrupted (Ctrl-C): the payload holds where it is (the next bring-up "
            "folds the fingers before homing)"
        )
        return False
    return True


def deployment_cleared(design: Any) -> None:
    """Refuse a design whose deployment ``payload report envelope`` does not clear."""
    from payload.envelope.stowed_fit import design_failures
    from payload.errors import first_of

    failures = design_failures(design)  # the design the driver holds, not its file now
    if failures:
        raise DynamixelError(
            f"the design's deployment is not clear ({first_of(failures, 1)}; `payload report "
            "envelope`): the payload stays where it is"
        )


class _unguarded:
    """The command guard set aside (the envelope check has cleared the path), back after
    with its last safe command where the servos are (none if they cannot be read)."""

    def __init__(self, hardware: Any) -> None:
        self.hardware = hardware
        self.guard = getattr(hardware, "guard", None)

    def __enter__(self) -> None:
        self.hardware.guard = None

    def __exit__(self, *exc: object) -> None:
        self.hardware.guard = self.guard
        if self.guard is None:
            return
        self.guard.reset(None)
        try:
            now = self.hardware.read()
            self.guard.reset(np.append(now.q, now.deploy))
        except Exception as err:  # the motion's own error is the one to say
            log.warning("could not read the posture to reset the command guard: %s", err)


def _ramp_payload(
    hardware: Any, start: np.ndarray, goal: np.ndarray, deploy: float, during: str
) -> None:
    """The fingers and the rail from ``start`` to ``goal`` on a straight line, the stage
    held at ``deploy``, through the driver's ``send`` (guarded if its guard is on)."""
    specs = hardware.map.servos[:-1]  # the 17

    def send(q: np.ndarray) -> None:
        hardware.send(PayloadCommand(q, deploy, 0.0))

    ramp(send, lambda: hardware.read().q, start, goal, specs, hardware.design, during)


def ramp(
    send: Callable[[np.ndarray], None],
    read: Callable[[], np.ndarray],
    start: np.ndarray,
    goal: np.ndarray,
    specs: Sequence[ServoSpec],
    design: Any,
    during: str,
) -> None:
    """Goals from ``start`` to ``goal`` (the joints of ``specs``) on a straight line in
    joint space, stepped at 50 Hz along it as :func:`smooth_share` times them (at rest at
    both ends: a goal stopped at once from speed left the servos to overshoot it), no
    servo faster than :data:`DEPLOY_SPEED` of its no-load speed; a servo trailing its
    goal by more than :data:`DEPLOY_LAG_RAD` a period after it went out stops the motion
    where the servos are (``during`` says when)."""
    per_rad = shaft_per_rad(specs)
    speed = design.servo.no_load_speed * per_rad * DEPLOY_SPEED
    start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    seconds = float(np.max(np.abs(goal - start) / speed))  # the farthest joint's, at speed
    steps = max(1, math.ceil(SMOOTH_PEAK * seconds / CONTROL_DT))
    due = time.monotonic()
    for k in range(1, steps + 1):
        s = smooth_share(k / steps)
        target = (1 - s) * start + s * goal
        send(target)
        now = time.monotonic()  # a late period is not caught up (goals in a burst: off the line)
        due = max(due + CONTROL_DT, now)
        time.sleep(due - now)
        lag = np.abs(read() - target) / per_rad  # a period after the goal went out
        if np.any(lag > DEPLOY_LAG_RAD):  # held back: hold where it is, say which
            send(read())
            i = int(np.argmax(lag))
            raise DynamixelError(
                f"{specs[i].joint} trails its goal by {lag[i]:.2f} rad (over {DEPLOY_LAG_RAD}) "
                f"{during}: held back? the payload holds where it is"
            )


SMOOTH_PEAK = 30.0 * 0.5**2 * (1.0 - 0.5) ** 2  # the profile's rate 30 tau^2 (1 - tau)^2 at 1/2
"""The largest rate of :func:`smooth_share` (at the middle), over its mean: a motion timed
by it takes this much longer than one at its peak speed throughout."""


def smooth_share(tau: float) -> float:
    """The share of the way along a motion at ``tau`` of its time: ``10 tau^3 - 15 tau^4
    + 6 tau^5``, the minimum-jerk profile (at rest, unaccelerated, at both ends; its rate
    at most :data:`SMOOTH_PEAK`)."""
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def tolerance(hardware: Any) -> np.ndarray:
    """Each servo's "there" (see :func:`move_to_home`), in joint units, map order."""
    from payload.design.servo import dead_band_ticks, kind_of

    band = [dead_band_ticks(hardware.design, kind_of(s.joint)) + 1.0 for s in hardware.map.servos]
    return np.array([s.units_per_tick for s in hardware.map.servos]) * band


def settle(
    hardware: Any, cmd: PayloadCommand, tol: np.ndarray, timeout: float, what: str
) -> PayloadState:
    """Send ``cmd`` until every servo has stopped within ``tol`` of it (of its joint's
    limit, for a value past one); the state there."""
    specs = hardware.map.servos
    lower, upper = np.array([s.lower for s in specs]), np.array([s.upper for s in specs])
    # where the servos are sent: inside the joints' limits, as the driver's send clips a
    # command (a posture read past a limit, a servo overshooting it, is sent to the limit)
    target = np.clip(np.append(cmd.q, cmd.deploy), lower, upper)
    t0 = time.monotonic()
    last = None
    while time.monotonic() - t0 < timeout:
        hardware.send(cmd)
        state = hardware.read()
        now = np.append(state.q, state.deploy)
        # at rest: Present Velocity zero, and the stage (no velocity in the state) unmoved
        still = np.all(state.dq == 0.0) and last is not None and now[-1] == last[-1]
        if still and np.all(np.abs(now - target) <= tol):
            return state
        last = now
        time.sleep(0.01)
    off = np.abs(now - target) / tol  # [its tolerance]
    i = int(np.argmax(off))
    why = (f"{specs[i].joint} {off[i]:.1f} times its tolerance away" if off[i] > 1.0 else
           f"{specs[int(np.argmax(np.abs(state.dq)))].joint} still moving")  # fmt: skip
    raise DynamixelError(f"the payload did not reach its {what} within {timeout} s ({why})")


# -- a payload that powers up out of its bays ---------------------------------------------
def unstowed(design: Any, specs: Sequence[ServoSpec], ticks: np.ndarray) -> tuple[str, float]:
    """The joint of ``specs`` farthest from the design's stowed posture at their present
    positions ``ticks`` (the 16 finger servos: absolute within their one turn, known
    before homing; the rail: once homed), and how far [rad of the servo's shaft]."""
    stowed = posture_values(design, "stowed")
    q = np.array([sp.from_ticks(t) for sp, t in zip(specs, ticks)])
    return farthest_from(specs, q, np.array([stowed[sp.joint] for sp in specs]))


def linear_positions(spec: ServoSpec, ticks: int, pad: float) -> list[float]:
    """Where an unhomed rail or stage may be [m]: its reading ``ticks`` plus any whole
    number of turns (a power-up loses the count and keeps the Homing Offset, the last
    completed homing's), within its travel or up to ``pad`` [m] past an end (a servo at
    rest within its dead band of a goal at the end: taken as at the end). A travel over a
    turn (the packaged rail's and stage's) always holds one; a shorter one may hold none,
    and then the whole travel is taken, at the envelope check's 0.5 mm. A servo whose
    Homing Offset is not from a homing (a new one) reads off by part of a turn: no
    reading can tell."""
    from payload.envelope.deployment import UNFOLD_STEP_M

    out = []
    for k in range(-8, 9):
        v = spec.from_ticks(ticks + k * TICKS_PER_REV)
        if spec.lower - pad <= v <= spec.upper + pad:
            out.append(min(max(v, spec.lower), spec.upper))
    if out:
        return out
    n = max(1, math.ceil((spec.upper - spec.lower) / UNFOLD_STEP_M))
    return list(np.linspace(spec.lower, spec.upper, n + 1))


def fold_failures(design: Any, fingers: Mapping[str, float], rails: Sequence[float]) -> list[str]:
    """What folding the fingers from ``fingers`` (joint -> value) to the stowed posture,
    straight in joint space with the stage down and the rail at each of ``rails`` [m], then
    the rail to its stowed end, would hit, as ``payload report envelope`` checks the
    deployment (:func:`payload.envelope.deployment.unfolding_check`, the line between its
    postures proved contact-free): links through each other (pairs already colliding
    where the fingers are, or stowed, only if they go deeper), links into the vehicle
    body, a stretch not proved clear. Empty when clear."""
    from payload.design import build_tree
    from payload.envelope.deployment import unfolding_check
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.self_collision import self_contacts
    from payload.envelope.vehicle import vehicle_from_dict

    vehicle = vehicle_from_dict(design.vehicle or {}, source=str(design.source))
    geom = PayloadGeometry(build_tree(design))
    stowed = posture_values(design, "stowed")
    down = posture_values(design, "home")["stage"]
    out: list[str] = []
    for rail in rails:
        start = {**stowed, **fingers, "rail": rail, "stage": down}
        folded = {**stowed, "rail": rail, "stage": down}
        end = {**stowed, "stage": down}
        touching = {
            frozenset((c.a, c.b)): c.distance
            for q in (start, end)
            for c in self_contacts(geom, geom.poses(q))
            if c.colliding
        }
        legs = [unfolding_check(geom, vehicle, start, folded, [])]
        if rail != stowed["rail"]:  # then home: the rail in
            legs.append(unfolding_check(geom, vehicle, folded, end, []))
        where = f"with the rail at {rail * 1e3:.1f} mm"
        for leg in legs:
            for c in leg.collisions:
                before = touching.get(frozenset((c.a, c.b)))
                if before is None or c.distance < before - 1e-4:  # new, or deeper
                    out.append(f"{c.a} and {c.b} collide ({-c.distance * 1e3:.1f} mm deep) {where}")
            out += [f"{h.link} hits the {h.body} ({-h.distance * 1e3:.1f} mm deep) {where}"
                    for h in leg.hits]  # fmt: skip
            if not leg.certified:  # a stretch the proof could not settle either way
                out.append(f"the fold is not proved clear between its checked postures {where}")
    return out


def fold_before_homing(hardware: Any, timeout: float = 6.0) -> bool:
    """Before the rail and the stage are homed (driven to their stowed stops, the stage up
    into the bays): fingers more than :data:`STOWED_TOL_RAD` from stowed are folded to the
    stowed posture first, straight in joint space, goals stepped as :func:`ramp` steps
    them, the rail and the stage held where they are. The fingers' positions are known
    (absolute within their one turn), the stage's and the rail's only up to whole turns
    (:func:`linear_positions`): the stage must read as down at one of its positions (the
    payload's own motions unfold the fingers only with the stage down and fold them
    before raising it), and the fold is checked (:func:`fold_failures`) with the rail at
    each of its positions.

    Returns:
        Whether the fingers were folded (the rail is then to be homed before the stage).

    Raises:
        HomingError: The stage does not read as down, or the fold would collide:
            nothing has moved.
        DynamixelError: A finger fell behind its goal (the fingers hold where they are),
            or the fingers were not within their dead bands of stowed in ``timeout`` [s].
    """
    specs = hardware.map.servos
    fingers, rail, stage = specs[:RAIL], specs[RAIL], specs[STAGE]
    ticks = hardware.present_ticks()
    joint, off = unstowed(hardware.design, fingers, ticks[:RAIL])
    if off <= STOWED_TOL_RAD:
        return False
    down = posture_values(hardware.design, "home")["stage"]
    there = tolerance(hardware)  # each servo's dead band and a tick
    stages = linear_positions(stage, int(ticks[STAGE]), float(there[STAGE]))
    near = STOWED_TOL_RAD * float(shaft_per_rad([stage])[0])  # [m]
    if not any(abs(v - down) <= near for v in stages):
        where = " or ".join(f"{v * 1e3 + 0.0:.1f}" for v in sorted(stages))  # (no -0.0)
        raise HomingError(
            f"the payload powered up with {joint} {off:.2f} rad from stowed and the stage not "
            f"down (at {where} mm, not {down * 1e3:.1f}): the fingers may be in the bays; "
            "nothing moved: fold the fingers and lower the stage by hand with the servos "
            "unpowered, then bring it up again"
        )
    q = np.array([sp.from_ticks(t) for sp, t in zip(fingers, ticks[:RAIL])])
    rails = linear_positions(rail, int(ticks[RAIL]), float(there[RAIL]))
    failures = fold_failures(hardware.design, {sp.joint: v for sp, v in zip(fingers, q)}, rails)
    if failures:
        raise HomingError(
            f"the payload powered up out of its bays ({joint} {off:.2f} rad from stowed) and "
            f"folding it from there would collide: {failures[0]}; nothing moved: fold the "
            "fingers by hand with the servos unpowered, then bring it up again"
        )
    log.warning(
        "%s is %.2f rad from the stowed posture (over %s): the payload is out of its bays; "
        "folding the fingers to the stowed posture before the rail and the stage are homed",
        joint,
        off,
        STOWED_TOL_RAD,
    )
    stowed = posture_values(hardware.design, "stowed")

    def send(v: np.ndarray) -> None:
        hardware.goal_ticks({sp.id: sp.to_ticks(x) for sp, x in zip(fingers, v)})

    def read() -> np.ndarray:
        return np.array([sp.from_ticks(t) for sp, t in zip(fingers, hardware.present_ticks())])

    goal = np.array([stowed[sp.joint] for sp in fingers])
    ramp(send, read, q, goal, fingers, hardware.design, "as the fingers fold before homing")
    t0 = time.monotonic()
    while np.any(np.abs(read() - goal) > there[:RAIL]):  # at the stowed posture before homing
        if time.monotonic() - t0 > timeout:
            raise DynamixelError(f"the fingers did not reach the stowed posture within {timeout} s")
        send(goal)
        time.sleep(0.01)
    return True
