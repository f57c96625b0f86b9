"""One point of a design sweep: a project of its own, built, checked and analysed.

:func:`run_point` runs in whichever process Dask gives it. It writes the point's
design file, then runs what the commands a person would type in that project run
(:func:`point_commands`: ``payload build``, ``payload report envelope``, ``payload
report reach`` and, with trials, ``payload trials run``) through the same library
functions, with the same settings, and writes the same files; so a point's figures are
those commands' figures. An invalid design or a failed step is a result, never an
exception.
"""

from __future__ import annotations

import json
import time
import traceback
from pathlib import Path
from typing import Any

from payload.errors import DesignError, PayloadError

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
        # not checked (extra fields: after the contract's in sweep.json)
        "passed": None,
        "reach_passed": None,
        "min_self_clearance_mm": None,
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
        ``passed`` (the envelope check as a whole), ``reach_passed`` (the reach report's
        verdict), ``min_self_clearance_mm`` (the
        least gap between two payload parts, stowed, as the envelope report's),
        ``span_min_mm`` and ``failures``.
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
    try:
        return _analyse(root, params, samples, seed, trials)
    except Exception as exc:  # a crashed point is a result, not a crashed sweep
        result = _empty(params, f"{type(exc).__name__}: {exc}", valid=False)
        result["traceback"] = traceback.format_exc(limit=8)
        return {**result, "project": str(root)}


def _first_line(exc: BaseException | str) -> str:
    lines = [ln for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def _build(root: Path) -> None:
    """``payload build`` in the point's project."""
    from payload.design import load_design, write

    write(load_design(root / "cad" / "design.toml"), root)


class _Reports:
    """``payload report envelope --no-search`` and ``payload report reach --samples N
    --seed S --workers 1`` in the point's project: their JSON, their files written."""

    def __init__(self, root: Path, samples: int, seed: int) -> None:
        from payload.project import Project, provenance

        self.project = Project.at(root)
        self.samples, self.seed = samples, seed
        self.cmds = point_commands(root, samples, seed, 0)
        self.prov = provenance(self.project, self.project.design_path)
        self.prov.pop("project")

    def _record(self, data: dict[str, Any]) -> dict[str, Any]:
        return {**data, "provenance": self.prov}

    def envelope(self) -> dict[str, Any]:
        from payload.design import build_tree
        from payload.envelope.fit import analyse_envelope
        from payload.envelope.geometry import PayloadGeometry
        from payload.envelope.report import envelope_json, write_envelope
        from payload.envelope.vehicle import load_design_and_vehicle

        t0 = time.perf_counter()
        design, self.vehicle = load_design_and_vehicle(self.project.design_path)
        self.geom = PayloadGeometry(build_tree(design))
        env = analyse_envelope(self.geom, self.vehicle, search=False)
        env.seconds = time.perf_counter() - t0
        out = self.project.analyses_dir
        write_envelope(self.geom, env, out, _typed(self.cmds[1]), self._record)
        return self._record(envelope_json(env))

    def reach(self) -> dict[str, Any]:
        from payload.envelope.reach import CTB_FEATURES, analyse_reach
        from payload.envelope.report import reach_json, write_reach

        t0 = time.perf_counter()
        a = analyse_reach(
            self.geom,
            self.vehicle,
            samples=self.samples,
            seed=self.seed,
            features=list(CTB_FEATURES),
            workers=1,  # one process: a Dask worker may not fork
        )
        out = self.project.analyses_dir
        write_reach(self.geom, a, out, _typed(self.cmds[2]), t_start=t0, record=self._record)
        return self._record(reach_json(a))


def _typed(argv: list[str]) -> str:
    """A point command as the report names it: without ``--project``, ``--json``, the
    default seed and ``--workers`` (which do not change the figures)."""
    words = [w for w in argv[2:] if w != "--json"]
    for flag, value in (("--seed", "0"), ("--workers", "1")):
        if flag in words and words[words.index(flag) + 1] == value:
            i = words.index(flag)
            del words[i : i + 2]
    return "payload " + " ".join(words)


def _trials(root: Path, trials: int, seed: int) -> dict[str, Any]:
    """``payload trials run --n N --seed S --workers 1 --out runs/campaign`` in the point's
    project: its summary (written into that folder)."""
    from payload.project import Project, provenance
    from payload.trials.campaign import run_campaign, runner_trial_fn, write_summary
    from payload.trials.setup_options import RUN_SETTINGS
    from payload.trials.sources import trial_setup
    from payload.trials.summary import campaign_title

    project = Project.at(root)
    out = root / "runs" / "campaign"
    setup = trial_setup()
    seeds = list(range(seed, seed + trials))
    t0 = time.perf_counter()
    trial = runner_trial_fn("synthetic", project.root, **{k: setup[k] for k in RUN_SETTINGS})
    results = run_campaign(trial, seeds, out, workers=1, progress=False)
    run = {
        "workers": 1,
        "scheduler": None,
        "wall_s": time.perf_counter() - t0,
        "trial_wall_s": float(sum(r.get("wall_s") or 0.0 for r in results)),
    }
    title = campaign_title(trials, setup)
    # a trial that raised counts as a failure in the summary, as in the command's JSON
    return write_summary(results, out, title=title, run=run, provenance=provenance(project))


def _analyse(
    root: Path, params: dict[str, float], samples: int, seed: int, trials: int
) -> dict[str, Any]:
    result = {**_empty(params, None, valid=True), "project": str(root)}
    try:
        _build(root)
    except PayloadError as exc:  # the design validates but its solids or files cannot be made
        return {**result, "valid": False, "error": f"build: {_first_line(exc)}"}
    reports = _Reports(root, samples, seed)
    try:
        env = reports.envelope()
    except PayloadError as exc:
        return {**result, "valid": False, "error": f"report envelope: {_first_line(exc)}"}
    result.update(
        fits=bool(env["fits"]),
        passed=bool(env["passed"]),
        min_clearance_mm=env["min_clearance_mm"],
        min_self_clearance_mm=env["min_self_clearance_mm"],
        failures=env["failures"],
    )
    try:
        reach = reports.reach()
    except PayloadError as exc:
        return {**result, "error": f"report reach: {_first_line(exc)}"}
    result.update(
        reach_passed=reach.get("passed"),
        below_vehicle_mm=reach["below_vehicle_mm"],
        span_max_mm={p: reach["pairs"][p]["span_max_mm"] for p in ("L", "R")},
        span_min_mm={p: reach["pairs"][p]["span_min_mm"] for p in ("L", "R")},
    )
    if trials:
        try:
            summary = _trials(root, trials, seed)
        except PayloadError as exc:
            return {**result, "error": f"trials run: {_first_line(exc)}"}
        raised = [t for t in summary["trials"] if t.get("error")]
        result["trials"] = {
            "n": int(summary["n"]),
            "success": int(summary["success"]),
            "rms_mm_median": summary["rms_mm"]["median"],
            "duration_s_median": summary["duration_s"]["median"],
            "errors": len(raised),
        }
        if raised:  # a trial that raised, not one that ran and failed: as `trials run` says
            result["error"] = (
                f"trials run: {len(raised)} of {len(summary['trials'])} trial(s) raised an "
                f"error (first: {_first_line(raised[0]['error'])}; tracebacks in "
                "runs/campaign/summary.json)"
            )
    return result


__all__ = ["POINT_FIELDS", "point_commands", "run_point"]
