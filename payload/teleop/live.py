"""The live headset as a hand source: frames from the WebXR page, resampled to the 50 Hz loop.

The server (an asyncio thread) puts each validated frame into a :class:`LiveHub`; the
teleoperation loop (another thread) takes the newest one at every control step
(sample-and-hold: at 72 to 120 Hz display rates a fresh frame is at most one display
period old). The hub also holds what both sides report: counters for ``/status``, the
frame ages, the end-to-end latencies and the session state the page shows.

Safety: when no page holds control (it disconnected, handed control over or left VR), or
its newest frame is older than ``stale_s``, or it reports a hand as not tracked, that hand
is declared lost to the pipeline's tracking supervisor at once, so the vehicle brakes and
the fingers hold from that very control step; frames coming back blend the channels in
again (no recalibration). The reason says which (:data:`DISCONNECTED`,
:data:`HANDED_OVER`, :data:`LEFT_VR`, a stale link or an untracked hand).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from payload.schema import PayloadCommand
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.hands import Hand, HandFrame
from payload.teleop.messages import DROP_KINDS, FrameMessage
from payload.teleop.operator import WorldView
from payload.teleop.pipeline import TeleopPipeline

MAX_CLIENTS = 4
"""Open WebSocket connections the server takes at once: an operator, a spare page, a few
watchers (``/status`` says it as ``max_clients``, for the page)."""
STALE_S = 0.1
"""A frame older than this is no longer the operator's hand [s] (the supervisor's timeout)."""


def now_ms() -> float:
    """The server clock [ms] (monotonic)."""
    return time.perf_counter() * 1e3


def percentiles(values: Any) -> dict[str, float | None]:
    """``{"median", "p99"}`` of a sequence (None when empty: JSON has no NaN)."""
    arr = np.asarray(list(values), dtype=float)
    if arr.size == 0:
        return {"median": None, "p99": None}
    return {"median": float(np.median(arr)), "p99": float(np.percentile(arr, 99))}


@dataclass
class Received:
    """The newest frame of the active connection.

    Attributes:
        message: The validated frame.
        arrival_ms: Server clock at arrival [ms].
        xr_server_ms: The XR frame time on the server clock [ms] (None before clock sync).
    """

    message: FrameMessage
    arrival_ms: float
    xr_server_ms: float | None


SIMULATOR = "simulator"
"""The driver's name when the loop drives the simulator alone (:attr:`LiveHub.driver`)."""

DISCONNECTED = "page disconnected"
"""Why control was given up when the holder's WebSocket closed (a safe stop's reason)."""
HANDED_OVER = "operator handed control over"
"""Why, when the holder pressed Hand over control (``release``)."""
LEFT_VR = "operator left VR"
"""Why, when the holder's XR session ended (Exit VR, ``xr_end``): the page stays connected."""

HOLDER = "holder"
"""A page's role when it holds control (:meth:`LiveHub.role`); the page compares a state
message's ``notice_to`` with it."""


@dataclass
class LiveHub:
    """State shared by the server thread and the loop thread (all access under ``lock``)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    clients: int = 0
    active: int | None = None  # id of the connection that holds control (drives)
    released: str = DISCONNECTED  # why the last holder gave control up (while none holds it)
    driver: str = SIMULATOR  # what the loop drives: "simulator" / "hardware on DEVICE"
    latest: Received | None = None
    frames: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_KINDS, 0))
    frame_age_ms: deque = field(default_factory=lambda: deque(maxlen=20000))
    latency_ms: deque = field(default_factory=lambda: deque(maxlen=20000))
    loop_overruns: int = 0
    state: str = "waiting"
    snapshot: dict[str, Any] = field(default_factory=dict)
    snapshot_seq: int = 0
    stop: threading.Event = field(default_factory=threading.Event)

    def drop(self, kind: str) -> None:
        with self.lock:
            self.dropped[kind] += 1

    def connect(self, conn_id: int) -> None:
        """A new connection: it watches until it takes control (see :meth:`put`)."""
        with self.lock:
            self.clients += 1

    def disconnect(self, conn_id: int) -> None:
        """A connection closed: control is free again if it held it."""
        self.release(conn_id, DISCONNECTED)
        with self.lock:
            self.clients -= 1

    def release(self, conn_id: int, why: str = HANDED_OVER) -> bool:
        """The holder gives control up (``why``: :data:`HANDED_OVER`, :data:`LEFT_VR`,
        :data:`DISCONNECTED`, the safe stop's reason until another page takes control);
        returns whether ``conn_id`` held it."""
        with self.lock:
            if self.active != conn_id:
                return False
            self.active = None
            self.latest = None
            self.released = why
            return True

    @property
    def drives_hardware(self) -> bool:
        """Whether the loop drives real servos (or an emulated bus) besides the simulator."""
        return self.driver != SIMULATOR

    def role(self, conn_id: int) -> str:
        """``holder``, ``watching`` (another connection holds control) or ``free``."""
        with self.lock:
            if self.active is None:
                return "free"
            return HOLDER if self.active == conn_id else "watching"

    def put(self, conn_id: int, message: FrameMessage, offset_ms: float | None) -> bool:
        """Store a validated frame; ``offset_ms`` = page clock - server clock.

        The first connection to send frames while control is free takes it (it is the one
        that calibrates); another connection's frames are refused (counted ``not_holder``)
        until the holder disconnects or hands over. Returns whether the frame was taken.
        """
        arrival = now_ms()
        xr = None if offset_ms is None else message.t - offset_ms
        with self.lock:
            if self.active is None:
                self.active = conn_id
            if self.active != conn_id:
                self.dropped["not_holder"] += 1
                return False
            self.frames += 1
            if xr is not None:
                self.frame_age_ms.append(arrival - xr)
            self.latest = Received(message, arrival, xr)
            return True

    def publish(self, snapshot: dict[str, Any], state: str | None = None) -> None:
        """Set the snapshot the page shows, and with it the state (from the loop thread)."""
        with self.lock:
            self.snapshot = snapshot
            self.snapshot_seq += 1
            if state is not None:
                self.state = state

    def status(self) -> dict[str, Any]:
        """The ``/status`` document."""
        with self.lock:
            return {
                "state": self.state,
                "driver": self.driver,
                "operator": "holding" if self.active is not None else "none",
                "clients": int(self.clients),
                "max_clients": MAX_CLIENTS,
                "frames": int(self.frames),
                "dropped": {k: int(v) for k, v in self.dropped.items()},
                "frame_age_ms": percentiles(self.frame_age_ms),
                "loop_overruns": int(self.loop_overruns),
            }

    def latency(self) -> dict[str, float]:
        """XR frame -> command sent to the driver [ms], median and p99."""
        with self.lock:
            return percentiles(self.latency_ms)


class LiveSource:
    """The hub as a :class:`~payload.teleop.loop.HandSource` for one session attempt.

    Args:
        hub: The shared hub.
        calibration: This attempt's calibration procedure (the attempt ends, returning
            None, when the page goes away before calibration is done).
        stale_s: Frame age beyond which a hand counts as lost [s].
    """

    def __init__(
        self, hub: LiveHub, calibration: CalibrationProcedure, stale_s: float = STALE_S
    ) -> None:
        self.hub = hub
        self.calibration = calibration
        self.stale_s = stale_s
        self.pipeline: TeleopPipeline | None = None
        self.used: Received | None = None
        self.lost_reason: str | None = None
        self._ended = False

    def frame(self, t: float, world: WorldView | None) -> HandFrame | None:
        with self.hub.lock:
            connected = self.hub.active is not None
            latest = self.hub.latest
            released = self.hub.released
        if self.hub.stop.is_set() or (not self.calibration.done and not connected):
            self._ended = True
            return None
        reason = None
        if not connected:
            reason = released  # disconnected, handed over or left VR
        elif latest is None or now_ms() - latest.arrival_ms > self.stale_s * 1e3:
            reason = f"no frame from the page for > {self.stale_s * 1e3:.0f} ms"
        if reason is not None:
            self.used = None
            left = right = Hand.untracked()
        else:
            self.used = latest
            left, right = latest.message.left, latest.message.right
        reasons = {}
        for side, hand in (("left", left), ("right", right)):
            if not hand.tracked:
                reasons[side] = reason or f"{side} hand not tracked by the headset"
        self.lost_reason = "; ".join(sorted(set(reasons.values()))) or None
        if self.pipeline is not None:
            for side, why in reasons.items():
                self.pipeline.supervisor.force_lost(side, t, why)
        return HandFrame(t, left, right, "webxr")

    @property
    def finished(self) -> bool:
        return self._ended


class TimedDriver:
    """A driver proxy that measures XR frame -> command sent, per control step.

    Args:
        driver: The real driver (simulator or hardware).
        source: The live source whose last used frame the command comes from.
        hub: Where the latencies go.
    """

    def __init__(self, driver: Any, source: LiveSource, hub: LiveHub) -> None:
        self._driver = driver
        self._source = source
        self._hub = hub

    def send(self, command: PayloadCommand) -> None:
        self._driver.send(command)
        used = self._source.used
        if used is not None and used.xr_server_ms is not None:
            latency = now_ms() - used.xr_server_ms
            with self._hub.lock:
                self._hub.latency_ms.append(latency)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._driver, name)
