"""The bus options every command that opens the servo bus shares (the ``hw`` commands and
``payload teleop serve --driver hardware``): the servo map and the reply timeout's latency
allowance. Standard library only: a command's parser is built before anything loads.
"""

from __future__ import annotations

import argparse
import math

LATENCY_MS = 16.0
"""The reply timeout's allowance for the USB adapter's latency [ms]: the SDK's
``LATENCY_TIMER``, an FTDI adapter's factory latency timer (``--latency-ms``)."""

EMULATOR_LATENCY_MS = 50.0
"""The allowance on an emulated bus the command starts itself (``--emulator``) when
``--latency-ms`` is not given [ms]: the emulator is a Python process on the same host, not
an adapter, and on a loaded two-core host it answers later than 16 ms allows (the driver's
tests take it for the same reason)."""


def add_servo_map(p: argparse.ArgumentParser, text: str = "servo map TOML") -> None:
    """``--servos MAP``: the servo map (default: the packaged map)."""
    p.add_argument("--servos", metavar="MAP", help=text)


def add_latency(p: argparse.ArgumentParser, when: str = "", emulator: str | None = None) -> None:
    """``--latency-ms MS`` (default :data:`LATENCY_MS`; ``when`` saying when it applies).
    ``emulator``: when the command starts an emulated bus itself ("with --emulator"), where
    the default is :data:`EMULATOR_LATENCY_MS` instead: the option's default is then None,
    the command's allowance :func:`latency_of` the option."""
    on_emulator = f", {EMULATOR_LATENCY_MS:g} {emulator}" if emulator else ""
    p.add_argument(
        "--latency-ms",
        type=float,
        metavar="MS",
        default=None if emulator else LATENCY_MS,
        help=f"reply timeout allowance per packet [ms] (the SDK's LATENCY_TIMER{when}; "
        f"default {LATENCY_MS:g}, a USB adapter's{on_emulator})",
    )


def latency_of(given: float | None, emulated: bool) -> float:
    """The reply timeout's latency allowance a command uses [ms]: ``--latency-ms`` as
    given, else :data:`EMULATOR_LATENCY_MS` on an emulated bus the command started
    (``emulated``), else :data:`LATENCY_MS`."""
    if given is not None:
        return given
    return EMULATOR_LATENCY_MS if emulated else LATENCY_MS


def latency_problem(value: float | None) -> str | None:
    """Why ``--latency-ms`` cannot be used (a NaN or infinite reply timeout would wait
    forever on a silent servo), or None."""
    if value is not None and not 0.0 <= value < math.inf:
        return f"--latency-ms must be a finite number of ms >= 0, got {value}"
    return None


__all__ = [
    "EMULATOR_LATENCY_MS",
    "LATENCY_MS",
    "add_latency",
    "add_servo_map",
    "latency_of",
    "latency_problem",
]
