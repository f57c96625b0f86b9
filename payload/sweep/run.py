"""Run a design sweep's points on Dask (a local cluster by default, or an existing one)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from payload.project import Project
from payload.sweep.grid import Axis, SweepError, check_axes, edit_design, grid, validate_point
from payload.sweep.point import run_point
from payload.trials.cluster import dask_client

DEFAULT_SAMPLES = 20_000
"""Reach samples per point (``payload report reach`` uses 100,000; a sweep compares)."""


def point_dir(out: Path, index: int) -> Path:
    """Folder of point ``index`` under the sweep folder."""
    return out / f"point-{index:03d}"


def plan(base: Project, axes: list[Axis], out: Path) -> list[tuple[Path, dict[str, float], str]]:
    """The points of a sweep: ``(folder, params, design text)`` each.

    Raises:
        SweepError: Bad axes, a point folder that already exists and is not empty
            (a sweep never overwrites earlier results), or a grid whose every point is an
            invalid design (a unit slip in every value: nothing to run).
    """
    from payload.design import load_design
    from payload.errors import DesignError

    check_axes(axes, load_design(base.design_path))
    text = base.design_path.read_text(encoding="utf-8")
    points = []
    invalid = []
    for i, params in enumerate(grid(axes)):
        folder = point_dir(out, i)
        if folder.exists() and any(folder.iterdir()):
            raise SweepError(
                f"{folder}: already holds files; choose another --out (results are never "
                "overwritten)"
            )
        points.append((folder, params, edit_design(text, params)))
        try:
            validate_point(points[-1][2])
        except DesignError as exc:
            invalid.append((params, exc))
    if invalid and len(invalid) == len(points):
        params, exc = invalid[0]
        which = ", ".join(f"{k}={v:g}" for k, v in params.items())
        raise SweepError(
            f"every point of the sweep is an invalid design, nothing run (the first, {which}: "
            f"{exc})"
        )
    return points


def run_points(
    points: list[tuple[Path, dict[str, float], str]],
    *,
    samples: int,
    seed: int,
    trials: int,
    workers: int,
    scheduler: str | None,
    on_result: Callable[[dict[str, Any]], None] = lambda r: None,
) -> list[dict[str, Any]]:
    """Run every point on Dask and return the results in point order.

    Args:
        points: From :func:`plan`.
        samples: Reach samples per point.
        seed: Reach and trial seed.
        trials: Trials per point (0: none).
        workers: Local worker processes (one thread each); ignored with ``scheduler``.
        scheduler: Address of an existing Dask scheduler, e.g. ``tcp://host:8786``.
        on_result: Called with each result as it arrives (the progress bar).

    Raises:
        SweepError: The scheduler cannot be reached.
    """
    from distributed import as_completed

    results: dict[int, dict[str, Any]] = {}
    with dask_client(workers, scheduler, SweepError) as client:
        futures = {
            client.submit(
                run_point,
                str(folder),
                params,
                text,
                samples=samples,
                seed=seed,
                trials=trials,
                pure=False,
                key=f"sweep-point-{i}-{folder.parent.name}",
            ): i
            for i, (folder, params, text) in enumerate(points)
        }
        for fut in as_completed(list(futures)):
            i = futures[fut]
            try:
                results[i] = fut.result()
            except Exception as exc:  # e.g. a worker died
                results[i] = {
                    "params": points[i][1],
                    "valid": False,
                    "error": f"{type(exc).__name__}: {exc}",
                    "fits": False,
                    "min_clearance_mm": None,
                    "below_vehicle_mm": None,
                    "span_max_mm": None,
                    "trials": None,
                    "project": str(points[i][0]),
                }
            on_result(results[i])
    return [results[i] for i in range(len(points))]


__all__ = ["DEFAULT_SAMPLES", "plan", "point_dir", "run_points"]
