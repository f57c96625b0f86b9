"""Scoring one trial: its metrics and figures, written beside its recording.

A trial folder holds ``log.mcap`` and, written by :func:`finish_trial`, ``metrics.json``,
``fig_ctb_body_frame.png`` and ``fig_route.png``; a rescoring with another contact
definition writes its own files beside those, named by :func:`contact_tag`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from payload.folders import CTB_FIGURE, METRICS, ROUTE_FIGURE, tagged
from payload.safeio import write_unless_changed

if TYPE_CHECKING:
    from payload.trials.reading import Recording


def finish_trial(
    out_dir: str | Path,
    recording_path: str | Path,
    modules: Sequence[Any] | None = None,
    *,
    destination: str = "node2",
    min_interval_s: float | None = None,
    max_gap_s: float | None = None,
    beside: bool = False,
    force: bool = False,
    recording: Recording | None = None,
) -> dict[str, Any]:
    """Score a finished (or cut-short) recording and write the trial's files.

    Writes ``metrics.json``, ``fig_ctb_body_frame.png`` and ``fig_route.png`` into
    ``out_dir``. The runner calls this after its loop ends. A rescoring (``beside``)
    writes them beside the originals, named by the contact definition
    (``metrics.contact-min0.5s-gap0.1s.json``, ...), never over them; one with the
    definition the trial was recorded with that gives every figure of its ``metrics.json``
    again writes nothing (the result says ``RESCORING: AS_RECORDED``), unless an earlier
    rescoring's copy is there to follow it. A file that exists
    with other content is replaced only with ``force`` (through a temporary file and a
    rename); an identical one is left alone.

    Args:
        out_dir: The trial folder.
        recording_path: Its ``log.mcap``.
        modules: Module outlines for the route plot (see
            :func:`~payload.trials.figures.plot_route`); defaults to the recording's
            ``modules`` metadata if present.
        destination: Destination module for the success criterion.
        min_interval_s: Contact-interval relaxation (see
            :func:`~payload.trials.metrics.compute_metrics`); 0 = the paper's definition.
        max_gap_s: Contact-interval relaxation; 0 = the paper's definition.
        beside: Name the files by the contact definition (a rescoring).
        force: Replace files that exist with other content.
        recording: The :class:`~payload.trials.reading.Recording` the file reads back as,
            when the caller has it (the trial runner: its recorder's
            :meth:`~payload.trials.recorder.TrialRecorder.recording`); default: read the
            file.

    Returns:
        The metrics dict written to ``metrics.json`` (fields of
        :class:`~payload.trials.metrics.TrialMetrics` plus ``seed``, ``criterion``,
        ``recording``, ``literal``: the same figures under the paper-literal contact
        definition, and the trial's set-up: ``ctb``, ``propulsion``, ``ctb_offset_m``...).
    """
    from payload.trials.figures import plot_ctb_body_frame, plot_route
    from payload.trials.metrics import compute_metrics, recorded_definition
    from payload.trials.recorder import read_recording

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = recording if recording is not None else read_recording(recording_path)
    # the contact definition the trial was recorded with, unless the caller overrides it
    recorded = recorded_definition(rec)
    if min_interval_s is None:
        min_interval_s = recorded[0]
    if max_gap_s is None:
        max_gap_s = recorded[1]
    metrics = compute_metrics(
        rec, destination=destination, min_interval_s=min_interval_s, max_gap_s=max_gap_s
    )
    result = {"seed": rec.meta.get("seed"), **metrics.as_dict()}
    # the paper-literal definition (any single opposing-contact sample) beside it
    literal = (
        compute_metrics(rec, destination=destination) if (min_interval_s or max_gap_s) else metrics
    )
    result["literal"] = {k: v for k, v in literal.as_dict().items() if k != "criterion"}
    result.update(_trial_setup(rec.meta))
    if "ended_by" in rec.meta:  # what ended the session ("max_time": the cap, before the end)
        result["ended_by"] = rec.meta["ended_by"]
    rec_path = Path(recording_path)
    result["recording"] = (
        rec_path.name if rec_path.resolve().parent == out.resolve() else str(rec_path)
    )
    tag = contact_tag(min_interval_s, max_gap_s) if beside else None
    if (
        beside
        and (min_interval_s, max_gap_s) == recorded
        and says(out / METRICS, result)
        and not (out / tagged(METRICS, tag)).exists()  # an earlier copy follows its source
    ):  # the trial's own scoring again (its definition, the same figures): nothing new
        return {**result, RESCORING: AS_RECORDED}
    changed = write_unless_changed(
        out / tagged(METRICS, tag), json.dumps(result, indent=2) + "\n", force=force
    )
    figures = [out / tagged(CTB_FIGURE, tag), out / tagged(ROUTE_FIGURE, tag)]
    drawn = changed or not all(f.exists() for f in figures)
    if drawn:
        plot_ctb_body_frame(rec, figures[0], metrics)
        plot_route(rec, figures[1], modules if modules is not None else rec.meta.get("modules"))
    if beside:  # what the rescoring did with its files
        return {**result, RESCORING: WRITTEN if drawn else UNCHANGED}
    return result


RESCORING = "rescoring"
"""A rescored trial's key (not written to any file) for how it came out:
:data:`AS_RECORDED`, :data:`WRITTEN` or :data:`UNCHANGED`."""
AS_RECORDED = "as recorded"
"""A rescoring with the trial's recorded definition that gave its ``metrics.json`` again."""
WRITTEN = "written"
"""A rescoring whose files were written (new, or replacing others)."""
UNCHANGED = "unchanged"
"""A rescoring whose files were there already, as it would write them."""


def says(path: Path, result: dict[str, Any]) -> bool:
    """Whether the metrics file ``path`` holds every field of ``result`` with the same value
    (compared as JSON writes them, so a value not a number equals itself); False when the
    file is missing or not a JSON object."""
    try:
        held = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(held, dict):
        return False
    return all(k in held and same_value(held[k], v) for k, v in result.items())


def same_value(a: Any, b: Any) -> bool:
    """Two metric values alike as written (so -0.0 differs from 0.0, and a value not a
    number equals itself)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _trial_setup(meta: dict[str, Any]) -> dict[str, Any]:
    """What the recording says about how the trial was set up (CTB model, propulsion,
    acquisition offset), for ``metrics.json``; keys absent from older recordings are left
    out."""
    keys = (
        "retarget_budget",
        "retarget_collisions",
        "controller",
        "controller_overrides",
        "ctb",
        "propulsion",
        "physics_dt",
        "ctb_offset_m",
        "ctb_yaw_deg",
        "ctb_external_max",
        "equality_constraints",
        "acquisition_state",
        "base_filter",
        "link_delay",
        "zones",
        "zones_file",
        "station_contacts",
        "min_station_clearance_mm",
        "filter_active_s",
        "station_clearance_cap_mm",
    )
    return {k: meta[k] for k in keys if k in meta}


CONTACT_TAG = "contact-"
"""How the file-name tag of a contact definition begins (:func:`contact_tag`)."""

MIXED_TAG = f"{CONTACT_TAG}mixed"
"""The tag of a campaign rescored with trials of more than one contact definition."""
UNSCORED_TAG = f"{CONTACT_TAG}unscored"
"""The tag of a campaign rescored with no trial scored (each raised or was cut short)."""


def contact_tag(min_interval_s: float, max_gap_s: float) -> str:
    """A file-name tag for a contact definition, e.g. ``contact-min0.5s-gap0.1s``."""
    return f"{CONTACT_TAG}min{float(min_interval_s):g}s-gap{float(max_gap_s):g}s"


def rescorings(folder: Path, names: Sequence[str]) -> list[Path]:
    """The files rescorings wrote in ``folder`` beside the files ``names``, tagged with a
    contact definition (``metrics.contact-min0s-gap0.1s.json``) or a campaign's mixed ones
    (``summary.contact-mixed.md``); other files, a user's ``metrics.contact-notes.json``
    say, are not theirs."""
    found: list[Path] = []
    for name in names:
        stem, dot, suffix = name.rpartition(".")
        for tag in (f"{CONTACT_TAG}min*s-gap*s", MIXED_TAG):
            found += sorted(folder.glob(f"{stem}.{tag}{dot}{suffix}"))
    return found


def write_metrics(out: str | Path, result: dict[str, Any]) -> Path:
    """A run's ``metrics.json`` in ``out`` (its final form, after the runner's additions),
    replaced through a temporary file and a rename, never written in place."""
    from payload.safeio import replace_file

    path = Path(out) / METRICS
    replace_file(path, json.dumps(result, indent=2) + "\n")
    return path


__all__ = [
    "AS_RECORDED",
    "CONTACT_TAG",
    "MIXED_TAG",
    "RESCORING",
    "UNCHANGED",
    "WRITTEN",
    "contact_tag",
    "finish_trial",
    "rescorings",
    "same_value",
    "says",
    "write_metrics",
]
