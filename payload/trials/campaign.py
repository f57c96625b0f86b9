"""Trial campaigns: N seeded trials on Dask (or serially), and the paper-style summary.

A campaign folder holds one folder per trial, ``trial-NNNN`` (the seed, zero-padded), each
with ``log.mcap``, ``metrics.json``, ``fig_ctb_body_frame.png`` and ``fig_route.png``
(written by :func:`finish_trial`), plus the campaign's ``summary.md`` and ``summary.json``.

Scale-out: by default a Dask ``LocalCluster`` with K worker processes (one thread each)
runs the trials; ``scheduler="tcp://host:8786"`` runs the same campaign on an existing
Dask cluster (its workers need this package installed and the output folder on a shared
file system). ``workers`` of 0 or 1 runs serially in this process. The trial function is
called as ``trial_fn(seed, out_dir)`` and must be picklable (a module-level function or a
:func:`functools.partial` of one); the results are returned ordered by seed.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.project import Project
from payload.safeio import OverwriteError, write_unless_changed
from payload.trials.scoring import contact_tag, finish_trial

TrialFn = Callable[[int, Path], dict]
"""``trial_fn(seed, out_dir) -> metrics dict`` (what :func:`finish_trial` returns)."""

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

TRIAL_FILES: tuple[str, ...] = (
    "log.mcap",
    "metrics.json",
    "fig_ctb_body_frame.png",
    "fig_route.png",
)


class CampaignError(PayloadError):
    """A campaign cannot run or be summarised (bad arguments, no trials, no scheduler)."""


def trial_dir(out_dir: str | Path, seed: int) -> Path:
    """The folder of the trial with this seed inside a campaign folder."""
    return Path(out_dir) / f"trial-{int(seed):04d}"


# -- running ---------------------------------------------------------------------------
def _call_trial(trial_fn: TrialFn, seed: int, out_dir: str) -> dict[str, Any]:
    """Run one trial, timing it and turning an exception into an ``error`` entry."""
    t0 = time.perf_counter()
    try:
        metrics = dict(trial_fn(seed, Path(out_dir)))
        error = None
    except Exception as exc:  # a crashed trial is a result, not a crash
        metrics = {}
        error = f"{type(exc).__name__}: {exc}"
        metrics["traceback"] = traceback.format_exc(limit=8)
    return {
        **metrics,
        "seed": seed,
        "out_dir": out_dir,
        "wall_s": time.perf_counter() - t0,
        "error": error,
    }


def _runner_trial(
    seed: int,
    out_dir: Path,
    operator: str = "synthetic",
    project: Path | None = None,
    max_time: float | None = None,
    force: bool = False,
    **setup: str,
) -> dict[str, Any]:
    try:
        from payload.trials.runner import run_trial
    except ModuleNotFoundError as exc:
        if exc.name != "payload.trials.runner":
            raise
        raise CampaignError(
            "payload.trials.runner (the teleoperation trial loop, issue 6) is not installed yet"
        ) from None
    extra: dict[str, Any] = {"force": True} if force else {}
    if max_time is not None:
        extra["max_time"] = max_time
    return run_trial(
        seed=seed,
        operator=operator,
        replay=None,
        out_dir=Path(out_dir),
        project=Project.at(project) if project is not None else None,
        **extra,
        **setup,
    )


def runner_trial_fn(
    operator: str = "synthetic",
    project: Path | None = None,
    *,
    max_time: float | None = None,
    force: bool = False,
    **setup: str,
) -> TrialFn:
    """The picklable campaign trial function that calls the teleoperation runner
    (``payload.trials.runner.run_trial``), imported lazily in whichever process runs it.

    Args:
        operator: The operator of every trial.
        project: Root of the design project the trials run on (default: the current
            project of the process that runs each trial).
        max_time: Session length cap [s] (``None``: the runner's).
        force: Replace trials already in the campaign folder.
        setup: ``ctb``, ``propulsion``, ``retarget_budget``: the same for every trial.
    """
    return functools.partial(
        _runner_trial,
        operator=operator,
        project=project,
        max_time=max_time,
        force=force,
        **setup,
    )


def default_workers(n_trials: int) -> int:
    """Worker processes for a local cluster: one per core, at most one per trial."""
    return max(1, min(n_trials, os.cpu_count() or 1))


def run_campaign(
    trial_fn: TrialFn,
    seeds: Sequence[int],
    out_dir: str | Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Run one trial per seed, in parallel on Dask or serially.

    Args:
        trial_fn: ``trial_fn(seed, out_dir) -> metrics dict``; picklable for Dask.
        seeds: Distinct non-negative seeds.
        out_dir: Campaign folder; trial ``s`` runs in :func:`trial_dir` ``(out_dir, s)``.
        workers: Local worker processes (one thread each); ``None`` = one per core (at most
            one per trial); 0 or 1 = serial, in this process. Ignored with ``scheduler``.
        scheduler: Address of an existing Dask scheduler (``tcp://host:8786``).
        progress: Show a rich progress bar.

    Returns:
        One dict per seed, ordered by seed: the trial's metrics plus ``seed``, ``out_dir``,
        ``wall_s`` (wall-clock time of the trial [s]) and ``error`` (``None``, or the
        exception text of a trial that raised; such a trial has no metrics).

    Raises:
        CampaignError: No seeds, duplicate or negative seeds, bad worker count, or the
            scheduler cannot be reached.
    """
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise CampaignError("no seeds: a campaign needs at least one trial")
    if len(set(seeds)) != len(seeds):
        raise CampaignError(f"duplicate seeds in {seeds}")
    if min(seeds) < 0:
        raise CampaignError(f"seeds must be >= 0, got {min(seeds)}")
    if workers is not None and workers < 0:
        raise CampaignError(f"workers must be >= 0, got {workers}")
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    dirs = {s: str(trial_dir(out, s)) for s in seeds}
    k = default_workers(len(seeds)) if workers is None else workers

    results: dict[int, dict[str, Any]] = {}
    with _progress(progress, len(seeds)) as bar:
        if scheduler is None and k <= 1:
            for s in seeds:
                results[s] = _call_trial(trial_fn, s, dirs[s])
                bar.advance(results[s])
        else:
            _run_dask(trial_fn, seeds, dirs, k, scheduler, results, bar)
    return [results[s] for s in sorted(seeds)]


def _run_dask(
    trial_fn: TrialFn,
    seeds: list[int],
    dirs: dict[int, str],
    workers: int,
    scheduler: str | None,
    results: dict[int, dict[str, Any]],
    bar: _Bar,
) -> None:
    from distributed import Client, LocalCluster, as_completed

    cluster = None
    try:
        if scheduler is None:
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout=10)
            except (OSError, TimeoutError) as exc:
                raise CampaignError(f"cannot reach Dask scheduler {scheduler}: {exc}") from None
        with client:
            futures = {
                client.submit(_call_trial, trial_fn, s, dirs[s], pure=False, key=f"trial-{s}"): s
                for s in seeds
            }
            for fut in as_completed(list(futures)):
                s = futures[fut]
                try:
                    results[s] = fut.result()
                except Exception as exc:  # e.g. a worker died
                    results[s] = {
                        "seed": s,
                        "out_dir": dirs[s],
                        "wall_s": math.nan,
                        "error": f"{type(exc).__name__}: {exc}",
                    }
                bar.advance(results[s])
    finally:
        if cluster is not None:
            cluster.close()


class _Bar:
    """A rich progress bar (or nothing) counting finished and successful trials."""

    def __init__(self, enabled: bool, total: int) -> None:
        self.enabled = enabled
        self.total = total
        self.ok = 0
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> _Bar:
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self._progress = Progress(
                TextColumn("[bold]trials"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[ok]} succeeded"),
                TimeElapsedColumn(),
                console=Console(stderr=True),
                transient=False,
            )
            self._progress.__enter__()
            self._task = self._progress.add_task("trials", total=self.total, ok=0)
        return self

    def advance(self, result: dict[str, Any]) -> None:
        self.ok += bool(result.get("success")) and not result.get("error")
        if self._progress is not None:
            self._progress.update(self._task, advance=1, ok=self.ok)

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.__exit__(None, None, None)


def _progress(enabled: bool, total: int) -> _Bar:
    return _Bar(enabled, total)


# -- summary ---------------------------------------------------------------------------
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
    ``ctb`` and ``propulsion`` name the CTB model and the propulsion model of the trials.

    Args:
        results: Per-trial dicts (from :func:`run_campaign` or :func:`load_trial_results`).

    Returns:
        ``{"n", "success", "errors", "acquisition_success", <metric>: {"median", "min",
        "max", "count"}, "contact_definition", "seeds", "trials", "paper", "ctb",
        "propulsion", "literal"}``.
    """
    if not results:
        raise CampaignError("no trial results to summarise")
    rows = sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))
    summary = _summary_core(rows)
    summary["ctb"] = _one_value(rows, "ctb")
    summary["propulsion"] = _one_value(rows, "propulsion")
    summary["literal"] = _summary_core([_literal_row(r) for r in rows])
    return summary


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
    d = definition or {}
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
        lines += ["", f"{summary['errors']} trial(s) raised an error (counted as failures)."]
    lines += [
        "",
        "Contact definitions. Confirmed contact (the recorded one): "
        + _definition_text(summary.get("contact_definition"))
        + ". Paper-literal: "
        + _definition_text(lit.get("contact_definition") if lit else None)
        + ". Acquisition succeeds when a first contact interval exists under the definition.",
    ]
    budget = summary.get("retarget_budget")
    if budget:
        shown = budget if isinstance(budget, str) else ", ".join(budget)
        lines += [
            "",
            f"Retargeting budget: {shown} ('paper': at most 20 residual evaluations per pair "
            "solve, the paper's controller; 'converged': each start run to convergence).",
        ]
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
    """Write ``summary.md`` and ``summary.json`` into ``out_dir`` and return the summary.

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
    if run is not None:
        summary["run"] = run
    if provenance is not None:
        summary["provenance"] = provenance
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"summary.{tag}" if tag else "summary"
    data = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    text = summary_markdown(summary, title)
    files = {out / f"{stem}.json": data, out / f"{stem}.md": text}
    for path, content in files.items():  # check both before writing either
        if not force and path.exists() and path.read_bytes() != content.encode():
            raise OverwriteError(f"{path}: exists with different content (pass --force to replace)")
    write_unless_changed(out / f"{stem}.json", data, force=force)
    write_unless_changed(out / f"{stem}.md", text, force=force)
    return summary


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
            ``metrics.json`` is always scored.
        min_interval_s: Contact-interval definition used when rescoring (0 = paper;
            None = the one each recording was made with).
        max_gap_s: Same for the bridged indicator dropouts.
        force: Replace rescoring files that exist with other content.

    Raises:
        CampaignError: The folder does not exist or holds no trial folders.
        OverwriteError: A rescoring file exists with other content and ``force`` is false.
    """
    root = Path(out_dir)
    if not root.is_dir():
        raise CampaignError(f"{root}: no such campaign folder")
    dirs = sorted(p for p in root.glob("trial-*") if p.is_dir())
    if not dirs:
        raise CampaignError(f"{root}: no trial-* folders")
    results = []
    for d in dirs:
        try:
            seed: int | None = int(d.name.split("-", 1)[1])
        except ValueError:
            seed = None
        metrics_path = d / "metrics.json"
        if recompute or not metrics_path.exists():
            if not (d / "log.mcap").exists():
                results.append(
                    {"seed": seed, "out_dir": str(d), "error": "no log.mcap and no metrics.json"}
                )
                continue
            try:
                row = finish_trial(
                    d,
                    d / "log.mcap",
                    min_interval_s=min_interval_s,
                    max_gap_s=max_gap_s,
                    beside=recompute,
                    force=force,
                )
            except OverwriteError:
                raise
            except PayloadError as exc:
                results.append({"seed": seed, "out_dir": str(d), "error": str(exc)})
                continue
        else:
            row = json.loads(metrics_path.read_text())
        row.setdefault("error", None)
        if row.get("seed") is None:
            row["seed"] = seed
        row["out_dir"] = str(d)
        results.append(row)
    return sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))


__all__ = [
    "METRIC_KEYS",
    "PAPER_RESULTS",
    "CampaignError",
    "TrialFn",
    "contact_tag",
    "default_workers",
    "finish_trial",
    "load_trial_results",
    "run_campaign",
    "runner_trial_fn",
    "summarize",
    "summary_markdown",
    "trial_dir",
    "write_summary",
]
