"""One point of a design sweep: a project of its own, built, checked and analysed.

:func:`run_point` runs in whichever process Dask gives it. It writes the point's
design file, then runs the very commands a person would type in that project
(``payload build``, ``payload report envelope --json``, ``payload report reach --json``
and, with trials, ``payload trials run --json``), so a point's figures are those
commands' figures. An invalid design or a failed command is a result, never an
exception.
"""

from __future__ import annotations

import contextlib
import io
import json
import traceback
from pathlib import Path
from typing import Any

from payload.errors import DesignError

POINT_FIELDS = (
    "params",
    "valid",
    "error",
    "fits",
    "min_clearance_mm",
    "below_vehicle_mm",
    "span_max_mm",
    "trials",
)
"""The fields of a point in ``sweep.json`` (the issue's contract), in order."""


def _run(argv: list[str]) -> tuple[int, dict[str, Any] | None, str]:
    """Run ``payload ARGV`` in this process: exit code, the JSON it printed, its stderr."""
    from payload.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    text = out.getvalue().strip()
    data = None
    if text:
        try:
            data = json.loads(text.splitlines()[-1])
        except json.JSONDecodeError:
            data = None
    return code, data, err.getvalue().strip()


def _first_line(text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    return lines[-1].removeprefix("payload: error: ") if lines else "no message"


def point_commands(root: Path, samples: int, seed: int, trials: int) -> list[list[str]]:
    """The commands a point runs (what to type by hand in ``root`` for the same figures)."""
    project = ["--project", str(root)]
    cmds = [
        [*project, "build"],
        # the sweep reports the given posture: the stowed-posture search is not needed
        [*project, "report", "envelope", "--no-search", "--json"],
        # one process: a Dask worker may not fork (the figures do not depend on it)
        [
            *project,
            "report",
            "reach",
            "--samples",
            str(samples),
            "--seed",
            str(seed),
            "--workers",
            "1",
            "--json",
        ],
    ]
    if trials:
        cmds.append(
            [
                *project,
                "trials",
                "run",
                "--n",
                str(trials),
                "--seed",
                str(seed),
                "--workers",
                "1",
                "--out",
                str(root / "runs" / "campaign"),
                "--json",
            ]
        )
    return cmds


def _empty(params: dict[str, float], error: str | None, valid: bool) -> dict[str, Any]:
    return {
        "params": params,
        "valid": valid,
        "error": error,
        "fits": False,
        "min_clearance_mm": None,
        "below_vehicle_mm": None,
        "span_max_mm": None,
        "trials": None,
    }


def run_point(
    root: str | Path,
    params: dict[str, float],
    design_text: str,
    *,
    samples: int,
    seed: int = 0,
    trials: int = 0,
) -> dict[str, Any]:
    """Make, build and analyse one sweep point.

    Args:
        root: The point's project folder (created; must be new or empty).
        params: The swept values of this point, ``{dotted key: value}``.
        design_text: The point's design file (the base design with ``params`` written in).
        samples: Reach samples.
        seed: Reach and first trial seed.
        trials: Trials per point (0: none).

    Returns:
        The point as in ``sweep.json`` (:data:`POINT_FIELDS`), plus ``project``,
        ``passed`` (the envelope check as a whole), ``span_min_mm`` and ``failures``.
    """
    from payload.sweep.grid import validate_point

    root = Path(root).resolve()
    (root / "cad").mkdir(parents=True, exist_ok=True)
    (root / "cad" / "design.toml").write_text(design_text, encoding="utf-8")
    (root / "point.json").write_text(json.dumps({"params": params}, indent=2) + "\n")
    try:
        validate_point(design_text)
    except DesignError as exc:
        return {**_empty(params, str(exc), valid=False), "project": str(root)}
    cmds = point_commands(root, samples, seed, trials)
    try:
        return _analyse(root, params, cmds)
    except Exception as exc:  # a crashed point is a result, not a crashed sweep
        result = _empty(params, f"{type(exc).__name__}: {exc}", valid=False)
        result["traceback"] = traceback.format_exc(limit=8)
        return {**result, "project": str(root)}


def _analyse(root: Path, params: dict[str, float], cmds: list[list[str]]) -> dict[str, Any]:
    result = {**_empty(params, None, valid=True), "project": str(root)}
    code, _, err = _run(cmds[0])
    if code != 0:  # the design validates but its solids or files cannot be made
        return {**result, "valid": False, "error": f"build: {_first_line(err)}"}
    code, env, err = _run(cmds[1])
    if env is None:
        return {**result, "valid": False, "error": f"report envelope: {_first_line(err)}"}
    result.update(
        fits=bool(env["fits"]),
        passed=bool(env["passed"]),
        min_clearance_mm=env["min_clearance_mm"],
        failures=env["failures"],
    )
    code, reach, err = _run(cmds[2])
    if reach is None:
        return {**result, "error": f"report reach: {_first_line(err)}"}
    result.update(
        below_vehicle_mm=reach["below_vehicle_mm"],
        span_max_mm={p: reach["pairs"][p]["span_max_mm"] for p in ("L", "R")},
        span_min_mm={p: reach["pairs"][p]["span_min_mm"] for p in ("L", "R")},
    )
    if len(cmds) > 3:
        code, summary, err = _run(cmds[3])
        if summary is None:
            return {**result, "error": f"trials run: {_first_line(err)}"}
        result["trials"] = {
            "n": int(summary["n"]),
            "success": int(summary["success"]),
            "rms_mm_median": summary["rms_mm"]["median"],
            "duration_s_median": summary["duration_s"]["median"],
        }
    return result


__all__ = ["POINT_FIELDS", "point_commands", "run_point"]
