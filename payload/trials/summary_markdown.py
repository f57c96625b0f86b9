"""A campaign's summary as Markdown (``summary.md``): the paper's results paragraph as
tables, this campaign under both contact definitions next to the paper, the set-up, how
it ran, then one row per trial (the summary itself: :func:`payload.trials.summary.summarize`).
"""

from __future__ import annotations

import math
from typing import Any

from payload.schema import ENDED_BY_CAP
from payload.trials.summary_fields import (
    CAP_STOPPED,
    CAPPED,
    CONFIRMED_WORDS,
    METRIC_KEYS,
    PAPER_RESULTS,
    definition_words,
    least_clearance_text,
    metric_labels,
    no_contact_interval,
    without_contact,
)


def _delay_text(delay: Any) -> str:
    """The campaign's link delay, or that its trials differ in it."""
    if not delay:
        return ""
    if isinstance(delay, dict):  # {"mixed": [...]}: "None" for the trials without one
        said = ", ".join("none" if v == "None" else f"{v} s" for v in delay.get("mixed", []))
        return f"; link delay (delay, jitter) differs between the trials: {said}"
    return f"; link delay (delay, jitter) {delay} s"


def _station_lines(station: dict[str, Any] | None) -> list[str]:
    if not station or not station.get("measured"):
        return []
    active = station.get("filter_active_s") or {}
    delay = station.get("link_delay")
    mm = station.get("min_station_clearance_mm")
    on = {"True": "on", "False": "off"}.get(str(station.get("base_filter")), "mixed")
    zones = station.get("zones")
    if isinstance(zones, dict):
        on += f" (zones differ between the trials: {'; '.join(zones.get('mixed', []))})"
    elif zones:
        on += f" (zones: {zones})"
    return [
        "",
        f"Station contacts: {station['trials_with_contacts']} of {station['measured']} "
        f"trials touched the station ({station['station_contacts']['total']} control steps "
        f"in all); least clearance "
        f"{least_clearance_text(mm, station.get('station_clearance_cap_mm'), always_cap=True)}"
        f"; base filter {on}, active "
        f"{active.get('median', 0.0):.1f} s median per trial"
        f"{_delay_text(delay)}.",
    ]


def _fmt(stat: dict[str, Any] | None, digits: int) -> str:
    if not stat or stat.get("median") is None:
        return "n/a"
    return f"{stat['median']:.{digits}f} ({stat['min']:.{digits}f} to {stat['max']:.{digits}f})"


def _cell(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{float(value):.{digits}f}"


_DIGITS = {"duration_s": 1, "net_displacement_m": 2, "rms_mm": 1, "peak_mm": 1, "contact_s": 1}


LITERAL_NONE = "no paper-literal contact"
"""Said of a summary's paper-literal column where no trial has a contact interval."""


def _stat_text(summary: dict[str, Any], key: str, none: str = CONFIRMED_WORDS.none) -> str:
    """A metric's median and range in a summary (or its ``literal`` part); the first
    contact interval n/a, as the RMS is, when no scored trial has one
    (:func:`~payload.trials.summary_fields.no_contact_interval`), said as ``none``."""
    if key == "contact_s" and no_contact_interval(summary):
        return f"n/a ({none})"
    return _fmt(summary.get(key), _DIGITS[key])


def count_note(summary: dict[str, Any], key: str) -> str:
    """`` [2 of 10 trials]`` after a metric's median and range when they are over fewer
    than all of a summary's trials (those with a value: an RMS, a contact interval)."""
    n, stat = summary.get("n", 0), summary.get(key)
    count = stat.get("count", n) if stat else 0
    return "" if count == n else f" [{count} of {n} trials]"


def _trial_cell(row: dict[str, Any], key: str) -> str:
    """A metric of one trial in the per-trial table (its contact interval n/a when it has
    none, as its RMS is)."""
    if key == "contact_s" and without_contact(row):
        return "n/a"
    return _cell(row.get(key), _DIGITS[key])


def _definition_text(definition: dict[str, Any] | None) -> str:
    if definition is None:  # no trial was scored (each raised or left no finished recording)
        return "none (no trial was scored)"
    d = definition
    if "mixed" in d:
        return "mixed definitions across the trials"
    mi, mg = float(d.get("min_interval_s") or 0.0), float(d.get("max_gap_s") or 0.0)
    if not (mi or mg):
        return "the paper's: any single sample with opposing contact counts, no bridging"
    return (
        f"debounced: indicator dropouts up to {mg:.2f} s bridged, then runs shorter than "
        f"{mi:.2f} s skipped (NOT the paper's definition)"
    )


def _header_lines(summary: dict[str, Any], title: str | None) -> list[str]:
    seeds = [s for s in summary.get("seeds", []) if s is not None]
    setup = []
    for key, label in (("ctb", "CTB model"), ("propulsion", "propulsion model")):
        value = summary.get(key)
        if value is not None:
            shown = ", ".join(value["mixed"]) if isinstance(value, dict) else str(value)
            setup.append(f"{label} `{shown}`")
    dt = summary.get("physics_dt")
    if dt is not None:
        values = dt["mixed"] if isinstance(dt, dict) else [dt]
        shown = ", ".join(f"{1e3 * v:g} ms" for v in values)
        setup.append(f"physics step `{shown}`")
    return [
        f"# {title or 'Cargo-transport campaign'}",
        "",
        f"{summary['n']} trials"
        + (f", seeds {min(seeds)} to {max(seeds)}" if seeds else "")
        + (f"; {', '.join(setup)}" if setup else "")
        + ". Medians with ranges (min to max); the paper's figures are from its Results "
        "section (ten live teleoperated trials).",
        "",
    ]


def summary_markdown(summary: dict[str, Any], title: str | None = None) -> str:
    """The paper's results paragraph as Markdown tables: this campaign under the recorded
    (confirmed) and the paper-literal contact definitions next to the paper, then one row
    per trial."""
    paper = summary.get("paper", PAPER_RESULTS)
    lit = summary.get("literal") or {}
    n = summary["n"]

    def acq(s: dict[str, Any]) -> str:
        v = s.get("acquisition_success")
        return "n/a" if v is None else f"{100 * v:.0f} %"

    # the debounced definition is "confirmed contact"; any other (a rescoring, or trials
    # recorded under another) is named by its numbers, in every place the summary names it
    words = definition_words(summary.get("contact_definition"))
    confirmed = words == CONFIRMED_WORDS
    labels = metric_labels(summary.get("contact_definition"))
    lines = [
        *_header_lines(summary, title),
        f"| metric | this campaign, {words.contact} | this campaign, paper-literal contact "
        "| paper |",
        "| --- | --- | --- | --- |",
        f"| task success | {summary['success']}/{n} | {lit.get('success', 'n/a')}/{n} "
        f"| {paper['success']}/{paper['n']} |",
        f"| acquisition success | {acq(summary)} | {acq(lit)} | n/a |",
    ]
    for key in METRIC_KEYS:
        cells = []
        for s, none in ((summary, words.none), (lit, LITERAL_NONE)):
            cells.append(f"{_stat_text(s, key, none)}{count_note(s, key)}")
        paper_cell = _fmt(paper[key], _DIGITS[key])
        lines.append(f"| {labels[key]} | {cells[0]} | {cells[1]} | {paper_cell} |")
    if summary.get("errors"):
        lines += [
            "",
            f"{summary['errors']} trial(s) raised an error or left no finished recording "
            "(counted as failures):",
            "",
            *(f"- seed {t['seed']}: {t['error']}" for t in summary["trials"] if t.get("error")),
        ]
    lines += [
        "",
        (
            "Contact definitions. Confirmed contact (the recorded one): "
            if confirmed
            else "Contact definitions. This campaign's contact: "
        )
        + _definition_text(summary.get("contact_definition"))
        + ". Paper-literal: "
        + _definition_text((lit.get("contact_definition") if lit else None) or {})
        + ". Acquisition succeeds when a first contact interval exists under the definition.",
    ]
    prof = summary.get("controller")
    if prof:
        shown = prof if isinstance(prof, str) else ", ".join(prof)
        over = summary.get("controller_overrides") or []
        flat = sorted({x for o in over for x in (o if isinstance(o, list) else [o])})
        lines += [
            "",
            f"Controller profile: {shown} ('paper': the paper's controller; 'safe': the "
            "contact-aware self-collision model and the base safety filter)"
            + (f", overridden: {', '.join(flat)}." if flat else "."),
        ]
    budget = summary.get("retarget_budget")
    if budget:
        shown = budget if isinstance(budget, str) else ", ".join(budget)
        lines += [
            "",
            f"Retargeting budget: {shown} ('paper': at most 20 residual evaluations per pair "
            "solve, the paper's controller; 'converged': each start run to convergence).",
        ]
    modelled = summary.get("retarget_collisions")
    if modelled is not None:
        shown = ("yes" if modelled else "no") if isinstance(modelled, bool) else "mixed"
        lines += [
            "",
            f"Self-collision modelled in the pair solves: {shown} (the paper's controller "
            "does not; with it, no command comes closer than the design's margin).",
        ]
    lines += _station_lines(summary.get("station"))
    lines += _run_lines(summary.get("run"))
    lines += _capped_lines(int(summary.get("capped") or 0))
    lines += [
        "",
        "Success: the CTB is in the destination module at the end, and the first continuous "
        f"{words.interval} carries it there and holds it until arrival (the later "
        "of its entry and the start of the operator's arrival phase; without that phase, "
        "the end of the recording). RMS and peak deviation: eq. 5 "
        "over that interval, from the CTB position in the Astrobee body frame (eq. 4) at "
        "its first sample.",
        "",
        "## Trials",
        "",
        f"Per trial, {words.contact}, then the paper-literal success, RMS and contact interval.",
        "",
        "| seed | success | duration [s] | net displacement [m] | RMS [mm] | peak [mm] "
        "| contact [s] | CTB ends in | literal success | literal RMS [mm] | literal contact [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    literal_rows = {r.get("seed"): r for r in lit.get("trials", [])}
    for row in summary.get("trials", []):
        ok = "error" if row.get("error") else ("yes" if row["success"] else "no")
        if row.get("ended_by") == ENDED_BY_CAP:
            ok += f" ({CAPPED})"
        cells = " | ".join(_trial_cell(row, k) for k in METRIC_KEYS)
        lr = literal_rows.get(row["seed"], {})
        lok = "error" if row.get("error") else ("yes" if lr.get("success") else "no")
        lines.append(
            f"| {row['seed']} | {ok} | {cells} | {row.get('final_module') or 'n/a'} | {lok} "
            f"| {_trial_cell(lr, 'rms_mm')} | {_trial_cell(lr, 'contact_s')} |"
        )
    return "\n".join(lines) + "\n"


def _capped_lines(n_capped: int) -> list[str]:
    """How many trials the ``--max-time`` cap stopped (none: no line)."""
    if not n_capped:
        return []
    return [
        "",
        f"{n_capped} of the trials {'was' if n_capped == 1 else 'were'} {CAP_STOPPED} "
        f'before the operator finished ("{CAPPED}" in the table below); success is scored '
        "on what was recorded.",
    ]


def _run_lines(run: dict[str, Any] | None) -> list[str]:
    if not run or not run.get("wall_s"):
        return []
    if run.get("scheduler"):
        where = f"on the Dask scheduler {run['scheduler']}"
    elif (run.get("workers") or 0) > 1:
        where = f"on {run['workers']} local Dask workers"
    else:
        where = "serially"
    cap = run.get("max_time_s")
    capped = (
        []
        if cap is None
        else [
            f"Each trial's session was capped at {cap:g} s (--max-time): a trial stopped by "
            "the cap ended before its task did."
        ]
    )

    return [
        "",
        f"Ran {where} in {run['wall_s']:.1f} s; the trials took "
        f"{run.get('trial_wall_s', 0.0):.1f} s added up "
        f"(speed-up {run.get('trial_wall_s', 0.0) / run['wall_s']:.2f}x).",
        *capped,
    ]


__all__ = ["summary_markdown"]
