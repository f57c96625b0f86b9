"""Messages between the WebXR page and the teleop server: validation of what the page sends.

The page sends JSON text, one message per XR frame::

    {"type": "frame", "seq": int, "t": float,          # XR frame time [ms], page clock
     "hands": {"left": {"tracked": bool, "joints": [[x, y, z] x 25]} | null,
               "right": same}}

joints in WebXR's XRHand order and the ``local-floor`` reference space (metres, Y up), and
answers the server's clock pings with ``{"type": "pong", "id": int, "t": float}`` (page
clock [ms]); ``{"type": "release"}`` hands control over (the page's button), and
``{"type": "xr_end"}`` says the page's XR session ended (Exit VR) and hands control over
too (a safe stop then says the operator left VR, not that the page disconnected).
Anything else is rejected with one of the :data:`DROP_KINDS`, never raised past the server.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.teleop.hands import Hand

MAX_MESSAGE_BYTES = 64 * 1024
"""Largest message accepted [bytes]; a full two-hand frame is about 3 KiB."""

MAX_COORD_M = 100.0
"""A joint coordinate beyond this is not a hand in a room [m]."""

DROP_KINDS: tuple[str, ...] = (
    "malformed",
    "oversized",
    "non_finite",
    "out_of_order",
    "unauthorized",
    "rate_limited",
    "not_holder",
    "connection_cap",
)
"""Why a message or a connection was refused (the ``/status`` ``dropped`` counters)."""


class MessageError(PayloadError):
    """A message from the page was refused.

    Attributes:
        kind: One of :data:`DROP_KINDS`.
    """

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


@dataclass(frozen=True)
class FrameMessage:
    """One validated XR frame.

    Attributes:
        seq: Sequence number (strictly increasing per connection).
        t: XR frame time, page clock [ms].
        left: Left hand (untracked when the page sent null or ``tracked: false``).
        right: Right hand.
    """

    seq: int
    t: float
    left: Hand
    right: Hand


@dataclass(frozen=True)
class PongMessage:
    """The page's answer to a clock ping.

    Attributes:
        id: The ping's id.
        t: Page clock when the ping was answered [ms].
    """

    id: int
    t: float


def _reject_constant(name: str) -> Any:
    raise MessageError("non_finite", f"{name} is not a finite number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise MessageError("non_finite", f"{text[:20]} overflows a double")
    return value


def _number(obj: Any, where: str) -> float:
    if isinstance(obj, bool) or not isinstance(obj, (int, float)):
        raise MessageError("malformed", f"{where} must be a number, got {type(obj).__name__}")
    value = float(obj)
    if not math.isfinite(value):
        raise MessageError("non_finite", f"{where} is not finite")
    return value


def _integer(obj: Any, where: str) -> int:
    if isinstance(obj, bool) or not isinstance(obj, int):
        raise MessageError("malformed", f"{where} must be an integer, got {type(obj).__name__}")
    if not 0 <= obj < 2**53:
        raise MessageError("malformed", f"{where} out of range")
    return obj


def _hand(obj: Any, side: str) -> Hand:
    where = f"hands.{side}"
    if obj is None:
        return Hand.untracked()
    if not isinstance(obj, dict) or set(obj) != {"tracked", "joints"}:
        raise MessageError("malformed", f"{where} must be null or {{tracked, joints}}")
    tracked = obj["tracked"]
    if not isinstance(tracked, bool):
        raise MessageError("malformed", f"{where}.tracked must be a boolean")
    joints = obj["joints"]
    if joints is None and not tracked:
        return Hand.untracked()
    if not isinstance(joints, list) or len(joints) != 25:
        raise MessageError("malformed", f"{where}.joints must be a list of 25 points")
    rows = []
    for i, p in enumerate(joints):
        if not isinstance(p, list) or len(p) != 3:
            raise MessageError("malformed", f"{where}.joints[{i}] must be [x, y, z]")
        rows.append([_number(v, f"{where}.joints[{i}]") for v in p])
    arr = np.asarray(rows, dtype=np.float64)
    if np.any(np.abs(arr) > MAX_COORD_M):
        raise MessageError("malformed", f"{where}: a joint is more than {MAX_COORD_M} m away")
    return Hand(arr, tracked) if tracked else Hand.untracked()


@dataclass(frozen=True)
class ReleaseMessage:
    """The page hands control over (its operator leaves the controls)."""


@dataclass(frozen=True)
class XrEndMessage:
    """The page's XR session ended (the operator pressed Exit VR): control is handed over,
    the page stays connected."""


def message_bytes(data: str | bytes) -> int:
    """A message's size on the wire [bytes] (UTF-8 for text)."""
    if isinstance(data, bytes):
        return len(data)
    return len(data.encode("utf-8", "surrogatepass"))


def parse_message(
    data: str | bytes,
) -> FrameMessage | PongMessage | ReleaseMessage | XrEndMessage:
    """Validate one message from the page.

    Args:
        data: The WebSocket message (text expected).

    Raises:
        MessageError: With ``kind`` oversized, malformed or non_finite.
    """
    size = message_bytes(data)
    if size > MAX_MESSAGE_BYTES:
        raise MessageError("oversized", f"{size} bytes > {MAX_MESSAGE_BYTES}")
    if isinstance(data, bytes):
        raise MessageError("malformed", "binary message (JSON text expected)")
    try:
        obj = json.loads(data, parse_constant=_reject_constant, parse_float=_finite_float)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise MessageError("malformed", f"not JSON ({exc})") from None
    except ValueError as exc:  # int too large to convert, and the like
        raise MessageError("malformed", f"not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise MessageError("malformed", "a message must be a JSON object")
    kind = obj.get("type")
    if kind == "release":
        if set(obj) != {"type"}:
            raise MessageError("malformed", "release has only a type")
        return ReleaseMessage()
    if kind == "xr_end":
        if set(obj) != {"type"}:
            raise MessageError("malformed", "xr_end has only a type")
        return XrEndMessage()
    if kind == "pong":
        if set(obj) != {"type", "id", "t"}:
            raise MessageError("malformed", "pong needs exactly type, id, t")
        return PongMessage(_integer(obj["id"], "id"), _number(obj["t"], "t"))
    if kind != "frame":
        raise MessageError("malformed", f"unknown message type {str(kind)[:40]!r}")
    if set(obj) != {"type", "seq", "t", "hands"}:
        raise MessageError("malformed", "frame needs exactly type, seq, t, hands")
    hands = obj["hands"]
    if not isinstance(hands, dict) or set(hands) != {"left", "right"}:
        raise MessageError("malformed", "hands must be an object with left and right")
    return FrameMessage(
        _integer(obj["seq"], "seq"),
        _number(obj["t"], "t"),
        _hand(hands["left"], "left"),
        _hand(hands["right"], "right"),
    )
