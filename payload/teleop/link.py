"""A delayed ground link between the operator and the robot (``--link-delay S[:JITTER]``).

The paper's operator is on the ground: hand frames travel up to the robot and the robot's
state travels back down, each with a delay. :class:`DelayedLink` wraps a hand source:
every frame the operator makes at time ``t`` reaches the robot at ``t + delay`` (the robot
uses the newest frame that has arrived, holding it until a newer one does), and the
operator acts on the newest state that has reached it (the state sent at ``t`` arrives at
``t + delay``). With jitter each message's delay is drawn uniformly from
``[delay - jitter, delay + jitter]`` (at least 0), seeded, independently per direction.
Until its first frame arrives the robot holds the operator's first frame (the hands were
there before the link opened); until the first state arrives the operator sees the first.

The robot side (the base safety filter included) runs on what arrives; the frames handed
on are restamped with the robot's control time, so a recording of the session replays the
robot's side bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Any

import numpy as np

from payload.errors import PayloadError


class LinkError(PayloadError):
    """A bad ``--link-delay`` value."""


def parse_link_delay(text: str) -> tuple[float, float]:
    """``S[:JITTER]`` -> (delay [s], jitter [s]), both finite and >= 0, jitter <= delay.

    Raises:
        LinkError: Not that form.
    """
    parts = str(text).split(":")
    try:
        if len(parts) > 2:
            raise ValueError
        delay = float(parts[0])
        jitter = float(parts[1]) if len(parts) == 2 else 0.0
    except ValueError:
        raise LinkError(f"--link-delay: expected S or S:JITTER in seconds, got {text!r}") from None
    if not (math.isfinite(delay) and math.isfinite(jitter)):
        raise LinkError(f"--link-delay {text}: not a number of seconds (a finite S[:JITTER])")
    if not (delay >= 0 and jitter >= 0):
        raise LinkError(f"--link-delay: delay and jitter must be >= 0 s, got {text!r}")
    if jitter > delay:
        raise LinkError(f"--link-delay: jitter {jitter} s exceeds the delay {delay} s")
    return delay, jitter


class DelayLine:
    """One direction of the link: items put at time ``t`` arrive at ``t + delay``
    (+- jitter); :meth:`take` gives the newest-sent item arrived so far, holding it.

    Args:
        delay: One-way delay [s].
        jitter: Half-width of the uniform spread of each item's delay [s].
        rng: The jitter draws.
    """

    def __init__(self, delay: float, jitter: float, rng: np.random.Generator) -> None:
        self.delay = float(delay)
        self.jitter = float(jitter)
        self._rng = rng
        self._queue: deque[tuple[float, float, Any]] = deque()  # (arrival, sent, item)
        self.held: Any = None
        self._held_sent = -math.inf

    def put(self, t: float, item: Any) -> None:
        """Send ``item`` at time ``t`` [s]; the first item sent is held until another
        arrives (what was there before the link opened)."""
        spread = float(self._rng.uniform(-self.jitter, self.jitter)) if self.jitter else 0.0
        self._queue.append((t + max(0.0, self.delay + spread), t, item))
        if self.held is None:
            self.held = item

    def take(self, t: float) -> Any:
        """The newest-sent item that has arrived by ``t`` (arrived items leave the line)."""
        keep: deque[tuple[float, float, Any]] = deque()
        while self._queue:
            arrival, sent, item = self._queue.popleft()
            if arrival <= t + 1e-12:
                if sent > self._held_sent:
                    self.held, self._held_sent = item, sent
            else:
                keep.append((arrival, sent, item))
        self._queue = keep
        return self.held


class DelayedLink:
    """A hand source seen through a delayed link (see the module docstring).

    Args:
        source: The operator's hand source (``frame(t, world)``, ``finished``).
        delay: One-way delay [s].
        jitter: Half-width of the uniform spread of each message's delay [s].
        seed: Seed of the jitter draws.
    """

    def __init__(self, source: Any, delay: float, jitter: float = 0.0, seed: int = 0) -> None:
        self.source = source
        rng = np.random.default_rng(seed)
        self.up = DelayLine(delay, jitter, rng)  # hand frames to the robot
        self.down = DelayLine(delay, jitter, rng)  # the robot's state to the operator
        self._stamp0: float | None = None

    def frame(self, t: float, world: Any) -> Any:
        """The frame the robot has at control time ``t``; ``world`` is the robot's state
        now (it reaches the operator later)."""
        view = None
        if world is not None:
            self.down.put(t, world)
            view = dataclasses.replace(self.down.take(t), t=t)  # acted on now
        made = self.source.frame(t, view)
        if made is None:
            return None
        self.up.put(t, made)
        held = self.up.take(t)
        if self._stamp0 is None:
            self._stamp0 = float(held.stamp)
        return dataclasses.replace(held, stamp=self._stamp0 + t)

    @property
    def finished(self) -> bool:
        return bool(self.source.finished)

    @property
    def operator(self) -> Any:
        """The synthetic operator behind the link (``None`` for other sources)."""
        return getattr(self.source, "operator", None)


__all__ = ["DelayLine", "DelayedLink", "LinkError", "parse_link_delay"]
