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
"""The paper's ten-trial results (Sec. IV; shared/reference/facts.md), for comparison."""

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


# -- one trial's files -----------------------------------------------------------------
def finish_trial(
    out_dir: str | Path,
    recording_path: str | Path,
    modules: Sequence[Any] | None = None,
    *,
    destination: str = "node2",
    min_interval_s: float | None = None,
    max_gap_s: float | None = None,
) -> dict[str, Any]:
    """Score a finished (or cut-short) recording and write the trial's files.

    Writes ``metrics.json``, ``fig_ctb_body_frame.png`` and ``fig_route.png`` into
    ``out_dir``. The runner calls this after its loop ends.

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

    Returns:
        The metrics dict written to ``metrics.json`` (fields of
        :class:`~payload.trials.metrics.TrialMetrics` plus ``seed``, ``criterion`` and
        ``recording``).
    """
    from payload.trials.figures import plot_ctb_body_frame, plot_route
    from payload.trials.metrics import compute_metrics
    from payload.trials.recorder import read_recording

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = read_recording(recording_path)
    # the contact definition the trial was recorded with, unless the caller overrides it
    recorded = rec.meta.get("contact_definition") or {}
    if min_interval_s is None:
        min_interval_s = float(recorded.get("min_interval_s", 0.0))
    if max_gap_s is None:
        max_gap_s = float(recorded.get("max_gap_s", 0.0))
    metrics = compute_metrics(
        rec, destination=destination, min_interval_s=min_interval_s, max_gap_s=max_gap_s
    )
    result = {"seed": rec.meta.get("seed"), **metrics.as_dict()}
    rec_path = Path(recording_path)
    result["recording"] = (
        rec_path.name if rec_path.resolve().parent == out.resolve() else str(rec_path)
    )
    (out / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    plot_ctb_body_frame(rec, out / "fig_ctb_body_frame.png", metrics)
    plot_route(
        rec, out / "fig_route.png", modules if modules is not None else rec.meta.get("modules")
    )
    return result


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
    seed: int, out_dir: Path, operator: str = "synthetic", retarget_budget: str = "paper"
) -> dict[str, Any]:
    try:
        from payload.trials.runner import run_trial
    except ModuleNotFoundError as exc:
        if exc.name != "payload.trials.runner":
            raise
        raise CampaignError(
            "payload.trials.runner (the teleoperation trial loop, issue 6) is not installed yet"
        ) from None
    return run_trial(
        seed=seed,
        operator=operator,
        replay=None,
        out_dir=Path(out_dir),
        retarget_budget=retarget_budget,
    )


def runner_trial_fn(operator: str = "synthetic", retarget_budget: str = "paper") -> TrialFn:
    """The picklable campaign trial function that calls the teleoperation runner
    (``payload.trials.runner.run_trial``), imported lazily in whichever process runs it."""
    return functools.partial(_runner_trial, operator=operator, retarget_budget=retarget_budget)


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


def summarize(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The campaign summary (what ``summary.json`` holds).

    Every trial counts in ``n``; ``success`` counts trials that succeeded (a trial that
    raised is a failure). Each metric's ``median``, ``min`` and ``max`` are over the trials
    that have a finite value (``count`` of them; ``None`` if none has).

    Args:
        results: Per-trial dicts (from :func:`run_campaign` or :func:`load_trial_results`).

    Returns:
        ``{"n", "success", "errors", <metric>: {"median", "min", "max", "count"}, "seeds",
        "trials", "paper"}``.
    """
    if not results:
        raise CampaignError("no trial results to summarise")
    rows = sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))
    summary: dict[str, Any] = {
        "n": len(rows),
        "success": sum(1 for r in rows if r.get("success") and not r.get("error")),
        "errors": sum(1 for r in rows if r.get("error")),
    }
    for key in METRIC_KEYS:
        vals = _finite([r.get(key) for r in rows if not r.get("error")])
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
        (float(r.get("min_interval_s") or 0.0), float(r.get("max_gap_s") or 0.0))
        for r in rows
        if not r.get("error")
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


def _fmt(stat: dict[str, Any] | None, digits: int) -> str:
    if not stat or stat.get("median") is None:
        return "n/a"
    return f"{stat['median']:.{digits}f} ({stat['min']:.{digits}f} to {stat['max']:.{digits}f})"


def _cell(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{float(value):.{digits}f}"


_DIGITS = {"duration_s": 1, "net_displacement_m": 2, "rms_mm": 1, "peak_mm": 1, "contact_s": 1}


def summary_markdown(summary: dict[str, Any], title: str | None = None) -> str:
    """The paper's results paragraph as Markdown tables: this campaign next to the paper,
    then one row per trial."""
    paper = summary.get("paper", PAPER_RESULTS)
    seeds = [s for s in summary.get("seeds", []) if s is not None]
    lines = [
        f"# {title or 'Cargo-transport campaign'}",
        "",
        f"{summary['n']} trials"
        + (f", seeds {min(seeds)} to {max(seeds)}" if seeds else "")
        + ". Medians with ranges (min to max); the paper's figures are from its Results "
        "section (ten live teleoperated trials).",
        "",
        "| metric | this campaign | paper |",
        "| --- | --- | --- |",
        f"| task success | {summary['success']}/{summary['n']} | {paper['success']}/{paper['n']} |",
    ]
    for key in METRIC_KEYS:
        d = _DIGITS[key]
        stat = summary.get(key)
        count = stat.get("count", summary["n"]) if stat else 0
        note = "" if count == summary["n"] else f" [{count} of {summary['n']} trials]"
        lines.append(f"| {METRIC_LABELS[key]} | {_fmt(stat, d)}{note} | {_fmt(paper[key], d)} |")
    if summary.get("errors"):
        lines += ["", f"{summary['errors']} trial(s) raised an error (counted as failures)."]
    relaxed = summary.get("contact_definition") or {}
    if relaxed.get("min_interval_s") or relaxed.get("max_gap_s"):
        lines += [
            "",
            "Contact interval NOT the paper's definition: indicator dropouts up to "
            f"{relaxed.get('max_gap_s') or 0:.2f} s bridged, runs shorter than "
            f"{relaxed.get('min_interval_s') or 0:.2f} s skipped.",
        ]
    budget = summary.get("retarget_budget")
    if budget:
        shown = budget if isinstance(budget, str) else ", ".join(budget)
        lines += [
            "",
            f"Retargeting budget: {shown} ('paper': at most 20 residual evaluations per pair "
            "solve, the paper's controller; 'converged': each start run to convergence).",
        ]
    run = summary.get("run")
    if run and run.get("wall_s"):
        if run.get("scheduler"):
            where = f"on the Dask scheduler {run['scheduler']}"
        elif (run.get("workers") or 0) > 1:
            where = f"on {run['workers']} local Dask workers"
        else:
            where = "serially"
        lines += [
            "",
            f"Ran {where} in {run['wall_s']:.1f} s; the trials took "
            f"{run.get('trial_wall_s', 0.0):.1f} s added up "
            f"(speed-up {run.get('trial_wall_s', 0.0) / run['wall_s']:.2f}x).",
        ]
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
        "| seed | success | duration [s] | net displacement [m] | RMS [mm] | peak [mm] "
        "| contact [s] | CTB ends in |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in summary.get("trials", []):
        ok = "error" if row.get("error") else ("yes" if row["success"] else "no")
        cells = " | ".join(_cell(row.get(k), _DIGITS[k]) for k in METRIC_KEYS)
        lines.append(f"| {row['seed']} | {ok} | {cells} | {row.get('final_module') or 'n/a'} |")
    return "\n".join(lines) + "\n"


def write_summary(
    results: Sequence[dict[str, Any]],
    out_dir: str | Path,
    title: str | None = None,
    run: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``summary.md`` and ``summary.json`` into ``out_dir`` and return the summary.

    Args:
        results: Per-trial dicts.
        out_dir: The campaign folder.
        title: Heading of ``summary.md``.
        run: How the campaign ran, stored under ``run`` (e.g. ``workers``, ``scheduler``,
            ``wall_s`` of the whole campaign and ``trial_wall_s``, the sum over trials).
    """
    summary = summarize(results)
    budgets = sorted({str(r["retarget_budget"]) for r in results if r.get("retarget_budget")})
    if budgets:
        summary["retarget_budget"] = budgets[0] if len(budgets) == 1 else budgets
    if run is not None:
        summary["run"] = run
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    (out / "summary.md").write_text(summary_markdown(summary, title))
    return summary


def load_trial_results(
    out_dir: str | Path,
    recompute: bool = False,
    *,
    min_interval_s: float | None = None,
    max_gap_s: float | None = None,
) -> list[dict[str, Any]]:
    """Per-trial results from a campaign folder's ``trial-*`` folders, ordered by seed.

    Args:
        out_dir: The campaign folder.
        recompute: Rescore every trial from its ``log.mcap`` (rewriting ``metrics.json``
            and the figures) instead of reading ``metrics.json``; a trial without
            ``metrics.json`` is always rescored.
        min_interval_s: Contact-interval definition used when rescoring (0 = paper;
            None = the one each recording was made with).
        max_gap_s: Same for the bridged indicator dropouts.

    Raises:
        CampaignError: The folder does not exist or holds no trial folders.
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
                    d, d / "log.mcap", min_interval_s=min_interval_s, max_gap_s=max_gap_s
                )
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
