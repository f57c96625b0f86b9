"""The command schema shared by the simulator and the hardware driver.

Plain, typed, immutable data. The 17 manipulation coordinates follow the paper's
eq. 1 order: fingers A, B, C, D (MCP flexion, MCP abduction, PIP, DIP each),
then the pair-spacing rail. The deployment coordinate (stage) is separate.
Vehicle motion is a separate type: Astrobee is not part of the payload.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntFlag
from types import TracebackType
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np

from payload.design.tree import MANIPULATION_JOINTS
from payload.errors import PayloadError
from payload.rates import CONTROL_DT, PHYSICS_DT
from payload.vecmath import F64, all_finite

N_MANIPULATION = len(MANIPULATION_JOINTS)  # 17
_SHAPE = (N_MANIPULATION,)
_SHAPE3 = (3,)

ENDED_BY_CAP = "max_time"
"""A session's ``ended_by`` (the loop's statistics, a recording's metadata, a trial's
metrics) when the ``--max-time`` cap stopped it."""
CAP_STOPPED = "stopped by the --max-time cap"
"""How a trial the ``--max-time`` cap ended (:data:`ENDED_BY_CAP`) is said, in lines,
tables and figures."""

ENDED_BY_SOURCE = "source"
"""A session's ``ended_by`` when its hands ran out: the operator finished, or a replay's
recording ended."""


class SchemaError(PayloadError):
    """A command or state does not satisfy the schema."""


def _frozen_vector(values: object, n: int, what: str, allow_nan: bool = False) -> np.ndarray:
    arr = np.array(values, dtype=np.float64).reshape(-1)
    if arr.shape != (n,):
        raise SchemaError(f"{what}: expected {n} values, got {arr.size}")
    if not allow_nan and not all_finite(arr):
        names = MANIPULATION_JOINTS if n == N_MANIPULATION else ()
        bad = [names[i] for i in np.flatnonzero(~np.isfinite(arr))] if names else []
        raise SchemaError(f"{what}: non-finite value(s) {bad or arr.tolist()}")
    arr.setflags(write=False)
    return arr


def _as_is(a: object, shape: tuple[int, ...]) -> bool:
    """Whether ``a`` is a read-only float64 array of ``shape``: what an ``of_frozen``
    constructor takes as it is (the constructor would copy it into just such an array)."""
    return type(a) is np.ndarray and a.dtype == F64 and a.shape == shape and not a.flags.writeable


_T = TypeVar("_T")


def _taken(cls: type[_T], **fields: object) -> _T:
    """An instance of the frozen dataclass ``cls`` with ``fields`` as they are (its
    ``__post_init__`` not run: the ``of_frozen`` constructors checked them)."""
    self = object.__new__(cls)
    self.__dict__.update(fields)
    return self


@dataclass(frozen=True)
class PayloadCommand:
    """Position command for the payload.

    Attributes:
        q: The 17 manipulation coordinates, shape (17,) [rad, rail in m].
        deploy: The deployment (stage) coordinate [m], 0 = stowed.
        stamp: Time of the command [s].
    """

    q: np.ndarray
    deploy: float
    stamp: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "q", _frozen_vector(self.q, N_MANIPULATION, "PayloadCommand.q"))
        if not math.isfinite(self.deploy):
            raise SchemaError("PayloadCommand.deploy: not finite")
        if not math.isfinite(self.stamp):
            raise SchemaError("PayloadCommand.stamp: not finite")

    @classmethod
    def of_frozen(cls, q: np.ndarray, deploy: float, stamp: float) -> PayloadCommand:
        """The command of a vector made for it (:meth:`PayloadState.of_frozen`'s
        contract): a read-only float64 array of 17 that nothing writes to again, taken as
        it is and checked finite with the two numbers; anything else is built (and
        checked) as the constructor does."""
        if _as_is(q, _SHAPE) and all_finite(q) and math.isfinite(deploy) and math.isfinite(stamp):
            return _taken(cls, q=q, deploy=deploy, stamp=stamp)
        return cls(q, deploy, stamp)  # says what is wrong

    def as_dict(self) -> dict[str, float]:
        """Joint name -> value, the deployment coordinate under ``stage``."""
        out = {n: float(v) for n, v in zip(MANIPULATION_JOINTS, self.q)}
        out["stage"] = float(self.deploy)
        return out

    @staticmethod
    def from_dict(values: dict[str, float], stamp: float) -> PayloadCommand:
        """Build from joint names (missing manipulation joints are an error)."""
        missing = [n for n in MANIPULATION_JOINTS if n not in values]
        if missing:
            raise SchemaError(f"PayloadCommand: missing joints {missing}")
        return PayloadCommand(
            np.array([values[n] for n in MANIPULATION_JOINTS]),
            float(values.get("stage", 0.0)),
            stamp,
        )


class Health(IntFlag):
    """Health flags of a :class:`PayloadState` (0 = all good)."""

    OK = 0
    STALE = 1  # the reading is older than expected
    MISSING_SERVO = 2  # at least one servo did not answer
    HARDWARE_ERROR = 4  # a servo reported a hardware error (needs a reboot)
    OVERLOAD = 8  # a joint is at its effort limit
    LIMIT = 16  # a joint is at or beyond a position limit


HEALTHS: tuple[Health, ...] = tuple(
    Health(bits) for bits in range(1 << max(flag.value for flag in Health).bit_length())
)
"""Every combination of the flags, by its value (``HEALTHS[bits]`` is ``Health(bits)``,
without the enum's call)."""


@dataclass(frozen=True)
class PayloadState:
    """Measured state of the payload.

    Attributes:
        q: Positions of the 17 manipulation coordinates, shape (17,).
        deploy: Deployment coordinate [m].
        stamp: Time of the measurement [s].
        dq: Velocities, shape (17,), NaN where not measured.
        effort: Efforts [N m or N], shape (17,), NaN where not measured.
        health: Health flags.
    """

    q: np.ndarray
    deploy: float
    stamp: float
    dq: np.ndarray = field(default_factory=lambda: np.full(N_MANIPULATION, np.nan))
    effort: np.ndarray = field(default_factory=lambda: np.full(N_MANIPULATION, np.nan))
    health: Health = Health.OK

    def __post_init__(self) -> None:
        object.__setattr__(self, "q", _frozen_vector(self.q, N_MANIPULATION, "PayloadState.q"))
        object.__setattr__(
            self, "dq", _frozen_vector(self.dq, N_MANIPULATION, "PayloadState.dq", True)
        )
        object.__setattr__(
            self, "effort", _frozen_vector(self.effort, N_MANIPULATION, "PayloadState.effort", True)
        )

    @classmethod
    def of_frozen(
        cls,
        q: np.ndarray,
        deploy: float,
        stamp: float,
        dq: np.ndarray,
        effort: np.ndarray,
        health: Health = Health.OK,
    ) -> PayloadState:
        """The state of vectors made for it: read-only float64 arrays of 17 that nothing
        writes to again (a read-out's fresh buffer, frozen). They are taken as they are,
        not copied; ``q`` is still checked finite. Anything else is built (and checked) as
        the constructor does."""
        if _as_is(q, _SHAPE) and _as_is(dq, _SHAPE) and _as_is(effort, _SHAPE) and all_finite(q):
            return _taken(cls, q=q, deploy=deploy, stamp=stamp, dq=dq, effort=effort, health=health)
        return cls(q, deploy, stamp, dq, effort, health)  # says what is wrong


@dataclass(frozen=True)
class VehicleTwist:
    """Requested Astrobee body twist (REP-103 body frame).

    Attributes:
        linear: Linear velocity, shape (3,) [m/s].
        angular: Angular velocity, shape (3,) [rad/s].
        stamp: [s].
    """

    linear: np.ndarray
    angular: np.ndarray
    stamp: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "linear", _frozen_vector(self.linear, 3, "VehicleTwist.linear"))
        object.__setattr__(self, "angular", _frozen_vector(self.angular, 3, "VehicleTwist.angular"))

    @classmethod
    def of_frozen(cls, linear: np.ndarray, angular: np.ndarray, stamp: float) -> VehicleTwist:
        """The twist of vectors made for it (:meth:`PayloadState.of_frozen`'s contract):
        read-only float64 arrays of 3 that nothing writes to again, taken as they are and
        checked finite; anything else is built (and checked) as the constructor does."""
        a, b = linear, angular
        if _as_is(a, _SHAPE3) and _as_is(b, _SHAPE3) and all_finite(a) and all_finite(b):
            return _taken(cls, linear=linear, angular=angular, stamp=stamp)
        return cls(linear, angular, stamp)  # says what is wrong

    @staticmethod
    def zero(stamp: float = 0.0) -> VehicleTwist:
        return VehicleTwist(np.zeros(3), np.zeros(3), stamp)


@runtime_checkable
class PayloadDriver(Protocol):
    """What the teleoperation loop needs of a payload: the simulator or the hardware."""

    def send(self, command: PayloadCommand) -> None:
        """Send one position command."""

    def read(self) -> PayloadState:
        """Read the latest measured state."""

    def close(self) -> None:
        """Release the driver (idempotent)."""

    def __enter__(self) -> PayloadDriver: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


__all__ = [
    "CONTROL_DT",
    "N_MANIPULATION",
    "PHYSICS_DT",
    "Health",
    "PayloadCommand",
    "PayloadDriver",
    "PayloadState",
    "SchemaError",
    "VehicleTwist",
]
