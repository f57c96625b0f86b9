"""The operator calibration procedure: prompts, captures, and what they calibrate.

The procedure prompts the operator through a fixed sequence of gestures, each held for a
few seconds; the last ``capture`` seconds of each hold are averaged (so the operator's
reaction time does not matter):

1. ``neutral``: both hands relaxed at the comfortable working position, half open ->
   neutral wrist positions (the base channel's sphere centre) and the operator heading;
2. ``pinch``: thumb and index tips together on both hands -> the robot's minimum span;
3. ``open``: thumb and index spread wide -> the robot's maximum span;
4. ``together``: wrists brought close -> rail at 0;
5. ``apart``: wrists spread -> rail at full travel;
6. ``release``: back to neutral, half open, before control starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from payload.errors import PayloadError
from payload.teleop.hands import Hand, HandFrame


class CalibrationError(PayloadError):
    """The calibration captures are unusable (missing hand, inconsistent gestures)."""


@dataclass(frozen=True)
class Step:
    """One prompted gesture.

    Attributes:
        name: Gesture name (see the module docstring).
        hold: How long the prompt stays up [s].
        capture: The trailing window averaged into the capture [s].
        prompt: What the operator is told.
    """

    name: str
    hold: float
    capture: float
    prompt: str


DEFAULT_STEPS: tuple[Step, ...] = (
    Step("neutral", 2.5, 1.0, "Hold both hands relaxed at your working position, half open"),
    Step("pinch", 2.0, 0.8, "Pinch thumb and index together on both hands"),
    Step("open", 2.0, 0.8, "Open thumb and index wide on both hands"),
    Step("together", 2.0, 0.8, "Bring your wrists close together"),
    Step("apart", 2.0, 0.8, "Spread your wrists apart"),
    Step("release", 1.5, 0.5, "Back to your working position, half open"),
)


@dataclass
class Captures:
    """Averaged joint positions per gesture and hand: ``captures[step][side]`` (25, 3)."""

    hands: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def get(self, step: str, side: str) -> Hand:
        try:
            return Hand(self.hands[step][side])
        except KeyError as exc:
            raise CalibrationError(f"calibration captured no {side} hand during '{step}'") from exc


class CalibrationProcedure:
    """Runs the prompt sequence on incoming frames.

    Feed frames with :meth:`step`; :attr:`prompt` tells the operator what to do now;
    :attr:`done` becomes true after the last step, then :attr:`captures` holds the data.
    """

    def __init__(self, steps: tuple[Step, ...] = DEFAULT_STEPS, t0: float = 0.0) -> None:
        self.steps = steps
        self.t0 = t0
        self._ends = np.cumsum([s.hold for s in steps]) + t0
        self._buffers: dict[str, dict[str, list[np.ndarray]]] = {
            s.name: {"left": [], "right": []} for s in steps
        }
        self.captures = Captures()
        self.done = False
        self._index = 0

    @property
    def duration(self) -> float:
        return float(self._ends[-1] - self.t0)

    @property
    def current(self) -> Step | None:
        return None if self.done else self.steps[self._index]

    @property
    def prompt(self) -> str:
        step = self.current
        return "" if step is None else step.prompt

    def step_at(self, t: float) -> Step | None:
        """The prompted step at time ``t`` (None after the end)."""
        i = int(np.searchsorted(self._ends, t, side="right"))
        return self.steps[i] if i < len(self.steps) else None

    def step(self, frame: HandFrame) -> None:
        """Consume one frame (untracked or non-finite hands are skipped).

        Captures are kept in the workbench frame, like the pipeline's inputs, whatever the
        convention of the incoming frame (a WebXR frame is converted).
        """
        if self.done:
            return
        frame = frame.to_workbench()
        t = frame.stamp
        while self._index < len(self.steps) and t >= self._ends[self._index]:
            self._finish(self.steps[self._index])
            self._index += 1
        if self._index >= len(self.steps):
            self.done = True
            return
        step = self.steps[self._index]
        if t >= self._ends[self._index] - step.capture:
            for side in ("left", "right"):
                hand = frame.hand(side)
                if hand.tracked and np.all(np.isfinite(hand.joints)):
                    self._buffers[step.name][side].append(np.array(hand.joints))

    def _finish(self, step: Step) -> None:
        out = {}
        for side, frames in self._buffers[step.name].items():
            if frames:
                out[side] = np.mean(np.stack(frames), axis=0)
        self.captures.hands[step.name] = out
