"""``payload report envelope`` and ``payload report reach``."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from payload.cliutil import CheckFailed, command_project, emit_json

if TYPE_CHECKING:
    from payload.design.params import Design
    from payload.envelope.fit import EnvelopeAnalysis
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.vehicle import Vehicle
    from payload.project import Project

DEFAULT_SAMPLES = 100_000


def _project(args: argparse.Namespace) -> Project:

    return command_project(args, args.design)


def _design_path(args: argparse.Namespace) -> Path:
    return Path(args.design) if args.design else _project(args).design_path


def _out_dir(args: argparse.Namespace) -> Path:
    """``--out``, else the project's ``analyses/``."""
    return Path(args.out) if args.out else _project(args).analyses_dir


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


def _cmd_envelope(args: argparse.Namespace) -> int:
    from payload.envelope.fit import analyse_envelope
    from payload.envelope.report import envelope_json, write_envelope

    t0 = time.perf_counter()
    _project(args)
    _, vehicle, geom = _load(args)
    with _progress(not args.json and sys.stderr.isatty()) as progress:
        analysis = analyse_envelope(geom, vehicle, search=args.search, progress=progress)
    analysis.seconds = time.perf_counter() - t0
    record = _recorder(args)
    paths = write_envelope(
        geom, analysis, _out_dir(args), _command(args, "envelope"), record, force=args.force
    )
    if args.json:
        emit_json(_stdout_json(args, record(envelope_json(analysis))))
    else:
        _print_envelope(analysis, paths)
    if not analysis.passed:
        failures = analysis.given.failures()
        more = f" (+{len(failures) - 3} more)" if len(failures) > 3 else ""
        raise CheckFailed("stowed payload: " + "; ".join(failures[:3]) + more)
    return 0


def _print_envelope(analysis: EnvelopeAnalysis, paths: dict[str, Path]) -> None:
    g = analysis.given
    t = g.tightest
    print(f"assumption: {analysis.vehicle.assumption}")
    if g.fits:
        print(
            f"fits: every part inside; min clearance {t.clearance * 1e3:.2f} mm "
            f"({t.name}, {t.wall} wall)"
        )
    for f in g.failures():
        print(f"FAIL: {f}")
    if analysis.search is not None and analysis.suggested is not None:
        s, c = analysis.search, analysis.suggested
        fing = ", ".join(f"{v:.4f}" for v in s.finger)
        print(
            f"stowed-posture search: finger [{fing}] rad -> min clearance "
            f"{s.clearance * 1e3:.2f} mm ({s.limited_by}); {'passes' if c.passed else 'fails'}"
        )
    _print_written(paths)


def _print_written(paths: dict[str, Path]) -> None:
    if set(paths) == {"timing"}:
        print(f"report unchanged (figures as committed); timings in {paths['timing']}")
    else:
        print("wrote " + ", ".join(str(p) for p in paths.values()))


def _cmd_reach(args: argparse.Namespace) -> int:
    from payload.envelope.reach import CTB_FEATURES, GraspFeature, ReachError, analyse_reach
    from payload.envelope.report import reach_json, write_reach

    t0 = time.perf_counter()
    _project(args)
    if args.samples < 1000:
        raise ReachError(f"--samples must be at least 1000 (got {args.samples})")
    if args.seed < 0:
        raise ReachError(f"--seed must not be negative (got {args.seed})")
    if args.workers is not None and args.workers < 1:
        raise ReachError(f"--workers must be at least 1 (got {args.workers})")
    features = list(CTB_FEATURES)
    for t in args.thickness or ():
        if not t >= 0 or t > 1.0:
            raise ReachError(f"--thickness must be between 0 and 1 m (got {t})")
        features.append(GraspFeature(f"given thickness {t * 1e3:.1f} mm", t, "command line"))
    _, vehicle, geom = _load(args)
    with _progress(not args.json and sys.stderr.isatty()) as progress:
        analysis = analyse_reach(
            geom,
            vehicle,
            samples=args.samples,
            seed=args.seed,
            features=features,
            workers=args.workers,
            progress=progress,
        )
    record = _recorder(args)
    command = _command(args, "reach")
    paths = write_reach(
        geom, analysis, _out_dir(args), command, t_start=t0, record=record, force=args.force
    )
    if args.json:
        emit_json(_stdout_json(args, record(reach_json(analysis))))
    else:
        p = {x.name: x for x in analysis.pairs}
        print(f"assumption: {analysis.vehicle.assumption}")
        print(
            f"{analysis.samples:,} samples in {analysis.seconds:.1f} s; fingertips reach "
            f"{analysis.below_vehicle * 1e3:.1f} mm below the vehicle; self-collision-free "
            f"{analysis.collision_free_fraction:.1%}"
        )
        for name, pr in p.items():
            closes = [g.feature.name for g in pr.grasps if g.closes]
            print(
                f"pair {name}: span {pr.span_min * 1e3:.1f} .. {pr.span.maximum * 1e3:.1f} mm; "
                f"closes on: {', '.join(closes) if closes else 'nothing checked'}"
            )
        print(
            f"rail spacing {analysis.rail_spacing[0] * 1e3:.1f} .. "
            f"{analysis.rail_spacing[1] * 1e3:.1f} mm"
        )
        _print_written(paths)
    return 0


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from exc


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``report envelope`` and ``report reach`` to the shared ``report`` group."""
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
        "--force", action="store_true", help="replace a report whose figures changed"
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
    p.set_defaults(func=_cmd_envelope)

    p = groups["report"].add_parser(
        "reach",
        parents=[common],
        help="fingertip workspaces, pair spans, rail spacing, CTB grasp check",
    )
    p.add_argument(
        "--samples",
        type=_integer,
        default=DEFAULT_SAMPLES,
        help=f"sampled configurations (default {DEFAULT_SAMPLES:,})",
    )
    p.add_argument("--seed", type=_integer, default=0, help="random seed (default 0)")
    p.add_argument(
        "--thickness",
        nargs="+",
        type=float,
        metavar="T",
        help="extra thicknesses for the grasp check [m]",
    )
    p.add_argument(
        "--workers",
        type=_integer,
        default=None,
        help="processes for the collision checks (default: up to 2)",
    )
    p.set_defaults(func=_cmd_reach)


__all__ = ["register"]
