"""A campaign's results: the paper-style summary of its trials (:func:`summarize`) and
its files (:func:`write_summary`: ``summary.json``, ``summary.md`` and the figure).

What the summary is made of: :mod:`payload.trials.summary_fields`; its Markdown:
:mod:`payload.trials.summary_markdown`; the trial folders read for it:
:mod:`payload.trials.trial_results`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from payload.folders import SUMMARY, SUMMARY_TEXT, tagged
from payload.safeio import OverwriteError, write_unless_changed
from payload.schema import CONTROL_DT, ENDED_BY_CAP
from payload.trials.summary_fields import (
    CAP_STOPPED,
    METRIC_KEYS,
    METRIC_LABELS,
    NO_CONTACT,
    PAPER_RESULTS,
    STATION_ZONES,
    CampaignError,
    least_clearance_text,
    metric_labels,
    statistic_rows,
    without_contact,
    zones_name,
)
from payload.trials.summary_markdown import summary_markdown
from payload.trials.trial_results import load_trial_results


def _finite(values: list[Any]) -> list[float]:
    out = []
    for v in values:
        if v is None:
            continue
        f = float(v)
        if math.isfinite(f):
            out.append(f)
    return out


def _literal_row(r: dict[str, Any]) -> dict[str, Any]:
    """A trial's figures under the paper-literal contact definition."""
    lit = r.get("literal")
    base = {"seed": r.get("seed"), "error": r.get("error"), "wall_s": r.get("wall_s")}
    if isinstance(lit, dict):
        return {**lit, **base}
    if not (r.get("min_interval_s") or r.get("max_gap_s")):
        return dict(r)  # scored with the paper's definition already
    return {**base, "final_module": r.get("final_module")}


def _one_value(rows: Sequence[dict[str, Any]], key: str, none_is_a_value: bool = False) -> Any:
    """The value every trial records under ``key``; ``{"mixed": [...]}`` if they differ,
    ``None`` if none records it. ``none_is_a_value``: a recorded null is a setting (no link
    delay), so trials with and without one are mixed."""
    if none_is_a_value:  # each scored trial that records the key, its null too
        values = sorted({str(r[key]) for r in rows if key in r and not r.get("error")})
    else:
        values = sorted({str(r[key]) for r in rows if r.get(key) is not None})
    if values in ([], ["None"]):
        return None
    return values[0] if len(values) == 1 else {"mixed": values}


def _summary_core(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok_rows = [r for r in rows if not r.get("error")]
    summary: dict[str, Any] = {
        "n": len(rows),
        "success": sum(1 for r in ok_rows if r.get("success")),
        "errors": len(rows) - len(ok_rows),
        "acquisition_success": sum(1 for r in ok_rows if r.get("acquired")) / len(rows),
    }
    for key in METRIC_KEYS:
        vals = _finite([r.get(key) for r in statistic_rows(ok_rows, key)])
        if vals:
            arr = np.asarray(vals)
            summary[key] = {
                "median": float(np.median(arr)),
                "min": float(arr.min()),
                "max": float(arr.max()),
                "count": len(vals),
            }
        else:
            summary[key] = {"median": None, "min": None, "max": None, "count": 0}
    definitions = {
        (float(r.get("min_interval_s") or 0.0), float(r.get("max_gap_s") or 0.0)) for r in ok_rows
    }
    if len(definitions) == 1:
        (mi, mg) = definitions.pop()
        summary["contact_definition"] = {"min_interval_s": mi, "max_gap_s": mg}
    elif definitions:
        summary["contact_definition"] = {"mixed": sorted(definitions)}
    summary["seeds"] = [r.get("seed") for r in rows]
    summary["trials"] = [
        {
            "seed": r.get("seed"),
            "success": bool(r.get("success")) and not r.get("error"),
            "acquired": bool(r.get("acquired")) and not r.get("error"),
            **{k: r.get(k) for k in METRIC_KEYS},
            "final_module": r.get("final_module"),
            **{k: r.get(k) for k in STATION_KEYS if k in r},
            # a trial the cap stopped says so (the others' ends are their tasks')
            **({"ended_by": ENDED_BY_CAP} if r.get("ended_by") == ENDED_BY_CAP else {}),
            "error": r.get("error"),
            **({"traceback": r["traceback"]} if r.get("traceback") else {}),
            "wall_s": r.get("wall_s"),
        }
        for r in rows
    ]
    summary["paper"] = PAPER_RESULTS
    return summary


def summarize(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The campaign summary (what ``summary.json`` holds).

    Every trial counts in ``n``; ``success`` counts trials that succeeded (a trial that
    raised is a failure); ``acquisition_success`` is the fraction of trials whose pinch
    closed on the handle (a first confirmed-contact interval exists). Each metric's
    ``median``, ``min`` and ``max`` are over the trials that have a finite value
    (``count`` of them; ``None`` if none has); the first contact interval's over the trials
    that have one (each other trial's ``contact_s`` is the metric's 0 for none, not an
    interval that lasted 0 s: left out, as its RMS is). ``literal`` holds the same fields under the
    paper-literal contact definition (any single opposing-contact sample, no bridging);
    the top level uses the definition the trials were recorded with (``contact_definition``).
    ``ctb`` and ``propulsion`` name the CTB model and the propulsion model of the trials,
    ``physics_dt`` their physics step [s] (``{"mixed": [...]}`` if they differ; ``None``
    when no trial records it: those before the option, all at 1 ms).

    Args:
        results: Per-trial dicts (from :func:`run_campaign` or :func:`load_trial_results`).

    Returns:
        ``{"n", "success", "errors", "acquisition_success", <metric>: {"median", "min",
        "max", "count"}, "contact_definition", "seeds", "trials", "paper", "ctb",
        "propulsion", "physics_dt", "capped", "literal", "station"}``; ``capped`` counts
        the trials the ``--max-time`` cap stopped before their operator finished (each
        one's row says ``"ended_by": "max_time"``).
    """
    if not results:
        raise CampaignError("no trial results to summarise")
    rows = sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))
    summary = _summary_core(rows)
    summary["ctb"] = _one_value(rows, "ctb")
    summary["propulsion"] = _one_value(rows, "propulsion")
    steps = sorted({float(r["physics_dt"]) for r in rows if r.get("physics_dt") is not None})
    summary["physics_dt"] = (steps[0] if len(steps) == 1 else {"mixed": steps}) if steps else None
    summary["capped"] = sum(1 for r in rows if r.get("ended_by") == ENDED_BY_CAP)
    summary["literal"] = _summary_core([_literal_row(r) for r in rows])
    summary["station"] = station_summary(rows)
    return summary


STATION_KEYS = (
    "station_contacts",
    "min_station_clearance_mm",
    "filter_active_s",
    "station_clearance_cap_mm",
)
"""The per-trial station figures (:mod:`payload.trials.safety`)."""


def station_summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Station contacts over the trials that measured them: how many trials touched the
    station, the contact steps in all and at most, the least clearance [mm], the filter's
    active time [s] (median, max), and the base-filter, link-delay and zones settings
    (``zones``: :func:`~payload.trials.summary_fields.zones_name` of the filtered trials,
    ``{"mixed": [...]}`` if they differ, absent when none records them)."""
    ok = [r for r in rows if not r.get("error") and r.get("station_contacts") is not None]
    out: dict[str, Any] = {
        "measured": len(ok),
        "base_filter": _one_value(rows, "base_filter"),
        "link_delay": _one_value(rows, "link_delay", none_is_a_value=True),
    }
    zones = sorted({name for r in rows if not r.get("error") and (name := zones_name(r))})
    if zones:  # trials recorded before the zones were, or with the filter off, say none
        out["zones"] = zones[0] if len(zones) == 1 else {"mixed": zones}
    caps = {r["station_clearance_cap_mm"] for r in ok if r.get("station_clearance_cap_mm")}
    if len(caps) == 1:  # older trials do not say
        out["station_clearance_cap_mm"] = caps.pop()
    if not ok:
        return out
    contacts = [int(r["station_contacts"]) for r in ok]
    clearance = _finite([r.get("min_station_clearance_mm") for r in ok])
    active = _finite([r.get("filter_active_s") for r in ok])
    out.update(
        trials_with_contacts=sum(1 for c in contacts if c > 0),
        station_contacts={"total": sum(contacts), "max": max(contacts)},
        min_station_clearance_mm=min(clearance) if clearance else None,
        filter_active_s={"median": float(np.median(active)), "max": max(active)}
        if active
        else None,
    )
    return out


def trials_environment(results: list[dict[str, Any]]) -> dict[str, Any] | list | None:
    """What a campaign's trials ran on, from their own provenance (``environment``: the
    versions and BLAS kernels of the process that ran each, on whichever machine): the one
    environment when they agree, every distinct one (in the trials' order) when they do
    not, None when no trial reported one (every trial failed before scoring)."""
    seen: list[dict[str, Any]] = []
    for r in results:
        env = (r.get("provenance") or {}).get("environment")
        if env is not None and env not in seen:
            seen.append(env)
    return seen[0] if len(seen) == 1 else (seen or None)


def campaign_title(n: int, setup: dict[str, Any]) -> str:
    """A campaign summary's title: how many trials and the setup they ran (``setup``: the
    :data:`~payload.trials.setup_options.RUN_SETTINGS`; a setting None is not known and
    left out)."""
    from payload.schema import PHYSICS_DT

    parts = [f"{n} trials"]
    if setup.get("ctb") is not None:
        parts.append(f"CTB {setup['ctb']}")
    if setup.get("propulsion") is not None:
        parts.append(str(setup["propulsion"]))
    if setup.get("controller") is not None:
        parts.append(f"controller {setup['controller']}")
    if setup.get("retarget_budget") is not None:
        parts.append(f"retargeting budget {setup['retarget_budget']}")
    if setup.get("retarget_collisions"):
        parts.append("self-collision modelled")
    if setup.get("base_filter"):
        parts.append("base filter")
    delay = setup.get("link_delay")
    if isinstance(delay, (list, tuple)):  # as a trial records it: [delay, jitter] [s]
        delay = f"{delay[0]}" + (f":{delay[1]}" if delay[1] else "") if delay[0] else None
    if delay:  # as --link-delay gives it, S[:JITTER]
        parts.append(f"link delay {delay} s")
    dt = setup.get("physics_dt")
    if dt is not None and dt != PHYSICS_DT:
        parts.append(f"physics step {1e3 * dt:g} ms")
    return f"Cargo-transport campaign ({', '.join(parts)})"


def campaign_summary(
    results: Sequence[dict[str, Any]],
    title: str | None = None,
    run: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The summary :func:`write_summary` writes (its arguments of the same names), made and
    not written."""
    summary = summarize(results)
    if title is not None:
        summary["title"] = title
    budgets = sorted({str(r["retarget_budget"]) for r in results if r.get("retarget_budget")})
    if budgets:
        summary["retarget_budget"] = budgets[0] if len(budgets) == 1 else budgets
    # the controller profile and the settings the trials' flags override (one value when
    # every trial says the same, else the values seen)
    profiles = sorted({str(r["controller"]) for r in results if r.get("controller")})
    if profiles:
        summary["controller"] = profiles[0] if len(profiles) == 1 else profiles
    overrides = sorted(
        {tuple(r["controller_overrides"]) for r in results if "controller_overrides" in r}
    )
    if overrides:
        summary["controller_overrides"] = (
            list(overrides[0]) if len(overrides) == 1 else [list(o) for o in overrides]
        )
    # whether the pair solves modelled self-collision: one bool when every scored trial
    # says the same, else the values seen (None: a trial that does not say); an unscored
    # trial (aborted, killed) says nothing of it
    seen = {r.get("retarget_collisions") for r in results if not r.get("error")}
    seen = {v if isinstance(v, bool) else None for v in seen}
    if seen and seen != {None}:
        summary["retarget_collisions"] = (
            seen.pop() if len(seen) == 1 else sorted(seen, key=lambda v: (v is not None, v))
        )
    if run is not None:
        summary["run"] = run
    if provenance is not None:
        summary["provenance"] = provenance
    return summary


def write_summary(
    results: Sequence[dict[str, Any]],
    out_dir: str | Path,
    title: str | None = None,
    run: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
    *,
    tag: str | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Write ``summary.md``, ``summary.json`` and the campaign figure ``fig_campaign.png``
    (:mod:`payload.trials.campaign_figure`) into ``out_dir`` and return the summary.

    With ``tag`` (a rescoring's contact definition) the files are ``summary.<tag>.md``
    and ``summary.<tag>.json``, beside the originals. Files that exist with other content
    are replaced only with ``force``; identical ones are left alone.

    Args:
        results: Per-trial dicts.
        out_dir: The campaign folder.
        title: Heading of ``summary.md``.
        run: How the campaign ran, stored under ``run`` (e.g. ``workers``, ``scheduler``,
            ``wall_s`` of the whole campaign and ``trial_wall_s``, the sum over trials).
        provenance: What the trials ran on (:func:`payload.project.provenance`), stored
            under ``provenance``.
        tag: Name the files by this tag.
        force: Replace files that exist with other content.

    Raises:
        OverwriteError: A summary file exists with other content and ``force`` is false.
    """
    summary = campaign_summary(results, title, run, provenance)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    text = summary_markdown(summary, title)
    json_path, text_path = out / tagged(SUMMARY, tag), out / tagged(SUMMARY_TEXT, tag)
    files = {json_path: data, text_path: text}
    for path, content in files.items():  # check both before writing either
        if not force and path.exists() and path.read_bytes() != content.encode():
            raise OverwriteError(f"{path}: exists with different content (pass --force to replace)")
    changed = write_unless_changed(json_path, data, force=force)
    write_unless_changed(text_path, text, force=force)
    # the campaign figure follows the summary: drawn when the summary changed or it is missing
    # matplotlib only when a summary is written: a trial's worker never loads it
    from payload.trials.campaign_figure import campaign_figure_path, write_campaign_figure

    figure = campaign_figure_path(out, tag)
    if changed or force or not figure.exists():
        labels = metric_labels(summary.get("contact_definition"))
        write_campaign_figure(summary, labels, out, tag)
    return summary


def zones_text(result: dict[str, Any]) -> str:
    """Which zones a trial's base filter ran, as its set-up line says it (``""``: the
    filter off, or a run recorded before the zones were)."""
    name = zones_name(result)
    if name is None:
        return ""
    return f", {STATION_ZONES} zones" if name == STATION_ZONES else f", zones {name}"


def print_trial_summary(result: dict[str, Any], given: str = "") -> None:
    """Print a trial's set-up, success and metrics (``payload trial``, ``payload hw run``).

    Args:
        result: The trial's metrics (``metrics.json``).
        given: Where the set-up came from, appended to its line.
    """
    modelled = "modelled" if result.get("retarget_collisions") else "off"
    dt = result.get("physics_dt")
    physics = "" if dt is None else f"{1e3 * dt:g} ms physics step, "
    print(
        f"  setup: CTB {result.get('ctb')}, {result.get('propulsion')} propulsion, {physics}"
        f"controller {result.get('controller')}, retargeting budget "
        f"{result.get('retarget_budget')}, self-collision {modelled}{zones_text(result)}{given}"
    )
    print(f"  success: {'yes' if result.get('success') else 'no'}")
    if result.get("ended_by") == ENDED_BY_CAP:
        print(
            f"  {CAP_STOPPED} after "
            f"{result.get('steps', 0) * CONTROL_DT:.1f} s, before the operator finished"
        )
    if "station_contacts" in result:
        delay = result.get("link_delay")
        mm = result.get("min_station_clearance_mm")
        jitter = f" +-{delay[1]:g}" if delay and len(delay) > 1 and delay[1] else ""
        print(
            f"  base filter {'on' if result.get('base_filter') else 'off'}"
            f"{f', link delay {delay[0]:g}{jitter} s' if delay else ''}; "
            f"station contacts: {result.get('station_contacts')} steps, least clearance "
            f"{least_clearance_text(mm, result.get('station_clearance_cap_mm'))}, "
            f"filter active {result.get('filter_active_s')} s"
        )
    for key in METRIC_KEYS:
        value = result.get(key)
        shown = "n/a" if value is None else f"{value:.3f}"
        if key == "contact_s" and without_contact(result):
            shown += f" ({NO_CONTACT})"  # the metric's 0 when there is no interval
        print(f"  {METRIC_LABELS[key]}: {shown}")


__all__ = [
    "METRIC_KEYS",
    "METRIC_LABELS",
    "PAPER_RESULTS",
    "STATION_KEYS",
    "CampaignError",
    "campaign_summary",
    "campaign_title",
    "load_trial_results",
    "print_trial_summary",
    "station_summary",
    "summarize",
    "trials_environment",
    "write_summary",
]
