"""``payload report envelope``, ``payload report reach`` and ``payload report all``."""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from payload.cliutil import CheckFailed, command_project, emit_json, out_folder

if TYPE_CHECKING:
    from payload.design.params import Design
    from payload.envelope.fit import EnvelopeAnalysis
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.grasp import GraspFeature
    from payload.envelope.reach import ReachAnalysis
    from payload.envelope.vehicle import Vehicle
    from payload.project import Project

DEFAULT_SAMPLES = 100_000
BENCH_CHECK_SAMPLES = 10_000
"""``payload bench reach``: the samples both checks run on, by default."""
BENCH_RUNS = 3
"""``payload bench reach``: the timed reports, by default."""


def _project(args: argparse.Namespace) -> Project:

    return command_project(args, args.design)


def _design_path(args: argparse.Namespace) -> Path:
    return Path(args.design).expanduser() if args.design else _project(args).design_path


def _out_dir(args: argparse.Namespace) -> Path:
    """``--out``, else the project's ``analyses/`` when the design is the project's own: a
    report follows its design, so another design's (``--design F``, F not the project's
    ``cad/design.toml``) needs an ``--out`` and never replaces the project's report."""
    out = out_folder(args.out)
    if out is not None:
        return out
    project = _project(args)
    if args.design and Path(args.design).expanduser().resolve() != project.design_path.resolve():
        from payload.envelope.vehicle import load_design_and_vehicle
        from payload.errors import PayloadError

        load_design_and_vehicle(Path(args.design))  # a bad file says what is wrong with it
        raise PayloadError(
            f"--design {args.design} is not the project's design ({project.design_path}): "
            f"its report would replace the project's own in {project.analyses_dir}; give "
            "--out DIR"
        )
    return project.analyses_dir


def _recorder(args: argparse.Namespace) -> Callable[[dict[str, Any]], dict[str, Any]]:
    """Adds ``provenance`` (what the report was computed from) to a report's JSON. The
    files inside the project omit the project's absolute path; stdout adds ``project``."""
    from payload.project import provenance

    prov = provenance(_project(args), _design_path(args))
    prov.pop("project")
    return lambda data: {**data, "provenance": prov}


def _stdout_json(args: argparse.Namespace, data: dict[str, Any]) -> dict[str, Any]:
    return {**data, "project": str(_project(args).root)}


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

    project = _project(args)
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
    _models_follow(args)
    _, vehicle, geom = _load(args)
    search = True if args.write_stowed and args.search is None else args.search
    with _progress(not args.json and sys.stderr.isatty()) as progress:
        analysis = analyse_envelope(geom, vehicle, search=search, progress=progress)
    lines = [_search_line(analysis)] if analysis.search is not None else []
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


def _cmd_envelope(args: argparse.Namespace) -> int:
    from payload.envelope.report import envelope_json
    from payload.envelope.verdict import envelope_verdict

    analysis, paths, lines = run_envelope(args)
    if args.json:
        emit_json(_stdout_json(args, _recorder(args)(envelope_json(analysis))))
    else:
        print(envelope_verdict(analysis))
        print(f"assumption: {analysis.vehicle.assumption}")
        for line in [*lines, *written_lines(paths, "envelope")]:
            print(line)
    if not analysis.passed:
        failures = analysis.given.failures()
        more = f" (+{len(failures) - 3} more)" if len(failures) > 3 else ""
        raise CheckFailed("stowed payload: " + "; ".join(failures[:3]) + more)
    return 0


def _search_line(analysis: EnvelopeAnalysis) -> str:
    s, c = analysis.search, analysis.suggested
    assert s is not None and c is not None
    fing = ", ".join(f"{v:.4f}" for v in s.finger)
    return (
        f"stowed-posture search: finger [{fing}] rad -> min clearance "
        f"{s.clearance * 1e3:.2f} mm ({s.limited_by}); {'passes' if c.passed else 'fails'}"
    )


def _write_stowed(args: argparse.Namespace, analysis: EnvelopeAnalysis) -> str:
    """Write the search's proposed finger posture into the design's ``[stowed]`` table
    (only that value and its comment change); returns the line to print."""
    from payload.design.edit import set_in_text
    from payload.safeio import replace_file

    s, c = analysis.search, analysis.suggested
    assert s is not None and c is not None
    path = _design_path(args)
    if not c.passed:
        return f"not written into {path}: the proposed posture fails too"
    finger = [round(v, 4) + 0.0 for v in s.finger]  # + 0.0: no "-0.0" in the file
    comment = (
        "written by `payload report envelope --write-stowed` (stowed-posture search, "
        f"min clearance {s.clearance * 1e3:.2f} mm)"
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

    if set(paths) == {"timing"}:
        return [f"report unchanged (figures as before); timings in {paths['timing']}"]
    lines = []
    if "prev" in paths:
        before = json.loads(paths["prev"].read_text())
        lines.append(headline_changes(stem, before, json.loads(paths["json"].read_text())))
    return [*lines, "wrote " + ", ".join(str(p) for p in paths.values())]


def _check_reach_args(args: argparse.Namespace) -> None:
    """Bad numbers raise :class:`ReachError` (exit 2)."""
    from payload.envelope.pairs import MIN_SAMPLES, ReachError

    if args.samples < MIN_SAMPLES:
        raise ReachError(f"--samples must be at least {MIN_SAMPLES} (got {args.samples})")
    if args.seed < 0:
        raise ReachError(f"--seed must not be negative (got {args.seed})")
    if args.workers is not None and args.workers < 1:
        raise ReachError(f"--workers must be at least 1 (got {args.workers})")
    for t in args.thickness or ():
        if not t >= 0 or t > 1.0:
            raise ReachError(f"--thickness must be between 0 and 1 m (got {t})")


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
    _project(args)
    _check_reach_args(args)
    _out_dir(args)  # an --out that cannot take the report says so before the sampling
    _models_follow(args)
    _, vehicle, geom = _load(args)
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


def reach_lines(analysis: ReachAnalysis) -> list[str]:
    """The reach report's figures as terminal lines (after its verdict)."""
    lines = [
        f"assumption: {analysis.vehicle.assumption}",
        f"{analysis.samples:,} samples in {analysis.seconds:.1f} s; fingertips reach "
        f"{analysis.below_vehicle * 1e3:.1f} mm below the vehicle; self-collision-free "
        f"{analysis.collision_free_fraction:.1%}",
    ]
    for pr in analysis.pairs:
        closes = [g.feature.name for g in pr.grasps if g.closes]
        lines.append(
            f"pair {pr.name}: span {pr.span_min * 1e3:.1f} .. {pr.span.maximum * 1e3:.1f} mm; "
            f"closes on: {', '.join(closes) if closes else 'nothing checked'}"
        )
    lines.append(
        f"rail spacing {analysis.rail_spacing[0] * 1e3:.1f} .. "
        f"{analysis.rail_spacing[1] * 1e3:.1f} mm"
    )
    return lines


def _cmd_reach(args: argparse.Namespace) -> int:
    analysis, paths = run_reach(args)  # before the imports below: see run_reach
    from payload.envelope.report import reach_json
    from payload.envelope.verdict import reach_passed, reach_verdict

    if args.json:
        emit_json(_stdout_json(args, _recorder(args)(reach_json(analysis))))
    else:
        print(reach_verdict(analysis))
        for line in [*reach_lines(analysis), *written_lines(paths, "reach")]:
            print(line)
    if not reach_passed(analysis):
        raise CheckFailed("reach: " + reach_verdict(analysis).split("FAILS: ", 1)[1])
    return 0


def _all_verdict(envelope: EnvelopeAnalysis, reach: ReachAnalysis) -> str:
    """The one verdict line: ``verdict: passes: ...`` or ``verdict: FAILS: ...``."""
    from payload.envelope.verdict import envelope_verdict, reach_passed, reach_verdict

    env_ok, reach_ok = envelope.passed, reach_passed(reach)
    if env_ok and reach_ok:
        tight = envelope.given.tightest
        thinnest = {
            p.name: min(g.feature.thickness for g in p.grasps if g.closes) for p in reach.pairs
        }
        closes = ", ".join(f"{name} down to {t * 1e3:.1f} mm" for name, t in thinnest.items())
        return (
            f"verdict: passes: the stowed payload fits (min clearance "
            f"{tight.clearance * 1e3:.2f} mm, {tight.name}); every pair closes on a CTB "
            f"feature ({closes})"
        )
    failing = [] if env_ok else [f"stowed: {envelope_verdict(envelope).split(': ', 2)[2]}"]
    if not reach_ok:
        failing.append(f"reach: {reach_verdict(reach).split(': ', 2)[2]}")
    return "verdict: FAILS: " + "; ".join(failing)


def _cmd_all(args: argparse.Namespace) -> int:
    """``payload report all``: the models, the envelope, the reach and the design summary
    in one run, led by one verdict line; 0 when the design passes, else raises.

    Raises:
        CheckFailed: The stowed payload or the grasp check fails (exit 1).
    """
    from payload.design import load_design, models_follow_design
    from payload.design.summary import print_summary, summarize
    from payload.envelope.report import envelope_json, reach_json
    from payload.envelope.verdict import (
        envelope_verdict,
        reach_passed,
        reach_verdict,
    )

    project = _project(args)
    _check_reach_args(args)  # bad numbers: exit 2 before any work
    rebuilt = models_follow_design(project.design_path, project.root, json=args.json)
    envelope, env_paths, env_lines = run_envelope(args)
    reach, reach_paths = run_reach(args)
    design = load_design(_design_path(args))
    summary = summarize(design)
    env_ok, reach_ok = envelope.passed, reach_passed(reach)
    verdict = _all_verdict(envelope, reach)
    if args.json:
        record = _recorder(args)
        data: dict[str, Any] = {
            "passed": env_ok and reach_ok,
            "verdict": verdict.removeprefix("verdict: "),
            "models": {"rebuilt": rebuilt},
            "envelope": record(envelope_json(envelope)),
            "reach": record(reach_json(reach)),
            "summary": summary,
        }
        emit_json(_stdout_json(args, data))
    else:
        print(verdict)
        where = project.relative(project.design_path)
        print(f"models: {'rebuilt (above)' if rebuilt else 'match ' + where}")
        print("-- envelope")
        print(envelope_verdict(envelope))
        for line in [*env_lines, *written_lines(env_paths, "envelope")]:
            print(line)
        print("-- reach")
        print(reach_verdict(reach))
        for line in [
            *reach_lines(reach),
            *written_lines(reach_paths, "reach"),
        ]:
            print(line)
        print("-- design summary")
        print_summary(summary)
    if not (env_ok and reach_ok):
        raise CheckFailed(verdict.removeprefix("verdict: FAILS: "))
    return 0


def _cmd_bench_reach(args: argparse.Namespace) -> int:
    """``payload bench reach``: the compiled check against MuJoCo's collision, same run;
    ``report reach`` timed in a fresh interpreter."""
    from payload.envelope.bench import run_reach_bench
    from payload.envelope.pairs import ReachError

    _check_reach_args(args)  # --samples, --seed
    if args.check_samples < 1:
        raise ReachError(f"--check-samples must be at least 1 (got {args.check_samples})")
    if args.runs < 1:
        raise ReachError(f"--runs must be at least 1 (got {args.runs})")
    project = _project(args)
    _models_follow(args)
    _, vehicle, geom = _load(args)
    r = run_reach_bench(
        geom, vehicle, project.root, project.analyses_dir, samples=args.samples,
        check_samples=args.check_samples, runs=args.runs, seed=args.seed,
        aim_samples=DEFAULT_SAMPLES,
    )  # fmt: skip
    if args.json:
        emit_json(r)
        return 0
    same = "identical" if r["identical"] else (
        f"{r['rows_only_overlap']} only in the compiled check, "
        f"{r['rows_only_mujoco']} only in MuJoCo's"
    )  # fmt: skip
    print(
        f"reach check, {r['check_samples']:,} samples, one process: compiled "
        f"{r['overlap_us']:.1f} us a sample, MuJoCo's mj_collision {r['mujoco_us']:.1f} us "
        f"({r['speedup']:.1f}x); rows {same} ({r['rows']:,})"
    )
    walls = ", ".join(f"{w:.2f}" for w in r["report_wall_s"])
    aim = {
        True: f"every run under the aim of {r['aim_s']:g} s",
        False: f"NOT every run under the aim of {r['aim_s']:g} s",
        None: f"the aim of {r['aim_s']:g} s is for {r['aim_samples']:,} samples",
    }[r["within_aim"]]
    print(
        f"report reach --samples {r['samples']}: {walls} s wall (median "
        f"{r['report_wall_median_s']:.2f} s; {aim}), CPU "
        f"{statistics.median(r['report_cpu_s']):.2f} s (median, workers included); "
        f"load average {r['load'][0]} -> {r['load'][1]}"
    )
    return 0


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from exc


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``report envelope``, ``report reach`` and ``report all`` to the shared
    ``report`` group."""
    del sub
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--design", help="design TOML (default: cad/design.toml); may hold a [vehicle] table"
    )
    common.add_argument(
        "--bay-size",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        help="replace the assumed bay envelope (two lower bays combined) [m]",
    )
    common.add_argument("--json", action="store_true", help="print one JSON object")
    common.add_argument("--out", help="output directory (default: analyses/)")
    common.add_argument(
        "--force",
        action="store_true",
        help="rewrite the report even when its figures did not change (a report whose "
        "figures changed is always replaced: reports follow the design)",
    )

    p = groups["report"].add_parser(
        "envelope",
        parents=[common],
        help="stowed fit in the two lower bays, self-collision, deployment sweep",
    )
    search = p.add_mutually_exclusive_group()
    search.add_argument(
        "--search",
        action="store_true",
        default=None,
        help="run the stowed-posture search even when the given posture passes",
    )
    search.add_argument(
        "--no-search",
        dest="search",
        action="store_false",
        help="never run the stowed-posture search",
    )
    p.add_argument(
        "--write-stowed",
        action="store_true",
        help="write the stowed-posture search's proposed posture into the design's "
        "[stowed] table (a comment says so), then report on the edited design",
    )
    p.set_defaults(func=_cmd_envelope)

    sampling = argparse.ArgumentParser(add_help=False)
    sampling.add_argument(
        "--samples",
        type=_integer,
        default=DEFAULT_SAMPLES,
        help=f"sampled configurations (default {DEFAULT_SAMPLES:,})",
    )
    sampling.add_argument("--seed", type=_integer, default=0, help="random seed (default 0)")
    sampling.add_argument(
        "--thickness",
        nargs="+",
        type=float,
        metavar="T",
        help="extra thicknesses for the grasp check [m]",
    )
    sampling.add_argument(
        "--workers",
        type=_integer,
        default=None,
        help="processes for the collision checks (default: up to 2)",
    )
    p = groups["report"].add_parser(
        "reach",
        parents=[common, sampling],
        help="fingertip workspaces, pair spans, rail spacing, CTB grasp check",
    )
    p.set_defaults(func=_cmd_reach)

    p = groups["report"].add_parser(
        "all",
        parents=[common, sampling],
        help="models, envelope, reach and design summary in one run, one verdict line",
    )
    p.set_defaults(func=_cmd_all, search=None, write_stowed=False)

    p = groups["bench"].add_parser(
        "reach", help="the reach check against MuJoCo's collision, same run; the report's time"
    )
    p.add_argument(
        "--samples",
        type=_integer,
        default=DEFAULT_SAMPLES,
        help=f"samples of the timed report (default {DEFAULT_SAMPLES:,})",
    )
    p.add_argument(
        "--check-samples",
        type=_integer,
        default=BENCH_CHECK_SAMPLES,
        help=f"samples both checks run on (default {BENCH_CHECK_SAMPLES:,})",
    )
    p.add_argument(
        "--runs", type=_integer, default=BENCH_RUNS, help=f"timed reports (default {BENCH_RUNS})"
    )
    p.add_argument(
        "--seed",
        type=_integer,
        default=0,
        help="random seed of the samples both checks run on (default 0; the timed report "
        "runs at its default seed, as users run it)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_bench_reach, design=None, bay_size=None, workers=None, thickness=None)


__all__ = ["reach_lines", "register", "run_envelope", "run_reach", "written_lines"]
