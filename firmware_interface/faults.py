"""Fault specifications for the emulated bus (``payload hw emulate --fault SPEC``).

=======================  ==============================================================
spec                     effect
=======================  ==============================================================
``missing:7``            servo 7 is absent from the bus (never answers)
``corrupt:0.01``         each reply has one bit flipped with probability 0.01
``latency:3ms``          every reply comes 3 ms late (``us``, ``ms``, ``s``)
``drop:0.02``            each reply is lost with probability 0.02
``error:12:overload``    servo 12 latches a hardware error bit (``input_voltage``,
                         ``overheating``, ``encoder``, ``electrical_shock``, ``overload``)
``block:12``             servo 12's shaft is blocked: while a command drives its current to
                         the cap it stays there, and after a second at the cap in all the
                         overload bit trips (a servo held at its goal never trips)
``model:12:1060``        servo 12 reports model number 1060 (another Dynamixel model on
                         the map's ID) in its ping and its Model Number register
=======================  ==============================================================
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from firmware_interface.control_table import HW_ERROR_BITS
from payload.errors import PayloadError

FAULT_FORMS: tuple[str, ...] = (
    "missing:ID",
    "corrupt:P",
    "latency:3ms",
    "drop:P",
    "error:ID:BIT",
    "block:ID",
    "model:ID:NUMBER",
)
"""The forms of a fault spec (the table above), as the help and the errors list them."""


class FaultSpecError(PayloadError):
    """A fault spec that cannot be parsed; the message names it."""


@dataclass(frozen=True)
class Fault:
    """One parsed fault.

    Attributes:
        kind: ``missing``, ``corrupt``, ``latency``, ``drop``, ``error``, ``block`` or
            ``model``.
        id: Servo ID (missing, error, block, model).
        value: Probability (corrupt, drop), delay [s] (latency) or model number (model).
        bit: Hardware error bit name (error).
    """

    kind: str
    id: int | None = None
    value: float = 0.0
    bit: str | None = None


_UNITS = {"us": 1e-6, "ms": 1e-3, "s": 1.0}


def _servo_id(text: str, spec: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 252:
        raise FaultSpecError(f"fault {spec!r}: servo ID must be 0..252, got {text!r}")
    return int(text)


def _probability(text: str, spec: str) -> float:
    try:
        p = float(text)
    except ValueError:
        p = -1.0
    if not 0.0 <= p <= 1.0:
        raise FaultSpecError(f"fault {spec!r}: probability must be in [0, 1], got {text!r}")
    return p


def parse_fault(spec: str) -> Fault:
    """Parse one spec (see the module docstring).

    Raises:
        FaultSpecError: Unknown kind, bad ID, probability, delay or error bit.
    """
    parts = spec.strip().split(":")
    kind = parts[0]
    if kind in ("missing", "block") and len(parts) == 2:
        return Fault(kind, id=_servo_id(parts[1], spec))
    if kind in ("corrupt", "drop") and len(parts) == 2:
        return Fault(kind, value=_probability(parts[1], spec))
    if kind == "latency" and len(parts) == 2:
        m = re.fullmatch(r"([0-9]*\.?[0-9]+)(us|ms|s)", parts[1])
        if m is None:
            raise FaultSpecError(f"fault {spec!r}: latency must look like 3ms, 500us or 0.1s")
        return Fault(kind, value=float(m.group(1)) * _UNITS[m.group(2)])
    if kind == "error" and len(parts) == 3:
        if parts[2] not in HW_ERROR_BITS:
            raise FaultSpecError(
                f"fault {spec!r}: error bit must be one of {', '.join(HW_ERROR_BITS)}"
            )
        return Fault(kind, id=_servo_id(parts[1], spec), bit=parts[2])
    if kind == "model" and len(parts) == 3:
        if not parts[2].isdigit() or int(parts[2]) > 0xFFFF:
            raise FaultSpecError(f"fault {spec!r}: model number must be 0..65535")
        return Fault(kind, id=_servo_id(parts[1], spec), value=float(parts[2]))
    raise FaultSpecError(
        f"fault {spec!r}: expected {', '.join(FAULT_FORMS[:-1])} or {FAULT_FORMS[-1]}"
    )
