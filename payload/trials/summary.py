"""A campaign's results: reading the trial folders, the paper-style summary and its files."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.folders import METRICS, RECORDING, SUMMARY, SUMMARY_TEXT, held, tagged
from payload.safeio import OverwriteError, write_unless_changed
from payload.trials.scoring import finish_trial

METRIC_KEYS: tuple[str, ...] = (
    "duration_s",
    "net_displacement_m",
    "rms_mm",
    "peak_mm",
    "contact_s",
)
"""The per-trial figures the paper summarises, in its order."""

METRIC_LABELS: dict[str, str] = {
    "duration_s": "Teleoperation duration after calibration [s]",
    "net_displacement_m": "CTB net world-frame displacement [m]",
    "rms_mm": "RMS deviation in the body frame, eq. 5 [mm]",
    "peak_mm": "Peak deviation in the body frame [mm]",
    "contact_s": "First confirmed-contact interval [s]",
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


class CampaignError(PayloadError):
    """A campaign cannot run or be summarised (bad arguments, no trials, no scheduler)."""


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


def _one_value(rows: Sequence[dict[str, Any]], key: str) -> Any:
    """The value every trial records under ``key``; ``{"mixed": [...]}`` if they differ,
    ``None`` if none records it."""
    values = sorted({str(r[key]) for r in rows if r.get(key) is not None})
    if not values:
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
        vals = _finite([r.get(key) for r in ok_rows])
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
    (``count`` of them; ``None`` if none has). ``literal`` holds the same fields under the
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
        "propulsion", "physics_dt", "literal"}``.
    """
    if not results:
        raise CampaignError("no trial results to summarise")
    rows = sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))
    summary = _summary_core(rows)
    summary["ctb"] = _one_value(rows, "ctb")
    summary["propulsion"] = _one_value(rows, "propulsion")
    steps = sorted({float(r["physics_dt"]) for r in rows if r.get("physics_dt") is not None})
    summary["physics_dt"] = (steps[0] if len(steps) == 1 else {"mixed": steps}) if steps else None
    summary["literal"] = _summary_core([_literal_row(r) for r in rows])
    summary["station"] = station_summary(rows)
    return summary


STATION_KEYS = ("station_contacts", "min_station_clearance_mm", "filter_active_s")
"""The per-trial station figures (:mod:`payload.trials.safety`)."""


def station_summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Station contacts over the trials that measured them: how many trials touched the
    station, the contact steps in all and at most, the least clearance [mm], the filter's
    active time [s] (median, max), and the base-filter and link-delay settings."""
    ok = [r for r in rows if not r.get("error") and r.get("station_contacts") is not None]
    out: dict[str, Any] = {
        "measured": len(ok),
        "base_filter": _one_value(rows, "base_filter"),
        "link_delay": _one_value(rows, "link_delay"),
    }
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


def _station_lines(station: dict[str, Any] | None) -> list[str]:
    if not station or not station.get("measured"):
        return []
    active = station.get("filter_active_s") or {}
    delay = station.get("link_delay")
    on = {"True": "on", "False": "off"}.get(str(station.get("base_filter")), "mixed")
    return [
        "",
        f"Station contacts: {station['trials_with_contacts']} of {station['measured']} "
        f"trials touched the station ({station['station_contacts']['total']} control steps "
        f"in all); least clearance {station['min_station_clearance_mm']} mm (measured up to "
        f"300 mm); base filter {on}, active "
        f"{active.get('median', 0.0):.1f} s median per trial"
        f"{f'; link delay (delay, jitter) {delay} s' if delay else ''}.",
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

    lines = [
        *_header_lines(summary, title),
        "| metric | this campaign, confirmed contact | this campaign, paper-literal contact "
        "| paper |",
        "| --- | --- | --- | --- |",
        f"| task success | {summary['success']}/{n} | {lit.get('success', 'n/a')}/{n} "
        f"| {paper['success']}/{paper['n']} |",
        f"| acquisition success | {acq(summary)} | {acq(lit)} | n/a |",
    ]
    for key in METRIC_KEYS:
        d = _DIGITS[key]
        cells = []
        for s in (summary, lit):
            stat = s.get(key)
            count = stat.get("count", n) if stat else 0
            note = "" if count == n else f" [{count} of {n} trials]"
            cells.append(f"{_fmt(stat, d)}{note}")
        lines.append(f"| {METRIC_LABELS[key]} | {cells[0]} | {cells[1]} | {_fmt(paper[key], d)} |")
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
        "Contact definitions. Confirmed contact (the recorded one): "
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
    lines += [
        "",
        "Success: the CTB is in the destination module at the end, and the first continuous "
        "confirmed-contact interval carries it there and holds it until arrival (the later "
        "of its entry and the start of the operator's arrival phase; without that phase, "
        "the end of the recording). RMS and peak deviation: eq. 5 "
        "over that interval, from the CTB position in the Astrobee body frame (eq. 4) at "
        "its first sample.",
        "",
        "## Trials",
        "",
        "Per trial, confirmed contact, then the paper-literal success, RMS and contact interval.",
        "",
        "| seed | success | duration [s] | net displacement [m] | RMS [mm] | peak [mm] "
        "| contact [s] | CTB ends in | literal success | literal RMS [mm] | literal contact [s] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    literal_rows = {r.get("seed"): r for r in lit.get("trials", [])}
    for row in summary.get("trials", []):
        ok = "error" if row.get("error") else ("yes" if row["success"] else "no")
        cells = " | ".join(_cell(row.get(k), _DIGITS[k]) for k in METRIC_KEYS)
        lr = literal_rows.get(row["seed"], {})
        lok = "error" if row.get("error") else ("yes" if lr.get("success") else "no")
        lines.append(
            f"| {row['seed']} | {ok} | {cells} | {row.get('final_module') or 'n/a'} | {lok} "
            f"| {_cell(lr.get('rms_mm'), 1)} | {_cell(lr.get('contact_s'), 1)} |"
        )
    return "\n".join(lines) + "\n"


def _run_lines(run: dict[str, Any] | None) -> list[str]:
    if not run or not run.get("wall_s"):
        return []
    if run.get("scheduler"):
        where = f"on the Dask scheduler {run['scheduler']}"
    elif (run.get("workers") or 0) > 1:
        where = f"on {run['workers']} local Dask workers"
    else:
        where = "serially"
    return [
        "",
        f"Ran {where} in {run['wall_s']:.1f} s; the trials took "
        f"{run.get('trial_wall_s', 0.0):.1f} s added up "
        f"(speed-up {run.get('trial_wall_s', 0.0) / run['wall_s']:.2f}x).",
    ]


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
    # whether the pair solves modelled self-collision: one bool when every trial says the
    # same, else the values seen (None: a trial that does not say)
    seen = {r.get("retarget_collisions") for r in results}
    seen = {v if isinstance(v, bool) else None for v in seen}
    if seen != {None}:
        summary["retarget_collisions"] = (
            seen.pop() if len(seen) == 1 else sorted(seen, key=lambda v: (v is not None, v))
        )
    if run is not None:
        summary["run"] = run
    if provenance is not None:
        summary["provenance"] = provenance
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
        write_campaign_figure(summary, METRIC_LABELS, out, tag)
    return summary


def read_metrics(path: Path) -> dict[str, Any]:
    """A trial's ``metrics.json``.

    Raises:
        CampaignError: Unreadable, not JSON (cut short, binary) or not a JSON object: one
            line naming the file; or a field a summary reads has a value of the wrong
            kind (``success`` missing or not true or false, a figure that is not a number
            or null...): one line naming the file, the field and what was expected.
    """
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # JSON and UTF-8 errors are ValueErrors
        raise CampaignError(f"{path}: cannot read the trial's metrics ({exc})") from None
    if not isinstance(data, dict):
        raise CampaignError(f"{path}: cannot read the trial's metrics (not a JSON object)")
    if "success" not in data:
        raise CampaignError(f"{path}: success: missing (not a trial's metrics)")
    _check_metrics(data, str(path))
    _check_metrics(data.get("literal") or {}, f"{path}: literal")
    return data


_METRIC_KINDS: dict[str, Any] = {
    **dict.fromkeys(("success", "acquired", "complete"), "bool"),
    **dict.fromkeys(
        (*METRIC_KEYS, "min_interval_s", "max_gap_s", "physics_dt", "wall_s"), "float_nan"
    ),
    **dict.fromkeys(("final_module", "ctb", "propulsion", "error"), "text"),
}
"""The type of each field a summary or a comparison reads from ``metrics.json`` (null is
allowed for every number and text; older files may leave any of them out)."""


def _check_metrics(data: Any, where: str) -> None:
    """Raise :class:`CampaignError` naming the file and field of the first value that a
    summary cannot use (a metrics file edited by hand, or written by another tool)."""
    from payload.trials.stepcheck import field_problem

    if not isinstance(data, dict):
        raise CampaignError(f"{where}: expected a JSON object, got {type(data).__name__}")
    seed = data.get("seed")
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
        raise CampaignError(f"{where}: seed: expected an integer >= 0 or null, got {seed!r}")
    for key, kind in _METRIC_KINDS.items():
        value = data.get(key)
        if value is None:
            continue
        if kind == "text":
            problem = None if isinstance(value, str) else f"got {value!r}"
            problem = problem and f"expected text or null, {problem}"
        else:
            problem = field_problem(value, (), kind)
        if problem is not None:
            raise CampaignError(f"{where}: {key}: {problem}")


def _unfinished(meta: dict[str, Any] | None, complete: bool) -> str | None:
    """The error row's text of a trial whose recording is not a finished run's
    (:func:`~payload.trials.reading.unfinished_reason`), or ``None``."""
    from payload.trials.reading import unfinished_reason

    why = unfinished_reason(meta or {}, complete)
    return None if why is None else f"{RECORDING}: {why}; not scored"


def load_trial_results(
    out_dir: str | Path,
    recompute: bool = False,
    *,
    min_interval_s: float | None = None,
    max_gap_s: float | None = None,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Per-trial results from a campaign folder's ``trial-*`` folders, ordered by seed.

    Args:
        out_dir: The campaign folder.
        recompute: Rescore every trial from its ``log.mcap`` instead of reading
            ``metrics.json``, writing the results beside the originals, named by the
            contact definition (see :func:`finish_trial`); a trial without
            ``metrics.json`` is scored, unless its recording is an aborted trial's or was
            cut short (never closed): that trial is an ``error`` row, a failure.
        min_interval_s: Contact-interval definition used when rescoring (0 = paper;
            None = the one each recording was made with).
        max_gap_s: Same for the bridged indicator dropouts.
        force: Replace rescoring files that exist with other content.

    Raises:
        CampaignError: The folder does not exist or holds no trial folders.
        OverwriteError: A rescoring file exists with other content and ``force`` is false.
        DamagedRecordingError: A recording read for scoring is damaged.
        CampaignError: A trial's ``metrics.json`` cannot be read (:func:`read_metrics`).
    """
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise CampaignError(f"{root}: a file, not a campaign folder")
    if not root.is_dir():
        raise CampaignError(f"{root}: no such campaign folder")
    dirs = sorted(p for p in root.glob("trial-*") if p.is_dir())
    if not dirs:
        if held(root, (RECORDING, METRICS)):  # a trial's own folder, given for a campaign's
            raise CampaignError(
                f"{root}: a trial's folder, not a campaign's (no trial-* folders); give the "
                "campaign folder that holds it"
            )
        raise CampaignError(f"{root}: no trial-* folders")
    from payload.trials.reading import read_recording, recording_meta
    from payload.trials.records import DamagedRecordingError

    # every recording to be scored is read first: a damaged one stops the summary before
    # anything is written (a re-scoring beside an earlier trial's metrics, say)
    reads: dict[Path, Any] = {}
    for d in dirs:
        if (recompute or not (d / METRICS).exists()) and (d / RECORDING).exists():
            try:
                reads[d] = read_recording(d / RECORDING)
            except DamagedRecordingError:
                raise  # damage is not a trial's failure: nothing is scored from it
            except PayloadError as exc:
                reads[d] = exc
    results = []
    for d in dirs:
        try:
            seed: int | None = int(d.name.split("-", 1)[1])
        except ValueError:
            seed = None
        metrics_path = d / METRICS
        if recompute or not metrics_path.exists():
            if not (d / RECORDING).exists():
                results.append(
                    {"seed": seed, "out_dir": str(d), "error": f"no {RECORDING} and no {METRICS}"}
                )
                continue
            rec = reads[d]
            if isinstance(rec, PayloadError):
                results.append({"seed": seed, "out_dir": str(d), "error": str(rec)})
                continue
            try:
                unfinished = _unfinished(rec.meta, rec.complete)
                if unfinished:  # as the runner leaves it: a record, not a scored trial
                    results.append({"seed": seed, "out_dir": str(d), "error": unfinished})
                    continue
                row = finish_trial(
                    d,
                    d / RECORDING,
                    min_interval_s=min_interval_s,
                    max_gap_s=max_gap_s,
                    beside=recompute,
                    force=force,
                    recording=rec,
                )
            except OverwriteError:
                raise
            except PayloadError as exc:
                results.append({"seed": seed, "out_dir": str(d), "error": str(exc)})
                continue
        else:
            row = read_metrics(metrics_path)
            # scored before summaries checked: an aborted run's metrics.json does not say
            # so, its recording's metadata does (read through the file's index)
            meta = recording_meta(d / RECORDING)
            unfinished = _unfinished(meta, row.get("complete", True))
            if unfinished:
                results.append({"seed": seed, "out_dir": str(d), "error": unfinished})
                continue
        row.setdefault("error", None)
        if row.get("seed") is None:
            row["seed"] = seed
        row["out_dir"] = str(d)
        results.append(row)
    return sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))


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
        f"{result.get('retarget_budget')}, self-collision {modelled}{given}"
    )
    print(f"  success: {bool(result.get('success'))}")
    if "station_contacts" in result:
        delay = result.get("link_delay")
        jitter = f" +-{delay[1]:g}" if delay and len(delay) > 1 and delay[1] else ""
        print(
            f"  base filter {'on' if result.get('base_filter') else 'off'}"
            f"{f', link delay {delay[0]:g}{jitter} s' if delay else ''}; "
            f"station contacts: {result.get('station_contacts')} steps, least clearance "
            f"{result.get('min_station_clearance_mm')} mm, filter active "
            f"{result.get('filter_active_s')} s"
        )
    for key in METRIC_KEYS:
        value = result.get(key)
        shown = "n/a" if value is None else f"{value:.3f}"
        print(f"  {METRIC_LABELS[key]}: {shown}")
