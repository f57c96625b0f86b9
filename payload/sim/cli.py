"""Command line of the simulator: ``payload bench sim``."""

from __future__ import annotations

import argparse

from payload.cliutil import command_project, emit_json, load_average
from payload.sim.vehicle import (
    DEFAULT_FLIGHT_MODE,
    DEFAULT_PROPULSION,
    FLIGHT_MODES,
    PROPULSION_MODELS,
)


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from payload.sim.bench import run_bench
    from payload.sim.world import CTB_SIZES, SimError, WorldConfig

    if args.ctb not in (*CTB_SIZES, "none"):
        raise SimError(
            f"--ctb: unknown size {args.ctb!r} (expected {', '.join(CTB_SIZES)} or none)"
        )
    project = command_project(args)
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=args.json)
    config = WorldConfig.for_project(project, ctb=None if args.ctb == "none" else args.ctb)
    console = Console(stderr=True)
    with Progress(
        TextColumn("simulating"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=args.no_progress or not console.is_terminal,  # no bar, no stray newline
    ) as bar:
        task = bar.add_task("sim", total=args.seconds)
        result = run_bench(
            args.seconds,
            config=config,
            flight_mode=args.flight_mode,
            pin=args.pin,
            progress=lambda t: bar.update(task, completed=t),
            propulsion=args.propulsion,
        )
    if args.json:
        emit_json(
            {**result.as_dict(), "project": str(project.root), "load_average": load_average()}
        )
        return 0
    print(
        f"{result.sim_seconds:.1f} s simulated in {result.wall_seconds:.2f} s wall: "
        f"real-time factor {result.realtime_factor:.1f} "
        f"({result.cpu_realtime_factor:.1f} per CPU second; physics "
        f"{result.physics_hz:.0f} Hz, control {result.control_hz:.0f} Hz, "
        f"{'CPU ' + str(result.pinned_cpu) if result.pinned_cpu is not None else 'unpinned'})"
    )
    print(
        f"flight mode {result.flight_mode}, propulsion {result.propulsion}, CTB {result.ctb} "
        f"(x acceleration bound {result.accel_max[0]:.4f} m/s^2): opposing contact "
        f"{100 * result.opposing_contact_fraction:.1f} % of the flight, vehicle moved "
        f"{result.vehicle_distance:.2f} m, CTB {result.ctb_displacement:.2f} m, now in "
        f"{result.module}; MuJoCo warnings: {result.warnings or 'none'}"
    )
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``payload bench sim``."""
    p = groups["bench"].add_parser(
        "sim", help="real-time factor of the full CTB scene under the 50 Hz loop"
    )
    p.add_argument("--seconds", type=float, default=60.0, help="simulated seconds (default 60)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--flight-mode",
        choices=sorted(FLIGHT_MODES),
        default=DEFAULT_FLIGHT_MODE,
        help=f"Astrobee flight mode (default {DEFAULT_FLIGHT_MODE})",
    )
    p.add_argument("--ctb", default="single", help="CTB model: half, single, double, rigid or none")
    p.add_argument(
        "--propulsion",
        choices=PROPULSION_MODELS,
        default=DEFAULT_PROPULSION,
        help=f"vehicle propulsion model (default {DEFAULT_PROPULSION})",
    )
    p.add_argument("--pin", action="store_true", help="restrict the run to one CPU core (Linux)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_bench_sim)
