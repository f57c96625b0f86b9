"""Exception family of the workbench: catch :class:`PayloadError` to catch them all."""

from __future__ import annotations


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


class BuildError(PayloadError):
    """Generating the models failed (a solid is not watertight, a file cannot be written)."""


class RunAborted(Exception):
    """A run started and was aborted by an unexpected error (exit 1, not a bad input).

    What it had recorded is kept; the message says where.
    """
