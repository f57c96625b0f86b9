"""Errors of the hardware interface; all are :class:`~payload.errors.PayloadError`."""

from __future__ import annotations

from collections.abc import Sequence

from payload.errors import PayloadError, RunAborted


def cannot_open(port: str, reason: str | None = None) -> str:
    """The one wording of a serial device that cannot be opened: ``/dev/ttyUSB9: cannot
    open the serial port (No such file or directory)`` (the system's reason, once)."""
    return f"{port}: cannot open the serial port" + (f" ({reason})" if reason else "")


def missing_device(device: str | None) -> str | None:
    """:func:`cannot_open`'s words for a device path that is not there (the system's
    reason), for a command to refuse before any work; ``None`` for one that is there, no
    path (a name without a ``/`` is the driver's to try) or none given."""
    import errno
    import os

    if not device or "/" not in device or os.path.lexists(device):
        return None
    return cannot_open(device, os.strerror(errno.ENOENT))


class DynamixelError(PayloadError):
    """Root of the hardware interface's errors.

    Attributes:
        also: The other faults found with this one (a bring-up looks at every servo
            before it refuses them; a health read finds every servo at fault at once):
            each its own error, named in this one's message.
    """

    also: tuple[DynamixelError, ...] = ()

    @property
    def alone(self) -> str:
        """Its own message, without the faults found with it."""
        return getattr(self, "_alone", str(self))

    def joined(self, also: Sequence[DynamixelError]) -> DynamixelError:
        """This error with ``also``, the faults found with it: its message names each,
        its own words first (the most severe fault's type and attributes are the error's)."""
        self._alone = self.alone
        self.also = tuple(also)
        self.args = ("; ".join([self._alone, *(f.alone for f in self.also)]),)
        return self


class CommError(DynamixelError):
    """A packet was lost or corrupted (timeout, CRC) after the retries."""


class MissingServoError(DynamixelError):
    """Servos that did not answer at bring-up.

    Attributes:
        ids: Their IDs.
        joints: Their joints.
    """

    def __init__(self, ids: list[int], joints: list[str], everyone: bool = False) -> None:
        self.ids = list(ids)
        self.joints = list(joints)
        self.everyone = everyone  # no servo of the map answered
        names = ", ".join(f"ID {i} ({j})" for i, j in zip(ids, joints))
        super().__init__(f"servo(s) not answering: {names}")


class HardwareFault(DynamixelError):
    """A servo latched a hardware error; the payload is stopped until recovered.

    Attributes:
        id: The servo.
        joint: Its joint.
        bits: Names of the Hardware Error Status bits set (``["reset"]``: the servo was
            found torque off with no error, restarted by a power loss or a REBOOT).

    ``also`` given here (the other servos a health read found at fault at the same
    time) names them by ID after its own words; :meth:`~DynamixelError.joined` (a
    bring-up's faults) names them by their own words instead.
    """

    def __init__(
        self, dxl_id: int, joint: str, bits: list[str], also: Sequence[HardwareFault] = ()
    ) -> None:
        self.id = dxl_id
        self.joint = joint
        self.bits = list(bits)
        self.also = tuple(also)
        what = (
            "reset: torque off with no hardware error (power lost, or rebooted)"
            if self.bits == ["reset"]
            else f"hardware error {', '.join(bits) or 'unknown'}"
        )
        self._alone = f"servo {dxl_id} ({joint}): {what}"
        more = f" (also IDs {', '.join(str(f.id) for f in self.also)})" if self.also else ""
        super().__init__(f"{self._alone}{more}")


class WrongModelError(DynamixelError):
    """A servo that reports another model number than the servo map's (refused at
    bring-up: its control table, units and limits are not the ones the driver writes).

    Attributes:
        id: The servo.
        joint: Its joint.
        model: The model number it reported.
        expected: The map's.
    """

    def __init__(self, dxl_id: int, joint: str, model: int, expected: int) -> None:
        self.id, self.joint, self.model, self.expected = dxl_id, joint, model, expected
        super().__init__(f"servo {dxl_id} ({joint}): model number {model}, not the servo "
                         f"map's {expected}: another servo on this ID?")  # fmt: skip


class NotHomedError(DynamixelError):
    """A command for the rail or the stage before their absolute position is known."""


class HomingError(DynamixelError):
    """Homing did not find the hard stop (the message names the servo)."""


class BringUpFailed(RunAborted):
    """The payload could not be brought up or driven home (a servo missing or faulted,
    homing or the home posture failed): a failed start of the hardware (exit 1, ``payload:
    aborted: ...``), not bad input. The servos are left as the driver's close leaves them
    (torque off; one of another model than the map's untouched)."""
