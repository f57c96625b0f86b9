"""What ``payload report envelope`` and ``payload report reach`` run, from the parsed
arguments to the written report: the project, the design and the output folder, the
report's provenance, the loaded geometry, the progress bar and the models that follow the
design, then the analysis, its report and the lines a command prints after its verdict.

The commands themselves (their options, verdicts, JSON and exit codes) are
:mod:`payload.envelope.cli`, which re-exports :func:`run_envelope`, :func:`run_reach`,
:func:`reach_lines` and :func:`written_lines`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from payload.cliutil import command_project, out_folder
from payload.design.slip import SLIP_FACTOR
from payload.envelope.report_files import report_paths
from payload.folders import other_results
from payload.safeio import cannot_write_in

if TYPE_CHECKING:
    from payload.design.params import Design
    from payload.envelope.fit import EnvelopeAnalysis
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.grasp import GraspFeature
    from payload.envelope.reach import ReachAnalysis
    from payload.envelope.vehicle import Vehicle
    from payload.project import Project


def _project(args: argparse.Namespace) -> Project:

    return command_project(args, args.design)


def _project_or_none(args: argparse.Namespace) -> Project | None:
    """The command's project, or None for a design file in no project (``--design F``)
    reported into ``--out DIR`` from a folder in no project: such a report needs none
    (its models are not on disk to follow, its provenance names the file)."""
    import os

    from payload.project import ENV_VAR, ProjectError, project_of

    try:
        return _project(args)
    except ProjectError:
        named = getattr(args, "project", None) is not None or os.environ.get(ENV_VAR)
        if named:  # a --project or PAYLOAD_PROJECT that is wrong says so, as everywhere
            raise
        loose = args.design and project_of(Path(args.design).expanduser()) is None
        if loose and args.out:
            return None
        if loose:  # the report has no project's analyses/ to go in
            raise ProjectError(
                f"--design {args.design}: in no design project, nor is this folder; give "
                "--out DIR for its report"
            ) from None
        raise


def _design_path(args: argparse.Namespace) -> Path:
    return Path(args.design).expanduser() if args.design else _project(args).design_path


def _provenance_design(args: argparse.Namespace) -> Path:
    """The design file a report's provenance names, absolute (the provenance makes it
    relative to the project when inside it)."""
    return _design_path(args).resolve()


def _out_dir(args: argparse.Namespace) -> Path:
    """``--out``, else the project's ``analyses/`` when the design is the project's own: a
    report follows its design, so another design's (``--design F``, F not the project's
    ``cad/design.toml``) needs an ``--out`` and never replaces the project's report."""
    from payload.errors import PayloadError

    out = out_folder(args.out, holding=other_results("report"))
    project = _project_or_none(args)
    if project is None:  # a design outside any project: its report where --out says
        assert out is not None  # (_project_or_none's None comes with an --out)
        return out
    if out is not None and out.resolve() != project.analyses_dir.resolve():
        return out  # (--out naming the project's analyses/ is the default: checked below)
    if args.design and Path(args.design).expanduser().resolve() != project.design_path.resolve():
        from payload.envelope.vehicle import load_design_and_vehicle

        load_design_and_vehicle(Path(args.design))  # a bad file says what is wrong with it
        raise PayloadError(
            f"--design {args.design} is not the project's design ({project.design_path}): "
            f"its report would replace the project's own in {project.analyses_dir}; give "
            "--out DIR (another folder)"
        )
    analyses = project.analyses_dir
    problem = cannot_write_in(analyses) if analyses.is_dir() else None
    if problem is not None:  # before the analysis, not after it (a traceback)
        raise PayloadError(f"{analyses}: cannot write the report there ({problem}); give --out DIR")
    return analyses


def _recorder(args: argparse.Namespace) -> Callable[[dict[str, Any]], dict[str, Any]]:
    """Adds ``provenance`` (what the report was computed from) to a report's JSON. A
    report in its project's own ``analyses/`` omits the project's absolute path (the folder
    says it); one anywhere else (``--out``) keeps ``project`` (null for a design in no
    project, whose ``design`` is then absolute), so it says what it came from wherever it
    is read; stdout adds ``project``."""
    from payload.envelope.report_files import PROVENANCE_KEY
    from payload.project import provenance

    project = _project_or_none(args)
    prov = provenance(project, _provenance_design(args))
    if project is not None and _out_dir(args).resolve() == project.analyses_dir.resolve():
        prov.pop("project")
    return lambda data: {**data, PROVENANCE_KEY: prov}


def _refuse_foreign_reports(args: argparse.Namespace, *stems: str) -> None:
    """One line (exit 2) before any work when the output folder holds report files that are
    not this command's reports of this design, unless ``--force``: a report follows its
    own design, never replaces another's (or a file of the user's)."""
    from payload.envelope.report_files import foreign_report
    from payload.errors import PayloadError

    if args.force:
        return
    out = _out_dir(args)
    for stem in stems:
        why = foreign_report(out, stem, _design_path(args))
        if why is not None:
            where = f"--out {args.out}" if args.out else str(out)
            raise PayloadError(
                f"{where}: already {why}; pass --force to replace it or choose another --out"
            )


def _stdout_json(args: argparse.Namespace, data: dict[str, Any]) -> dict[str, Any]:
    project = _project_or_none(args)
    return {**data, "project": str(project.root) if project is not None else None}


def _load(args: argparse.Namespace) -> tuple[Design, Vehicle, PayloadGeometry]:
    from payload.design import build_tree
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.vehicle import load_design_and_vehicle, with_bay_size

    design, vehicle = load_design_and_vehicle(_design_path(args))
    if args.bay_size is not None:
        vehicle = with_bay_size(vehicle, args.bay_size)
    return design, vehicle, PayloadGeometry(build_tree(design))


@contextmanager
def _progress(enabled: bool) -> Iterator[Callable[[str, float], None]]:
    """A rich progress bar on stderr; yields ``update(stage, fraction)``."""
    if not enabled:
        yield lambda stage, fraction: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description:<24}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        tasks: dict[str, int] = {}

        def update(stage: str, fraction: float) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=1.0)
            bar.update(tasks[stage], completed=min(max(fraction, 0.0), 1.0))

        yield update


def _command(args: argparse.Namespace, name: str) -> str:
    parts = ["payload report", name]
    if args.design:
        parts.append(f"--design {args.design}")
    if args.bay_size is not None:
        parts.append("--bay-size " + " ".join(f"{v:g}" for v in args.bay_size))
    if name == "reach":
        parts.append(f"--samples {args.samples}")
        if args.seed:
            parts.append(f"--seed {args.seed}")
        if args.thickness:
            parts.append("--thickness " + " ".join(f"{v:g}" for v in args.thickness))
    if name == "envelope" and args.search is not None:
        parts.append("--search" if args.search else "--no-search")
    return " ".join(parts)


def _models_follow(args: argparse.Namespace) -> None:
    """The one rule for stale models (docs/design-loop.md): rebuild them, saying so."""
    from payload.design import models_follow_design

    project = _project_or_none(args)
    if project is None:  # a design file in no project: no models on disk to follow
        return
    models_follow_design(project.design_path, project.root, json=args.json)


def run_envelope(args: argparse.Namespace) -> tuple[EnvelopeAnalysis, dict[str, Path], list[str]]:
    """Analyse the stowed payload (after ``--write-stowed``'s write) and write its report.

    Returns:
        The analysis, the paths written, and the lines to print after the verdict.
    """
    from payload.envelope.fit import analyse_envelope
    from payload.envelope.report import write_envelope
    from payload.errors import PayloadError

    if args.write_stowed and args.search is False:
        raise PayloadError(
            "--write-stowed writes the stowed-posture search's proposal: drop --no-search"
        )
    t0 = time.perf_counter()
    _out_dir(args)  # an --out that cannot take the report says so before the analysis
    _refuse_foreign_reports(args, "envelope")
    _, vehicle, geom = _load(args)  # a bad --bay-size too, before the models are rebuilt
    _models_follow(args)
    search = True if args.write_stowed and args.search is None else args.search
    with _progress(not args.json and sys.stderr.isatty()) as progress:
        analysis = analyse_envelope(geom, vehicle, search=search, progress=progress)
    lines = [_search_line(analysis, args.write_stowed)] if analysis.search is not None else []
    if args.write_stowed:
        written = _write_stowed(args, analysis)
        lines.append(written)
        if written.startswith("wrote"):  # the models, then the report, follow the design
            _models_follow(args)
            _, vehicle, geom = _load(args)
            analysis = analyse_envelope(geom, vehicle, search=False)
    analysis.seconds = time.perf_counter() - t0
    paths = write_envelope(
        geom, analysis, _out_dir(args), _command(args, "envelope"), _recorder(args),
        force=args.force,
    )  # fmt: skip
    return analysis, paths, lines


def _search_line(analysis: EnvelopeAnalysis, writing: bool = False) -> str:
    """The search's line: a proposal, checked like the design's posture; not applied
    unless ``writing`` (``--write-stowed``, whose own line follows), and the verdict above
    is the design's own posture's."""
    from payload.envelope.fit_results import TIGHT_CLEARANCE, clearance_text

    s, c = analysis.search, analysis.suggested
    assert s is not None and c is not None
    fing = ", ".join(f"{round(v, 4) + 0.0:.4f}" for v in s.finger)  # no "-0.0000"
    head = (
        f"stowed-posture search: proposes finger [{fing}] rad, min clearance "
        f"{clearance_text(s.clearance)} ({s.limited_by})"
    )
    if not c.passed:
        return f"{head}; it fails too: {c.failures()[0]}"
    tight = f", tight (under {clearance_text(TIGHT_CLEARANCE)})" if c.tight else ""
    if writing:
        return f"{head}; it passes{tight}"
    return (
        f"{head}; it would pass{tight}; not applied (the verdict above is the design's own "
        "[stowed] posture's): `payload report envelope --write-stowed` writes it into the design"
    )


def _write_stowed(args: argparse.Namespace, analysis: EnvelopeAnalysis) -> str:
    """Write the search's proposed finger posture into the design's ``[stowed]`` table
    (only that value and its comment change); returns the line to print."""
    from payload.design.edit import set_in_text
    from payload.envelope.fit_results import clearance_text
    from payload.safeio import replace_file

    s, c = analysis.search, analysis.suggested
    assert s is not None and c is not None
    path = _design_path(args)
    if not c.passed:
        return f"not written into {path}: the proposed posture fails too"
    finger = [round(v, 4) + 0.0 for v in s.finger]  # + 0.0: no "-0.0" in the file
    comment = (
        "written by `payload report envelope --write-stowed` (stowed-posture search, "
        f"min clearance {clearance_text(s.clearance)})"
    )
    text = path.read_text(encoding="utf-8")
    edited = set_in_text(text, "stowed.finger", finger, comment)
    if edited == text:
        return f"{path} already holds the proposed posture"
    replace_file(path, edited)
    return f"wrote [stowed] finger = {finger} into {path}"


def written_lines(paths: dict[str, Path], stem: str) -> list[str]:
    """What a report wrote: the change of its headline figures, then the files."""
    from payload.envelope.verdict import headline_changes

    if set(paths) == {"timing"}:  # the report's files are there as they were: named
        kept = [k for k in report_paths(paths["timing"].parent, stem) if k != paths["timing"]]
        return [
            f"report unchanged (figures as before): {', '.join(str(k) for k in kept)}; "
            f"timings in {paths['timing']}"
        ]
    lines = []
    if "prev" in paths:
        before = json.loads(paths["prev"].read_text())
        lines.append(headline_changes(stem, before, json.loads(paths["json"].read_text())))
    return [*lines, "wrote " + ", ".join(str(p) for p in paths.values())]


def _check_reach_args(args: argparse.Namespace) -> None:
    """Bad numbers raise :class:`ReachError` (exit 2)."""
    from payload.envelope.pairs import ReachError, check_reach_numbers

    check_reach_numbers(args.samples, args.seed, args.workers)
    for t in args.thickness or ():
        if not t >= 0 or t > 1.0:
            slip = (  # a thickness in mm typed as metres, as the design's values are checked
                f": did you mean {t:g} mm = {t / SLIP_FACTOR:g}?" if 1.0 < t <= SLIP_FACTOR else ""
            )
            raise ReachError(f"--thickness must be between 0 and 1 m, got {t}{slip}")


def _grasp_features(args: argparse.Namespace) -> list[GraspFeature]:
    """The CTB's features and the ``--thickness`` ones (checked by :func:`_check_reach_args`)."""
    from payload.envelope.reach import CTB_FEATURES, GraspFeature

    features = list(CTB_FEATURES)
    for t in args.thickness or ():
        features.append(GraspFeature(f"given thickness {t * 1e3:.1f} mm", t, "command line"))
    return features


def run_reach(args: argparse.Namespace) -> tuple[ReachAnalysis, dict[str, Path]]:
    """Sample the deployed workspace and write the reach report; (analysis, paths).

    The collision check starts in forked workers before the rest of the analysis is
    imported (:mod:`payload.envelope.reach_start`), so that those imports overlap it."""
    from payload.envelope.reach_start import start_check

    t0 = time.perf_counter()
    _project_or_none(args)
    _check_reach_args(args)
    _out_dir(args)  # an --out that cannot take the report says so before the sampling
    _refuse_foreign_reports(args, "reach")
    _, vehicle, geom = _load(args)  # a bad --bay-size too, before the models are rebuilt
    _models_follow(args)
    t0 += _load_check()  # a compile is not the report's time
    with _progress(not args.json and sys.stderr.isatty()) as progress:
        started = start_check(geom, vehicle, args.samples, args.seed, args.workers, progress)
        from payload.envelope.reach import analyse_reach

        analysis = analyse_reach(
            geom,
            vehicle,
            samples=args.samples,
            seed=args.seed,
            features=_grasp_features(args),
            workers=args.workers,
            progress=progress,
            started=started,
        )
    from payload.envelope.report import write_reach

    command = _command(args, "reach")
    paths = write_reach(
        geom, analysis, _out_dir(args), command, t_start=t0, record=_recorder(args),
        force=args.force,
    )  # fmt: skip
    return analysis, paths


COMPILING_AFTER_S = 1.0
"""How long loading the reach check may take before ``report reach`` says what it is
doing."""

COMPILING_LINE = (
    "loading the reach check (Numba compiles it once after its code or Numba changes, "
    "about 5 s) ..."
)
"""What ``report reach`` says on stderr when loading the check takes long: a compile."""


def _load_check() -> float:
    """Load the reach check from Numba's cache, or compile it, before the sampling starts;
    a load that takes :data:`COMPILING_AFTER_S` (a compile: the first run after its code
    changed, seconds of silence otherwise) is said on stderr, never after this returns.
    Returns the seconds such a load took (0 for a quick one), which the report's time
    leaves out."""
    import threading

    from payload.envelope.overlap import compile_check

    lock = threading.Lock()
    state = {"done": False, "said": False}

    def say() -> None:
        with lock:
            if state["done"]:
                return
            state["said"] = True
            print(COMPILING_LINE, file=sys.stderr, flush=True)

    notice = threading.Timer(COMPILING_AFTER_S, say)
    notice.daemon = True
    t = time.perf_counter()
    notice.start()
    try:
        compile_check()
    finally:
        notice.cancel()
        with lock:
            state["done"] = True
    return time.perf_counter() - t if state["said"] else 0.0


def reach_lines(analysis: ReachAnalysis, assumption: bool = True) -> list[str]:
    """The reach report's figures as terminal lines (after its verdict); ``assumption``:
    lead with the vehicle's assumption line (``report all`` says it once for both
    reports)."""
    from payload.envelope.markdown import assumption_line

    depth = analysis.below_vehicle
    lines = [
        *([assumption_line(analysis)] if assumption else []),
        f"{analysis.samples:,} samples in {analysis.seconds:.1f} s; "
        + (
            f"fingertips reach {depth * 1e3:.1f} mm below the vehicle"
            if math.isfinite(depth)
            else "no finger moved free in any sample"
        )
        + f"; self-collision-free {analysis.collision_free_fraction:.1%}",
    ]
    for pr in analysis.pairs:
        closes = [g.feature.name for g in pr.grasps if g.closes]
        lines.append(
            f"pair {pr.name}: span {pr.span_min * 1e3:.1f} .. {pr.span.maximum * 1e3:.1f} mm; "
            + (
                f"closes on: {', '.join(closes)}"
                if closes
                else f"closes on none of the {len(pr.grasps)} features checked"
            )
        )
    lines.append(
        f"rail spacing {analysis.rail_spacing[0] * 1e3:.1f} .. "
        f"{analysis.rail_spacing[1] * 1e3:.1f} mm"
    )
    return lines


__all__ = ["reach_lines", "run_envelope", "run_reach", "written_lines"]
