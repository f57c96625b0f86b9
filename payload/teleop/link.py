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
    if not (math.isfinite(delay) and math.isfinite(jitter) and delay >= 0 and jitter >= 0):
        raise LinkError(f"--link-delay: delay and jitter must be >= 0 s, got {text!r}")
    if jitter > delay:
        raise LinkError(f"--link-delay: jitter {jitter} s exceeds the delay {delay} s")
    return delay, jitter


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
        self.delay = float(delay)
        self.jitter = float(jitter)
        self._rng = np.random.default_rng(seed)
        self._views: deque[tuple[float, float, Any]] = deque()  # (arrival, sent, view)
        self._frames: deque[tuple[float, float, Any]] = deque()  # (arrival, sent, frame)
        self._seen: Any = None  # newest state the operator has
        self._seen_sent = -math.inf
        self._held: Any = None  # newest frame the robot has
        self._held_sent = -math.inf
        self._stamp0: float | None = None

    def _arrival(self, t: float) -> float:
        if self.jitter == 0.0:
            return t + self.delay
        return t + max(0.0, self.delay + float(self._rng.uniform(-self.jitter, self.jitter)))

    @staticmethod
    def _newest(queue: deque, t: float, held: Any, held_sent: float) -> tuple[Any, float]:
        """The newest-sent item of ``queue`` that has arrived by ``t`` (arrived items
        leave the queue), or what was held."""
        keep = deque()
        while queue:
            arrival, sent, item = queue.popleft()
            if arrival <= t + 1e-12:
                if sent > held_sent:
                    held, held_sent = item, sent
            else:
                keep.append((arrival, sent, item))
        queue.extend(keep)
        return held, held_sent

    def frame(self, t: float, world: Any) -> Any:
        """The frame the robot has at control time ``t``; ``world`` is the robot's state
        now (it reaches the operator later)."""
        if world is not None:
            self._views.append((self._arrival(t), t, world))
            if self._seen is None:
                self._seen = world
            self._seen, self._seen_sent = self._newest(self._views, t, self._seen, self._seen_sent)
        view = None
        if self._seen is not None:  # the operator acts now on what it has seen
            view = dataclasses.replace(self._seen, t=t)
        made = self.source.frame(t, view)
        if made is None:
            return None
        self._frames.append((self._arrival(t), t, made))
        if self._held is None:
            self._held = made
        self._held, self._held_sent = self._newest(self._frames, t, self._held, self._held_sent)
        if self._stamp0 is None:
            self._stamp0 = float(self._held.stamp)
        return dataclasses.replace(self._held, stamp=self._stamp0 + t)

    @property
    def finished(self) -> bool:
        return bool(self.source.finished)

    @property
    def operator(self) -> Any:
        """The synthetic operator behind the link (``None`` for other sources)."""
        return getattr(self.source, "operator", None)


__all__ = ["DelayedLink", "LinkError", "parse_link_delay"]
