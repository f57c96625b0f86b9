"""Envelope and reach reports: Markdown, PNG figures (matplotlib) and JSON in ``analyses/``.

The pieces, one job each: :mod:`~payload.envelope.report_json` (the data),
:mod:`~payload.envelope.markdown`, :mod:`~payload.envelope.envelope_figure` and
:mod:`~payload.envelope.reach_figure` (with :mod:`~payload.envelope.drawing`), and
:mod:`~payload.envelope.writer` (the files, written only when a figure changed).
Each loads on first use: a report whose figures did not change is not drawn, and then
matplotlib is never imported.
"""

from __future__ import annotations

from payload.lazy import lazy_exports

_LAZY: dict[str, str] = {
    "FINGER_COLOURS": "payload.envelope.drawing",
    "STRUCTURE_COLOUR": "payload.envelope.drawing",
    "envelope_figure": "payload.envelope.envelope_figure",
    "envelope_json": "payload.envelope.report_json",
    "envelope_markdown": "payload.envelope.markdown",
    "reach_figure": "payload.envelope.reach_figure",
    "reach_json": "payload.envelope.report_json",
    "reach_markdown": "payload.envelope.markdown",
    "write_envelope": "payload.envelope.writer",
    "write_reach": "payload.envelope.writer",
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = sorted(_LAZY)
