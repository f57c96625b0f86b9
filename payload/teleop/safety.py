"""Tracking supervision: dropouts, NaN or absurd frames, and time going backwards.

A hand that is not tracked keeps its last valid frame for up to ``timeout`` (short
dropouts are bridged); past that, or at once for a faulty frame (NaN, joints metres
away, time going backwards), it is *lost*: the vehicle brakes smoothly, the
fingers hold their last command, and an event is logged. When valid frames return the
hand is *recovering* for ``recovery_time`` so the channels blend back in without a jump.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from payload.teleop.hands import WRIST, XR_JOINTS, Hand, HandFrame
from payload.vecmath import norm

log = logging.getLogger(__name__)

SIDES: tuple[str, str] = ("left", "right")
"""The hands in the order the supervisor judges them (its events come in this order)."""


def allowed_jump(max_speed: float, since: float) -> float:
    """How far [m] a wrist may have moved in ``since`` [s] since its last valid frame, at
    ``max_speed`` [m/s] (the compiled intake's C does the same operation)."""
    return max_speed * since


@dataclass(frozen=True)
class SafetyConfig:
    """Supervisor settings.

    Attributes:
        timeout: A hand without valid frames for longer than this is lost [s] (issue: 100 ms).
        max_extent: A joint farther than this from its wrist makes the frame absurd [m].
        workspace_radius: A wrist farther than this from its calibrated neutral is absurd [m]
            (about an arm's reach).
        max_wrist_speed: A wrist moving faster than this since its last valid frame is a
            tracking glitch [m/s] (hands rarely exceed 3 m/s).
        recovery_time: Blend time after tracking returns [s].
    """

    timeout: float = 0.1
    max_extent: float = 0.35
    workspace_radius: float = 0.8
    max_wrist_speed: float = 5.0
    recovery_time: float = 0.5


@dataclass(frozen=True)
class SafetyEvent:
    """A logged safety event."""

    stamp: float
    hand: str
    kind: str  # "invalid", "lost", "regained", "time_backwards"
    detail: str


@dataclass
class HandStatus:
    """Supervisor state for one hand."""

    last_valid: Hand | None = None
    last_valid_stamp: float = -np.inf
    lost: bool = True  # until the first valid frame
    lost_since: float | None = None
    recovering_until: float = -np.inf
    was_invalid: bool = False


@dataclass(frozen=True)
class Supervised:
    """What the channels get from the supervisor at one step.

    Attributes:
        left: The hand to use (last valid while bridging), or None when lost.
        right: Same for the right hand.
        blend_left: 0..1 weight of fresh commands for the left hand (1 = normal).
        blend_right: Same for the right hand.
        events: Events raised at this step.
    """

    left: Hand | None
    right: Hand | None
    blend_left: float
    blend_right: float
    events: tuple[SafetyEvent, ...]

    @property
    def any_lost(self) -> bool:
        return self.left is None or self.right is None


class TrackingSupervisor:
    """Judges each incoming frame; see the module docstring."""

    def __init__(
        self,
        config: SafetyConfig | None = None,
        neutral: dict[str, np.ndarray] | None = None,
    ) -> None:
        self.config = config or SafetyConfig()
        self.neutral = neutral or {}
        self.status = {"left": HandStatus(), "right": HandStatus()}
        self.last_stamp = -np.inf
        self.events: list[SafetyEvent] = []
        self._kernels: dict[str, tuple[tuple[Any, Any], Any]] = {}

    def _valid(self, side: str, hand: Hand, t: float) -> tuple[bool, str]:
        """Whether ``hand`` passes the checks at ``t``, and if not, why (the numbers
        compiled when they can be: :mod:`payload.teleop.safety_c`)."""
        if not hand.tracked:
            return False, "not tracked"
        st = self.status[side]
        since = None
        if st.last_valid is not None and t > st.last_valid_stamp:
            since = t - st.last_valid_stamp
        last = None if since is None else st.last_valid.wrist
        allowed = 0.0 if since is None else allowed_jump(self.config.max_wrist_speed, since)
        joints = hand.joints
        kernel = self._check_kernel(side)
        if (
            kernel is not None
            and type(joints) is np.ndarray
            and joints.dtype == np.float64
            and joints.shape == kernel.shape
            and kernel(joints, last, allowed) == 0
        ):
            return True, ""
        why = self._judge(side, joints, last, allowed, since)
        return not why, why

    def _judge(
        self,
        side: str,
        joints: np.ndarray,
        last: np.ndarray | None,
        allowed: float,
        since: float | None = None,
    ) -> str:
        """Why a tracked hand's joints fail the checks, or "" (numpy): ``last`` is the
        last valid wrist (None: no jump check), ``allowed`` how far it may have moved in
        the ``since`` seconds since."""
        c = self.config
        if not np.isfinite(joints).all():
            return "non-finite joint position"
        wrist = joints[WRIST]
        d = joints - wrist  # np.linalg.norm(d, axis=1)'s formula, then the max
        extent = float(np.sqrt(np.add.reduce(d * d, axis=1)).max())
        if extent > c.max_extent:
            return f"joint {extent:.2f} m from the wrist"
        if side in self.neutral:
            dist = float(norm(wrist - self.neutral[side]))
            if dist > c.workspace_radius:
                return f"wrist {dist:.2f} m from neutral"
        if last is not None:
            jump = float(norm(wrist - last))
            if jump > allowed:
                return f"wrist jumped {jump:.2f} m in {since:.3f} s"
        return ""

    def _check_kernel(self, side: str) -> Any:
        """The compiled checks of one side for the current settings and neutral pose, or
        None (numpy)."""
        key = (self.config, self.neutral.get(side))
        made = self._kernels.get(side)
        if made is None or made[0][0] is not key[0] or made[0][1] is not key[1]:
            from payload.teleop.safety_c import compiled_hand_check

            c = self.config
            kernel = compiled_hand_check(
                len(XR_JOINTS),
                WRIST,
                c.max_extent,
                key[1],
                c.workspace_radius,
                lambda joints, last, allowed: not self._judge(side, joints, last, allowed, 0.0),
            )
            made = self._kernels[side] = (key, kernel)
        return made[1]

    def _event(self, stamp: float, side: str, kind: str, detail: str) -> SafetyEvent:
        ev = SafetyEvent(stamp, side, kind, detail)
        self.events.append(ev)
        # a bridged dropout or a (re)acquisition is routine; a loss or a fault is not
        routine = kind in ("acquired", "regained") or detail == "not tracked"
        log.log(
            logging.INFO if routine else logging.WARNING,
            "teleop safety: t=%.3f %s hand %s: %s",
            stamp,
            side,
            kind,
            detail,
        )
        return ev

    def force_lost(self, side: str, stamp: float, reason: str) -> None:
        """Declare a hand lost now, without bridging (the live link dropped, or the headset
        reports the hand gone): from the next :meth:`step` the vehicle brakes and the
        fingers hold until valid frames return and blend in."""
        st = self.status[side]
        if st.lost:
            return
        st.lost, st.lost_since, st.was_invalid = True, stamp, True
        self._event(stamp, side, "lost", reason)

    def step(self, frame: HandFrame) -> Supervised:
        c = self.config
        events: list[SafetyEvent] = []
        t = frame.stamp
        backwards = t < self.last_stamp
        if backwards:
            events.append(
                self._event(t, "both", "time_backwards", f"{t:.3f} s < {self.last_stamp:.3f} s")
            )
            t_eval = self.last_stamp  # judge timeouts on the last good clock
        else:
            self.last_stamp = t
            t_eval = t
        out: dict[str, Hand | None] = {}
        blend: dict[str, float] = {}
        for side in SIDES:
            st = self.status[side]
            hand = frame.hand(side)
            ok, why = (False, "time went backwards") if backwards else self._valid(side, hand, t)
            if ok:
                if st.lost:
                    # first acquisition and every recovery blend in over recovery_time
                    kind = "regained" if st.lost_since is not None else "acquired"
                    events.append(self._event(t, side, kind, f"tracking {kind}"))
                    st.recovering_until = t + c.recovery_time
                    st.lost = False
                    st.lost_since = None
                _take(st, hand, t)
            else:
                if not st.was_invalid and not st.lost:
                    events.append(self._event(t_eval, side, "invalid", why))
                st.was_invalid = True
                fault = why != "not tracked"  # NaN, absurd or backwards: no bridging
                if not st.lost and (fault or t_eval - st.last_valid_stamp > c.timeout + 1e-9):
                    st.lost = True
                    st.lost_since = t_eval
                    detail = why if fault else f"no valid frame for > {c.timeout} s"
                    events.append(self._event(t_eval, side, "lost", detail))
            if st.lost:
                out[side], blend[side] = None, 0.0
            else:
                out[side] = st.last_valid
                blend[side] = self._weight(st, t_eval)
        return Supervised(out["left"], out["right"], blend["left"], blend["right"], tuple(events))

    def accepted(self, frame: HandFrame) -> Supervised:
        """What :meth:`step` does with a frame whose hands are both valid, neither lost
        and its time not going backwards (a caller that checked them itself: the
        pipeline's compiled intake, :mod:`payload.teleop.intake_c`): no events, each hand
        its own, blended in while recovering."""
        t = frame.stamp
        self.last_stamp = t
        left, right = self.status["left"], self.status["right"]
        _take(left, frame.left, t)
        _take(right, frame.right, t)
        return Supervised(
            frame.left, frame.right, self._weight(left, t), self._weight(right, t), ()
        )

    def _weight(self, st: HandStatus, t: float) -> float:
        """The weight of a hand's fresh commands at ``t`` (1 unless recovering)."""
        remaining = st.recovering_until - t
        return 1.0 if remaining <= 0 else 1.0 - remaining / self.config.recovery_time


def _take(st: HandStatus, hand: Hand, t: float) -> None:
    """A valid hand at ``t`` is the last valid one."""
    st.last_valid, st.last_valid_stamp, st.was_invalid = hand, t, False


@dataclass
class Blender:
    """Holds a command while lost and ramps back to fresh commands on recovery."""

    held: np.ndarray | None = None
    _anchor: np.ndarray | None = field(default=None, repr=False)

    def step(self, fresh: np.ndarray | None, weight: float) -> np.ndarray | None:
        """Blend: ``weight`` 1 passes ``fresh``; 0 (or no fresh command) holds. A blend
        runs from the command held when it began (its anchor): a step without a fresh
        command in the middle of it (a refused solve) holds without moving the anchor, so
        the blend goes on where it was instead of jumping ahead."""
        if fresh is None or weight <= 0.0:
            if weight <= 0.0 or self._anchor is None:
                self._anchor = self.held
            return self.held
        if weight >= 1.0 or self.held is None:
            self.held = np.array(fresh, dtype=float)
            self._anchor = None
            return self.held
        if self._anchor is None:
            self._anchor = self.held
        self.held = (1.0 - weight) * self._anchor + weight * np.asarray(fresh, float)
        return self.held
