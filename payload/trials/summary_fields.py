"""What a campaign's summary is made of: the per-trial figures it summarises (in the
paper's order, with their labels), the paper's own results beside them, and the error of
a campaign that cannot run or be summarised.

The summary itself: :mod:`payload.trials.summary`; its Markdown:
:mod:`payload.trials.summary_markdown`; the trial folders it is made from:
:mod:`payload.trials.trial_results`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from payload.errors import PayloadError
from payload.schema import CAP_STOPPED
from payload.sim.zone_form import box_counts
from payload.trials.definition import CONFIRMED_WORDS, MIXED_WORDS, ContactWords, contact_words

METRIC_KEYS: tuple[str, ...] = (
    "duration_s",
    "net_displacement_m",
    "rms_mm",
    "peak_mm",
    "contact_s",
)
"""The per-trial figures the paper summarises, in its order."""


def contact_label(interval: str) -> str:
    """The first contact interval's label, its interval named ``interval``."""
    return f"First {interval} [s]"


METRIC_LABELS: dict[str, str] = {
    "duration_s": "Teleoperation duration after calibration [s]",
    "net_displacement_m": "CTB net world-frame displacement [m]",
    "rms_mm": "RMS deviation in the body frame, eq. 5 [mm]",
    "peak_mm": "Peak deviation in the body frame [mm]",
    "contact_s": contact_label(CONFIRMED_WORDS.interval),
}

PAPER_RESULTS: dict[str, Any] = {
    "n": 10,
    "success": 10,
    "duration_s": {"median": 77.5, "min": 67.3, "max": 97.5},
    "net_displacement_m": {"median": 9.30, "min": 7.87, "max": 9.46},
    "rms_mm": {"median": 35.6, "min": 16.4, "max": 79.0},
    "peak_mm": {"median": 67.7, "min": 26.8, "max": 176.6},
    "contact_s": {"median": 75.1, "min": 65.7, "max": 94.5},
}
"""The paper's ten-trial results (Sec. IV; docs/sources.md), for comparison."""


NO_CONTACT = CONFIRMED_WORDS.none
"""Said beside a first contact interval where a trial has none: its ``contact_s`` is the
metric's 0 by definition, not a contact that lasted 0 s (its RMS and peak are n/a)."""


def definition_words(definition: Mapping[str, Any] | None) -> ContactWords:
    """How a summary names the contact its trials were scored with, from its
    ``contact_definition``: :data:`CONFIRMED_WORDS` for the confirmed definition (and for
    a summary that has none: no trial was scored), :data:`MIXED_WORDS` for trials scored
    with different ones, any other by its numbers (a rescoring's, or trials recorded
    under another)."""
    d = definition or {}
    lo, gap = d.get("min_interval_s"), d.get("max_gap_s")
    if "mixed" not in d and lo is None and gap is None:
        return CONFIRMED_WORDS
    if "mixed" in d or lo is None or gap is None:
        return MIXED_WORDS
    return contact_words(float(lo), float(gap))


def metric_labels(definition: Mapping[str, Any] | None) -> dict[str, str]:
    """:data:`METRIC_LABELS` of a summary whose trials were scored with ``definition``
    (its ``contact_definition``): the first contact interval named after it."""
    interval = definition_words(definition).interval
    return {**METRIC_LABELS, "contact_s": contact_label(interval)}


def no_contact_interval(summary: Mapping[str, Any]) -> bool:
    """Whether no scored trial of a summary (or of its ``literal`` part) has a first
    contact interval: its first contact interval is then n/a in the summary's table and
    figure, as the RMS is (each trial's 0 s is the metric's value for none, which
    ``summary.json`` keeps); a summary with no scored trial is not said to be without
    contact."""
    scored = [t for t in summary.get("trials", []) if not t.get("error")]
    return bool(scored) and all(without_contact(t) for t in scored)


def without_contact(row: Mapping[str, Any]) -> bool:
    """Whether a scored trial has no first contact interval: ``n_contact_samples`` 0 in
    a trial's metrics; in a summary's row of it (which leaves the count out), ``acquired``
    false and no RMS (a trial that has an interval has its RMS). A trial that raised is
    not scored, so not said to be without contact."""
    if row.get("error"):
        return False
    if "n_contact_samples" in row:
        return row["n_contact_samples"] == 0
    rms = row.get("rms_mm")
    return row.get("acquired") is False and (rms is None or not math.isfinite(rms))


def statistic_rows(rows: Sequence[Mapping[str, Any]], key: str) -> list[Mapping[str, Any]]:
    """The trials a metric's median and range are taken over: those scored, and for the
    first contact interval (``contact_s``) those that have one (another's 0 s is the
    metric's value for none; it has no interval to time, as it has no RMS)."""
    scored = [r for r in rows if not r.get("error")]
    return [r for r in scored if not without_contact(r)] if key == "contact_s" else scored


class CampaignError(PayloadError):
    """A campaign cannot run or be summarised (bad arguments, no trials, no scheduler)."""


def least_clearance_text(mm: Any, cap_mm: Any, *, always_cap: bool = False) -> str:
    """The least station clearance as said to a reader: ``"5.8 mm"``, or, at the cap the
    monitor measures up to (``station_clearance_cap_mm``), ``"over 300 mm (measured up to
    300 mm)"``: the cap is not a distance that was seen. ``always_cap``: name the cap
    below it too. Without a cap (older trials) the figure alone."""
    if mm is None:
        return "n/a"
    if not isinstance(cap_mm, (int, float)):
        return f"{mm} mm"
    if mm >= cap_mm:
        return f"over {cap_mm:g} mm (measured up to {cap_mm:g} mm)"
    return f"{mm} mm (measured up to {cap_mm:g} mm)" if always_cap else f"{mm} mm"


STATION_ZONES = "the station's"
"""What :func:`zones_name` calls the station's own zones (a trial run without ``--zones``)."""

CAPPED = "capped"
"""A per-trial row's note beside its success when the ``--max-time`` cap ended its session
before the operator finished (``ended_by`` ``"max_time"``: success is still scored on what
was recorded)."""


def zones_name(result: Mapping[str, Any]) -> str | None:
    """Which zones a trial's base filter ran: ``"the station's"``, or the zones file's name
    (``"recorded"`` for zones without one) with its keep-in and keep-out box counts;
    ``None`` with the filter off or for a trial recorded before the zones were."""
    if not result.get("base_filter") or "zones" not in result:
        return None
    zones = result["zones"]
    if zones is None:
        return STATION_ZONES
    keep_in, keep_out = box_counts(zones)
    named = result.get("zones_file") or "recorded"
    return f"{named} ({keep_in} keep-in, {keep_out} keep-out boxes)"


__all__ = [
    "CAPPED",
    "CAP_STOPPED",
    "CONFIRMED_WORDS",
    "METRIC_KEYS",
    "METRIC_LABELS",
    "MIXED_WORDS",
    "NO_CONTACT",
    "PAPER_RESULTS",
    "STATION_ZONES",
    "CampaignError",
    "ContactWords",
    "definition_words",
    "least_clearance_text",
    "metric_labels",
    "no_contact_interval",
    "statistic_rows",
    "without_contact",
    "zones_name",
]
