"""Exception family of the workbench: catch :class:`PayloadError` to catch them all."""

from __future__ import annotations

import datetime
import json
import signal
from collections.abc import Sequence
from typing import Any


class PayloadError(Exception):
    """Root of every error the workbench raises on purpose."""


class DesignError(PayloadError):
    """The design file is invalid.

    Attributes:
        parameter: Dotted path of the offending parameter, e.g. ``finger.lengths.proximal``.
        reason: What is wrong with it.
    """

    def __init__(self, parameter: str, reason: str) -> None:
        self.parameter = parameter
        self.reason = reason
        super().__init__(f"{parameter}: {reason}")


def port_in_use_hint(server: str) -> str:
    """The advice beside a port that cannot be listened on (``review``, ``teleop serve``)."""
    return f"(another {server}? choose another --port, or --port 0 for any free port)"


def not_text(exc: UnicodeDecodeError, kind: str) -> str:
    """Why a binary file given where a text file of ``kind`` (``"TOML"``, ``"JSON"``) is
    expected cannot be read: the reason of a one-line error that names the file."""
    return f"not a text (UTF-8 {kind}) file: byte {exc.start} is 0x{exc.object[exc.start]:02x}"


def closest(word: str, options: Any) -> str | None:
    """The one of ``options`` a misspelt ``word`` is closest to (difflib's ratio, its
    default cutoff), for a "did you mean" in a one-line error; None when none is close."""
    import difflib

    near = difflib.get_close_matches(word, list(options), n=1)
    return near[0] if near else None


def counted(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural but for one (``1 point``, ``2 points``; nouns taking
    ``-s``)."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def first_of(items: Sequence[str], shown: int, where: str = "") -> str:
    """The first ``shown`` of ``items`` joined by "; ", and "(and N more)" when some are
    left out (``where``: where the rest are, "(and N more: payload report envelope)")."""
    left = len(items) - shown
    more = f" (and {left} more{': ' + where if where else ''})" if left > 0 else ""
    return "; ".join(items[:shown]) + more


def is_number(value: Any) -> bool:
    """A TOML number of a design file (an int or a float; a boolean is not one)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def as_toml(value: Any) -> str:
    """``value`` as a TOML design file spells it (``true``, ``"text"``, ``[1, 2]``), for a
    :class:`DesignError` about what the file holds (Python's ``True`` is not what the
    designer typed)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):  # a TOML basic string: JSON's escapes, newlines included
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (datetime.date, datetime.time)):  # TOML dates and times
        return value.isoformat()
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(as_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {as_toml(v)}" for k, v in value.items()) + "}"
    return repr(value)


class BuildError(PayloadError):
    """Generating the models failed (a solid is not watertight, a file cannot be written)."""


class RunAborted(Exception):
    """A run started and was aborted by an unexpected error (exit 1, not a bad input).

    What it had recorded is kept; the message says where.
    """


STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""The signals besides Ctrl-C's SIGINT that stop a ``payload`` command as Ctrl-C does
(:class:`Terminated`)."""


class Terminated(KeyboardInterrupt):
    """The process was asked to stop by a signal other than Ctrl-C (SIGTERM from ``kill``
    or a process manager, SIGHUP from a closed terminal). Raised in the main thread as a
    :class:`KeyboardInterrupt`, so every command's Ctrl-C clean-up runs: a recording is
    closed and marked aborted, the servos' torque is switched off.

    Attributes:
        signum: The signal's number (the exit code is ``128 + signum``).
    """

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)
