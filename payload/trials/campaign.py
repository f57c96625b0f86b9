"""Trial campaigns: N seeded trials on Dask or serially (summary: :mod:`payload.trials.summary`).

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
import os
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from payload.folders import trial_dir
from payload.project import Project
from payload.trials.cluster import dask_client
from payload.trials.scoring import contact_tag, finish_trial
from payload.trials.setup_options import seed_problem
from payload.trials.summary import summarize, write_summary
from payload.trials.summary_fields import METRIC_KEYS, METRIC_LABELS, PAPER_RESULTS, CampaignError
from payload.trials.summary_markdown import summary_markdown
from payload.trials.trial_results import load_trial_results

TrialFn = Callable[[int, Path], dict]
"""``trial_fn(seed, out_dir) -> metrics dict`` (what :func:`finish_trial` returns)."""


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
    **setup: Any,
) -> dict[str, Any]:
    from payload.trials.runner import run_trial

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
    **setup: Any,
) -> TrialFn:
    """The picklable campaign trial function that calls the teleoperation runner
    (``payload.trials.runner.run_trial``), imported lazily in whichever process runs it.

    Args:
        operator: The operator of every trial.
        project: Root of the design project the trials run on (default: the current
            project of the process that runs each trial).
        max_time: Session length cap [s] (``None``: the runner's).
        force: Replace trials already in the campaign folder.
        setup: ``ctb``, ``propulsion``, ``retarget_budget``, ``retarget_collisions``: the
            same for every trial.
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
    on_trial: Callable[[dict[str, Any]], None] | None = None,
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
        on_trial: Called with each trial's result as it finishes (in finishing order),
            e.g. to print a line per trial where no progress bar can show.

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
    for seed in (min(seeds), max(seeds)):
        if (problem := seed_problem(seed)) is not None:
            raise CampaignError(f"seeds {problem}")
    if workers is not None and workers < 0:
        raise CampaignError(f"workers must be >= 0, got {workers}")
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    dirs = {s: str(trial_dir(out, s)) for s in seeds}
    k = default_workers(len(seeds)) if workers is None else workers

    results: dict[int, dict[str, Any]] = {}
    with _Bar(progress, len(seeds), on_trial) as bar:
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
    from distributed import as_completed

    with dask_client(workers, scheduler, CampaignError) as client:
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
                    "wall_s": None,  # not known (JSON has no NaN: the summary refuses it)
                    "error": f"{type(exc).__name__}: {exc}",
                }
            bar.advance(results[s])


class _Bar:
    """A rich progress bar (or nothing) counting finished and successful trials."""

    def __init__(
        self,
        enabled: bool,
        total: int,
        on_trial: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.enabled = enabled
        self.on_trial = on_trial
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
        if self.on_trial is not None:
            self.on_trial(result)

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.__exit__(None, None, None)


# -- summary ---------------------------------------------------------------------------
__all__ = [
    "METRIC_KEYS",
    "METRIC_LABELS",
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
