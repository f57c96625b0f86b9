"""The bimanual teleoperation pipeline: hand frames in, three concurrent channels out.

Each 50 Hz step, from one :class:`~payload.teleop.hands.HandFrame`:

- finger channel, per hand: thumb-index features in the wrist frame -> calibrated robot
  targets -> the production retargeter (warm-started) -> 8 joint commands;
- rail channel: calibrated inter-wrist distance -> rail position;
- base channel: left wrist against the virtual sphere -> jerk-limited body twist.

Keypoints are One Euro filtered; the tracking supervisor bridges short dropouts, and a
hand lost for more than 100 ms (or a NaN or absurd frame) brakes the vehicle while the
fingers and rail hold; recovery blends back in without a jump.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from payload.design.params import Design, load_design
from payload.design.tree import MANIPULATION_JOINTS
from payload.errors import PayloadError
from payload.retarget.calibration import OpeningError, PairCalibration, PairRange, calibrate
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.errors import RetargetError
from payload.retarget.features import PairFeatures, features_from_points
from payload.retarget.solver import SolveInfo
from payload.schema import CONTROL_DT, PayloadCommand, VehicleTwist
from payload.teleop.calibration import CalibrationError, Captures
from payload.teleop.channels import (
    BaseChannel,
    BaseCommand,
    BaseConfig,
    RailConfig,
    RailOrderError,
    rail_command,
)
from payload.teleop.filters import OneEuroConfig, OneEuroFilter
from payload.teleop.hand_c import compiled_hand_features
from payload.teleop.hands import (
    WRIST,
    Hand,
    HandFrame,
    HandFrameError,
    pinch_points,
    wrist_frame,
)
from payload.teleop.intake_c import compiled_hand_intake, intake_objects, intake_parts
from payload.teleop.intake_c import ready as intake_ready
from payload.teleop.safety import (
    Blender,
    SafetyConfig,
    SafetyEvent,
    Supervised,
    TrackingSupervisor,
)

log = logging.getLogger(__name__)

HAND_OF_PAIR = {"L": "left", "R": "right"}

TRACKING_FAULTS: tuple[type[Exception], ...] = (RetargetError, HandFrameError)
"""What bad hand data raises in the finger channel (degenerate or non-finite geometry, a
malformed hand, a target or solve the retargeter rejects): the pair holds and a safety
event is logged. Any other exception is a bug: it propagates and aborts the session."""


def human_features(hand: Hand) -> PairFeatures:
    """Eq. 2 features of a hand's thumb (finger 1) and index (finger 2) in its wrist frame.

    Raises:
        RetargetError: Degenerate or non-finite geometry.
    """
    pts = pinch_points(hand, wrist_frame(hand))
    return features_from_points(pts["p1"], pts["p2"], pts["a1"], pts["a2"])


def human_feature_vector(hand: Hand) -> np.ndarray:
    """``human_features(hand).as_vector()``, compiled when it can be
    (:mod:`payload.teleop.hand_c`: the same bits).

    Raises:
        RetargetError: Degenerate or non-finite geometry.
    """
    kernel = compiled_hand_features(human_features)
    if kernel is not None:
        v = kernel(hand.joints)
        if v is not None:
            return v
    return human_features(hand).as_vector()


@dataclass(frozen=True)
class TeleopConfig:
    """Pipeline settings.

    Attributes:
        base: Base channel settings.
        safety: Tracking supervisor settings.
        filter: One Euro filter settings for the keypoints.
        filter_enabled: Whether keypoints are filtered.
        deploy: Deployment coordinate commanded during teleoperation [m] (the design's
            stage travel: fully deployed).
        rail_travel: Rail travel [m] (the design's).
        dt: Control period [s].
    """

    deploy: float
    rail_travel: float
    base: BaseConfig = field(default_factory=BaseConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    filter: OneEuroConfig = field(default_factory=OneEuroConfig)
    filter_enabled: bool = True
    dt: float = CONTROL_DT

    @staticmethod
    def from_design(design: Design | None = None, **overrides: Any) -> TeleopConfig:
        """Settings for a design: deployed stage and rail travel come from it.

        Args:
            design: The design (``None``: the project's ``cad/design.toml``).
            overrides: Any other field.
        """
        d = design if design is not None else load_design()
        return TeleopConfig(deploy=d.stage.travel, rail_travel=d.rail.travel, **overrides)


@dataclass(frozen=True)
class TeleopCalibration:
    """Everything the calibration procedure determined.

    Attributes:
        neutral_left: Neutral left-wrist position (base channel sphere centre) [m].
        neutral_right: Neutral right-wrist position [m].
        heading0: World yaw aligned with the operator's forward direction [rad].
        rail: Inter-wrist distance mapping.
        pairs: Finger calibration per pair (``L``, ``R``).
    """

    neutral_left: np.ndarray
    neutral_right: np.ndarray
    heading0: float
    rail: RailConfig
    pairs: dict[str, PairCalibration]


def calibrate_operator(
    captures: Captures,
    ranges: dict[str, PairRange],
    rail_travel: float,
    heading0: float = 0.0,
) -> TeleopCalibration:
    """Turn the procedure's captures into the channels' calibration.

    Raises:
        CalibrationError: A gesture was not captured or is inconsistent.
    """
    neutral = {s: captures.get("neutral", s).wrist.copy() for s in ("left", "right")}
    d_min = float(
        np.linalg.norm(
            captures.get("together", "left").wrist - captures.get("together", "right").wrist
        )
    )
    d_max = float(
        np.linalg.norm(captures.get("apart", "left").wrist - captures.get("apart", "right").wrist)
    )
    try:
        rail = RailConfig(d_min, d_max, rail_travel)
    except RailOrderError as exc:  # said as the operator did it, not in the rail's terms
        raise CalibrationError(
            f"calibration 'together'/'apart': the wrists were {100 * exc.d_max:.1f} cm apart "
            f"for 'apart' and {100 * exc.d_min:.1f} cm for 'together': hold them wider apart "
            "for 'apart'"
        ) from exc
    except PayloadError as exc:
        raise CalibrationError(f"calibration 'together'/'apart': {exc}") from exc
    pairs = {}
    for pair, side in HAND_OF_PAIR.items():
        try:
            pinch = human_features(captures.get("pinch", side))
            opened = human_features(captures.get("open", side))
            pairs[pair] = calibrate(pinch, opened, ranges[pair])
        except OpeningError as exc:  # as the operator did it
            raise CalibrationError(
                f"calibration of the {side} hand: its thumb and index were "
                f"{1e3 * exc.open_span:.0f} mm apart for 'open' and {1e3 * exc.pinch_span:.0f} "
                "mm for 'pinch': open them wide for 'open' and pinch them for 'pinch'"
            ) from exc
        except RetargetError as exc:
            raise CalibrationError(f"calibration of the {side} hand: {exc}") from exc
    return TeleopCalibration(neutral["left"], neutral["right"], heading0, rail, pairs)


@dataclass(frozen=True)
class TeleopStep:
    """The three channel commands produced at one step.

    Attributes:
        stamp: Time of the hand frame [s].
        q_left: Pair L command (A, C joints in the retargeter's order), shape (8,).
        q_right: Pair R command (B, D), shape (8,).
        rail: Rail command [m].
        base: The base channel's output (``base.twist`` is the vehicle command).
        command: The payload command (17 coordinates in the paper's order + deploy).
        events: Safety events raised at this step.
        solves: Solver info per pair (absent when the pair held).
    """

    stamp: float
    q_left: np.ndarray
    q_right: np.ndarray
    rail: float
    base: BaseCommand
    command: PayloadCommand
    events: tuple[SafetyEvent, ...]
    solves: dict[str, SolveInfo]

    @property
    def twist(self) -> VehicleTwist:
        return self.base.twist


_Intake = tuple[
    list[SafetyEvent],
    dict[str, float],
    dict[str, "np.ndarray | None"],
    dict[str, "np.ndarray | None"],
    dict[str, SolveInfo],
]
"""A step's hands taken in: its events, each hand's blend weight and filtered wrist (None:
lost), each pair's fresh command (None: held) and solve reports."""


def pair_index(retargeter: PairRetargeter) -> np.ndarray:
    """Positions of a pair's joints in the 17 manipulation coordinates, shape (8,)."""
    return np.array([MANIPULATION_JOINTS.index(j) for j in retargeter.joints])


class TeleopPipeline:
    """The three concurrent channels (see the module docstring).

    Args:
        calibration: The operator's calibration.
        retargeters: Production retargeters per pair (``L``, ``R``).
        config: Pipeline settings.
        initial: Initial 17-coordinate command (the payload's current posture).
    """

    def __init__(
        self,
        calibration: TeleopCalibration,
        retargeters: dict[str, PairRetargeter],
        config: TeleopConfig | None = None,
        initial: np.ndarray | None = None,
    ) -> None:
        self.config = config or TeleopConfig.from_design()
        self.calibration = calibration
        self.retargeters = retargeters
        c = self.config
        self.supervisor = TrackingSupervisor(
            c.safety, {"left": calibration.neutral_left, "right": calibration.neutral_right}
        )
        self.filters = {s: OneEuroFilter(c.filter) for s in ("left", "right")}
        self.base = BaseChannel(
            c.base,
            calibration.neutral_left,
            calibration.heading0,
            c.dt,
            neutral_right=calibration.neutral_right,
        )
        self.index = {pair: pair_index(r) for pair, r in retargeters.items()}
        q0 = np.zeros(len(MANIPULATION_JOINTS)) if initial is None else np.array(initial, float)
        # start from the payload's posture and blend the first commands in (no jump at the
        # start of control, as after a tracking recovery)
        self.blend = {p: Blender(q0[self.index[p]].copy()) for p in retargeters}
        for pair, r in retargeters.items():
            r.reset(q0[self.index[pair]])
        self.rail_blend = Blender(np.array([q0[-1]]))
        self.events: list[SafetyEvent] = []
        # pair -> (the calibration and retargeter it was made for, its finger chain
        # (pair_c) or None): a chain binds their buffers, so another of either needs another
        self._chains: dict[str, tuple[Any, Any, Any]] = {}
        self._intake: tuple[tuple, Any, tuple] | None = None  # (parts, intake, objects)
        # the intake, base step, rail settings and pairs' retargeters the intake's tail was
        # bound to, and whether it took them (_tail_ready)
        self._tail: tuple[Any, ...] | None = None

    def _filtered(self, side: str, hand: Hand | None, t: float) -> Hand | None:
        if hand is None:
            self.filters[side].reset()
            return None
        if not self.config.filter_enabled:
            return hand
        return Hand.taking(self.filters[side](hand.joints, t))  # the filter's copy

    def _finger(self, pair: str, hand: Hand) -> tuple[np.ndarray, SolveInfo]:
        """The pair's fresh command and solve report for a hand: the compiled chain
        (:mod:`payload.teleop.pair_c`) when it takes the hand, else :meth:`_finger_python`.

        Raises:
            RetargetError, HandFrameError: The hand's features, targets or solve refused.
        """
        chain = self._chain(pair, self)
        if chain is self:  # not made yet for this calibration and retargeter
            parts = (self.calibration.pairs[pair], self.retargeters[pair])
            chain = self._make_chain(pair)
            self._chains[pair] = (*parts, chain)
        if chain is not None:
            out = chain(hand.joints)
            if out is not None:
                return out
        return self._finger_python(pair, hand)

    def _chain(self, pair: str, missing: Any = None) -> Any:
        """The pair's finger chain (None: the Python path) if it was made for the
        pipeline's calibration and retargeter of the pair as they are now, else
        ``missing`` (none made for them yet: the pipeline's ``calibration`` or a
        retargeter replaced since, say)."""
        made = self._chains.get(pair)
        if (
            made is None
            or made[0] is not self.calibration.pairs[pair]
            or made[1] is not self.retargeters[pair]
        ):
            return missing
        return made[2]

    def _finger_python(self, pair: str, hand: Hand) -> tuple[np.ndarray, SolveInfo]:
        """Features, targets, posture reference and solve, one call each."""
        targets, q_ref = self.calibration.pairs[pair].command(human_feature_vector(hand))
        return self.retargeters[pair].solve(targets, q_ref=q_ref)

    def _make_chain(self, pair: str) -> Any:
        from payload.teleop.pair_c import compiled_finger_chain

        calibration = self.calibration.pairs[pair]
        retargeter = self.retargeters[pair]
        if not hasattr(retargeter, "step_entry"):  # another solver: no compiled step
            return None

        def python(joints: np.ndarray) -> tuple[np.ndarray, SolveInfo] | None:
            try:
                return self._finger_python(pair, Hand(joints, True))
            except TRACKING_FAULTS:
                return None

        return compiled_finger_chain(
            compiled_hand_features(human_features),
            calibration.targets_kernel,
            calibration.range,
            retargeter,
            python,
        )

    def step(self, frame: HandFrame, vehicle_rotation: np.ndarray | None = None) -> TeleopStep:
        """One 50 Hz step.

        Both hands are taken in first (:meth:`_intake_step` or :meth:`_hands`), then the
        channels run (on a steady step, in the intake's compiled call: :meth:`_steady`,
        the same commands). Bad hand data holds a pair (a safety event); any other exception is
        a bug that aborts the session, and what the step did before it stands (the other
        pair's solve, say).

        Args:
            frame: Hand frame (workbench or WebXR convention).
            vehicle_rotation: Vehicle body -> world rotation (3, 3), for the body twist.
        """
        frame = frame.to_workbench()
        t = frame.stamp if math.isfinite(frame.stamp) else self.supervisor.last_stamp
        stamp = float(frame.stamp) if math.isfinite(frame.stamp) else t
        taken = self._intake_step(frame, t, vehicle_rotation, stamp)
        if type(taken) is TeleopStep:  # a steady step, its channels run with the intake
            return taken
        if taken is None:
            taken = self._hands(frame, t)
        events, weights, wrists, fresh, solves = taken
        q_pair: dict[str, np.ndarray] = {}
        for pair, side in HAND_OF_PAIR.items():
            # the hand's weight even without a fresh command (a refused solve): mid-recovery
            # the blend holds and goes on from where it began (a lost hand's weight is 0)
            q = self.blend[pair].step(fresh[pair], weights[side])
            q_pair[pair] = q
            # warm start from what is actually commanded (held or blended)
            self.retargeters[pair].hold(q)
        both = wrists["left"] is not None and wrists["right"] is not None
        if both:
            rail_fresh = np.array(
                [rail_command(self.calibration.rail, wrists["left"], wrists["right"])]
            )
            rail = self.rail_blend.step(rail_fresh, min(weights["left"], weights["right"]))
        else:
            rail = self.rail_blend.step(None, 0.0)
        left_wrist = wrists["left"] if both else None  # a lost hand brakes the vehicle
        right_wrist = wrists["right"] if both else None
        base = self.base.step(left_wrist, vehicle_rotation, right_wrist, stamp)
        self.events.extend(events)
        return self._made(q_pair, float(rail[0]), base, tuple(events), solves, stamp)

    def _made(
        self,
        q_pair: dict[str, np.ndarray],
        rail: float,
        base: BaseCommand,
        events: tuple[SafetyEvent, ...],
        solves: dict[str, SolveInfo],
        stamp: float,
    ) -> TeleopStep:
        """The step of the channels' commands: the payload command of both pairs' and the
        rail's, and the step with its own copies of the pairs'."""
        q17 = np.zeros(len(MANIPULATION_JOINTS))
        for pair, q in q_pair.items():
            q17[self.index[pair]] = q
        q17[-1] = rail
        q17.setflags(write=False)  # the command's own: taken as it is
        command = PayloadCommand.of_frozen(q17, self.config.deploy, stamp)
        return TeleopStep(
            stamp, q_pair["L"].copy(), q_pair["R"].copy(), rail, base, command, events, solves
        )

    def _hands(self, frame: HandFrame, t: float) -> _Intake:
        """The supervisor's verdict, the filtered hands and each pair's fresh command (the
        Python path)."""
        sup = self.supervisor.step(frame)
        events = list(sup.events)
        hands = {
            "left": self._filtered("left", sup.left, t),
            "right": self._filtered("right", sup.right, t),
        }
        weights = {"left": sup.blend_left, "right": sup.blend_right}
        solves: dict[str, SolveInfo] = {}
        fresh: dict[str, np.ndarray | None] = {}
        for pair, side in HAND_OF_PAIR.items():
            hand = hands[side]
            fresh[pair] = None if hand is None else self._fresh(pair, hand, t, events, solves)
        wrists = {side: None if hand is None else hand.wrist for side, hand in hands.items()}
        return events, weights, wrists, fresh, solves

    def _fresh(
        self,
        pair: str,
        hand: Hand,
        t: float,
        events: list[SafetyEvent],
        solves: dict[str, SolveInfo],
        chain: bool = True,
    ) -> np.ndarray | None:
        """A pair's fresh command for a hand (its solve report into ``solves``), or None:
        bad hand data holds the pair (a safety event into ``events``); a bug aborts.
        ``chain``: try the compiled chain first."""
        side = HAND_OF_PAIR[pair]
        try:
            q, solves[pair] = self._finger(pair, hand) if chain else self._finger_python(pair, hand)
            return q
        except TRACKING_FAULTS as exc:
            events.append(SafetyEvent(t, side, "invalid", f"finger channel: {exc}"))
            log.warning("teleop: %s hand finger channel held: %s", side, exc)
            return None

    def _intake_step(
        self,
        frame: HandFrame,
        t: float,
        vehicle_rotation: np.ndarray | None = None,
        stamp: float = 0.0,
    ) -> _Intake | TeleopStep | None:
        """:meth:`_hands` through the compiled intake (:mod:`payload.teleop.intake_c`), or
        None (nothing changed) where the Python path is to run; on a steady step (both
        hands taken, neither recovering) the whole step, its channels run in the same
        compiled call (:meth:`_steady`)."""
        intake = self._intake_kernel()
        if intake is None:
            return None
        got = intake(frame, t, self._tail_ready(intake, vehicle_rotation))
        if got is None:
            return None
        sup, taken = got
        if taken & 4:
            return self._steady(intake, sup, taken >> 3, stamp)
        weights = {"left": sup.blend_left, "right": sup.blend_right}
        events: list[SafetyEvent] = []
        solves: dict[str, SolveInfo] = {}
        fresh: dict[str, np.ndarray | None] = {}
        filtered = {side: f.estimate() for side, f in self.filters.items()}
        for bit, (pair, side) in enumerate(HAND_OF_PAIR.items()):
            if taken >> bit & 1:
                fresh[pair], solves[pair] = self.retargeters[pair].finish_step()
            else:  # the chain refused the filtered hand: the Python path says why
                hand = Hand.taking(filtered[side])
                fresh[pair] = self._fresh(pair, hand, t, events, solves, chain=False)
        wrists = {side: joints[WRIST] for side, joints in filtered.items()}
        return events, weights, wrists, fresh, solves

    def _tail_ready(self, intake: Any, vehicle_rotation: Any) -> bool:
        """Whether the intake's call is to run the channels too (:meth:`HandIntake.bind_tail
        <payload.teleop.intake_c.HandIntake.bind_tail>`): the tail bound to the pipeline's
        retargeters, base channel and rail settings as they are now
        (:meth:`_tail_takes`), and the base channel's compiled step ready for this
        rotation."""
        base = getattr(self.base, "_compiled_step", None)
        rail = self.calibration.rail
        left, right = self.retargeters["L"], self.retargeters["R"]
        bound = self._tail
        if (
            bound is None
            or bound[0] is not intake
            or bound[1] is not base
            or bound[2] is not rail
            or bound[3] is not left
            or bound[4] is not right
        ):
            ok = self._tail_takes(base, left, right)
            try:
                if ok:
                    intake.bind_tail((left.step_output, right.step_output), base, rail)
            except ValueError as exc:
                log.info("pipeline: the channels after the intake in Python (%s)", exc)
                ok = False
            bound = self._tail = (intake, base, rail, left, right, ok)
        return bound[5] and base.prepare(vehicle_rotation)

    def _tail_takes(self, base: Any, left: Any, right: Any) -> bool:
        """Whether :meth:`_steady` makes what the Python path's objects would: the base
        channel's compiled step there, and the retargeters and base channel of the classes
        whose compiled parts it calls (a subclass's own ``step_output`` or ``step`` runs
        on the Python path)."""
        return (
            base is not None
            and all(type(r) is PairRetargeter for r in (left, right))
            and type(self.base) is BaseChannel
        )

    def _steady(self, intake: Any, sup: Supervised, mode: int, stamp: float) -> TeleopStep:
        """The step whose channels the intake's call ran (:meth:`_tail_ready`; ``sup``: the
        supervisor's verdict): what the Python path makes of it, each pair's solve blended
        in and held, the rail command blended in, the base channel's command, the payload
        command."""
        solves: dict[str, SolveInfo] = {}
        q_pair: dict[str, np.ndarray] = {}
        weights = {"left": sup.blend_left, "right": sup.blend_right}
        for pair, side in HAND_OF_PAIR.items():
            retargeter = self.retargeters[pair]
            fresh, solves[pair] = retargeter.finish_step()
            q = q_pair[pair] = self.blend[pair].step(fresh, weights[side])
            retargeter.hold(q)
        rail = self.rail_blend.step(intake.rail.copy(), min(weights["left"], weights["right"]))
        base = BaseCommand(*self.base._compiled_step.finish(mode, stamp))
        return self._made(q_pair, float(rail[0]), base, (), solves, stamp)

    def _intake_kernel(self) -> Any:
        """The compiled intake for the current parts (made when they are all there and
        compiled), or None."""
        if not self.config.filter_enabled:
            return None
        chains = (self._chain("L"), self._chain("R"))  # the left hand's pair, the right's
        objects = intake_objects(self.supervisor, self.filters, chains)
        parts = intake_parts(objects)
        made = self._intake
        if made is not None and made[0] == parts:
            return made[1]
        if not intake_ready(self.filters, chains):
            return None
        kernel = compiled_hand_intake(self.supervisor, self.filters, chains)
        self._intake = (parts, kernel, objects)  # the objects kept: their ids theirs
        return kernel
