"""Contact definitions: the workbench's confirmed contact, and how a definition is named
to a reader (:class:`ContactWords`). Below both the scoring (:mod:`payload.trials.metrics`)
and the summaries (:mod:`payload.trials.summary_fields`), which import it."""

from __future__ import annotations

from typing import NamedTuple

CONFIRM_MIN_S = 0.5
"""The workbench's *confirmed* contact: opposing contact held at least this long [s]. The
pads chatter for a few tenths of a second when they first land on a handle at 50 Hz."""

CONFIRM_MAX_GAP_S = 0.1
"""Indicator dropouts at most this long are bridged inside a confirmed interval [s]."""


class ContactWords(NamedTuple):
    """How a contact definition is named to a reader: the contact itself, its first
    interval, and a trial's lack of one."""

    contact: str
    interval: str
    none: str


CONFIRMED_WORDS = ContactWords(
    "confirmed contact", "confirmed-contact interval", "no confirmed contact"
)
"""The workbench's confirmed contact (:func:`~payload.trials.metrics.confirmed_definition`)
as named to a reader; any other definition is named by its numbers
(:func:`contact_words`)."""

MIXED_WORDS = ContactWords(
    "mixed contact definitions", "contact interval (mixed definitions)", "no contact"
)
"""The contact of trials scored with different definitions, as named to a reader."""


def contact_words(min_interval_s: float, max_gap_s: float) -> ContactWords:
    """How the contact definition ``(min_interval_s, max_gap_s)`` is named to a reader:
    the confirmed contact (:func:`~payload.trials.metrics.confirmed_definition`), else by
    its numbers, e.g.
    ``contact (>= 0 s, gaps <= 0 s)`` (a rescoring's figures and summaries say what they
    scored)."""
    if (min_interval_s, max_gap_s) == (CONFIRM_MIN_S, CONFIRM_MAX_GAP_S):
        return CONFIRMED_WORDS
    numbers = f"(>= {min_interval_s:g} s, gaps <= {max_gap_s:g} s)"
    return ContactWords(
        f"contact {numbers}", f"contact interval {numbers}", f"no contact {numbers}"
    )


__all__ = [
    "CONFIRMED_WORDS",
    "CONFIRM_MAX_GAP_S",
    "CONFIRM_MIN_S",
    "MIXED_WORDS",
    "ContactWords",
    "contact_words",
]
