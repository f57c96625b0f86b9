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


def add_servo_map(p: argparse.ArgumentParser, text: str = "servo map TOML") -> None:
    """``--servos MAP``: the servo map (default: the packaged map)."""
    p.add_argument("--servos", metavar="MAP", help=text)


def add_latency(
    p: argparse.ArgumentParser, when: str = "", default: float | None = LATENCY_MS
) -> None:
    """``--latency-ms MS`` (default :data:`LATENCY_MS`; ``default=None`` where the option
    is refused unless it applies, ``when`` saying when it does)."""
    p.add_argument(
        "--latency-ms",
        type=float,
        metavar="MS",
        default=default,
        help=f"reply timeout allowance per packet [ms] (the SDK's LATENCY_TIMER{when}; "
        f"default {LATENCY_MS:g})",
    )


def latency_problem(value: float | None) -> str | None:
    """Why ``--latency-ms`` cannot be used (a NaN or infinite reply timeout would wait
    forever on a silent servo), or None."""
    if value is not None and not 0.0 <= value < math.inf:
        return f"--latency-ms must be a finite number of ms >= 0, got {value}"
    return None


__all__ = ["LATENCY_MS", "add_latency", "add_servo_map", "latency_problem"]
