"""Envelope and reach reports: Markdown, PNG figures (matplotlib) and JSON in ``analyses/``.

The pieces, one job each: :mod:`~payload.envelope.report_json` (the data),
:mod:`~payload.envelope.markdown`, :mod:`~payload.envelope.envelope_figure` and
:mod:`~payload.envelope.reach_figure` (with :mod:`~payload.envelope.drawing`), and
:mod:`~payload.envelope.writer` (the files, written only when a figure changed).
"""

from payload.envelope.drawing import FINGER_COLOURS, STRUCTURE_COLOUR
from payload.envelope.envelope_figure import envelope_figure
from payload.envelope.markdown import envelope_markdown, reach_markdown
from payload.envelope.reach_figure import reach_figure
from payload.envelope.report_json import envelope_json, reach_json
from payload.envelope.writer import write_envelope, write_reach

__all__ = [
    "FINGER_COLOURS",
    "STRUCTURE_COLOUR",
    "envelope_figure",
    "envelope_json",
    "envelope_markdown",
    "reach_figure",
    "reach_json",
    "reach_markdown",
    "write_envelope",
    "write_reach",
]
