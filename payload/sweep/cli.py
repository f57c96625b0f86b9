"""``payload sweep``: a design sweep on Dask (contract in docs/cli.md and docs/design.md)."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from payload.cliutil import (
    CheckFailed,
    command_project,
    emit_json,
    out_folder,
    results_folder,
)
from payload.errors import first_of
from payload.folders import (
    SWEEP_FILES,
    held,
    other_results,
)
from payload.project import DESIGN_FILE
from payload.sweep.grid import SweepError, parse_set
from payload.sweep.run import DEFAULT_SAMPLES
from payload.trials.setup_options import seed_problem


def _progress(enabled: bool, total: int) -> Any:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("sweep"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[note]}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
        disable=not enabled,
    )


def _cmd_sweep(args: argparse.Namespace) -> int:
    from payload.envelope.pairs import check_reach_numbers
    from payload.project import provenance
    from payload.sweep.report import sweep_json, sweep_markdown, write_sweep
    from payload.sweep.run import plan, run_points

    axes = [parse_set(s) for s in args.set]
    if args.trials < 0:
        raise SweepError(f"--trials must be >= 0, got {args.trials}")
    check_reach_numbers(args.samples, args.seed, args.workers, SweepError)
    if args.trials and (problem := seed_problem(args.seed, args.trials)) is not None:
        raise SweepError(f"--seed {problem}")  # each point's trials: seeds S to S + N - 1
    from payload.trials.cluster import check_scheduler

    check_scheduler(args.scheduler, SweepError)  # before any folder is made for the sweep
    # a sweep never writes into a file, nor among a trial's, a campaign's, the design
    # reports' or a design project's files (its points are projects of their own)
    out_folder(args.out, holding=(*other_results("sweep"), DESIGN_FILE))
    earlier = held(Path(args.out), SWEEP_FILES) if args.out else []
    if earlier:  # an earlier sweep's (or a report of the same name)
        raise SweepError(
            f"--out {args.out}: already holds {', '.join(earlier)}; choose another folder "
            "(results are never overwritten)"
        )
    project = command_project(args)
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=args.json)
    with results_folder(args.out, project, "sweep", resolve=True) as out:
        # the folder made for the sweep is removed again if it fails while still empty
        # (bad input found in plan, a scheduler that does not answer)
        points = plan(project, axes, out)
        workers = args.workers or max(1, min(len(points), os.cpu_count() or 1))
        t0 = time.perf_counter()
        with _progress(not args.json, len(points)) as bar:
            task = bar.add_task("points", total=len(points), note="")
            # counted by the envelope check as a whole (the table's "envelope check"): a
            # point that fits the bays can still fail it (a self-collision, the deployment)
            counts = {"pass": 0, "fail": 0, "invalid": 0}

            lines = not args.json and not sys.stderr.isatty()  # no bar drawn: a line a point

            def advance(result: dict[str, Any]) -> None:
                if not result["valid"]:
                    kind, said = "invalid", "invalid"
                else:
                    kind = "pass" if result.get("passed") else "fail"
                    said = "envelope check passes" if kind == "pass" else "envelope check FAILS"
                    failed = result.get("failures") or []
                    if kind == "fail" and failed:  # what failed (a fit can fail it too)
                        said += f": {first_of(failed, 1)}"
                    elif kind == "fail":
                        said += " (does not fit the bays)" if not result["fits"] else ""
                counts[kind] += 1
                note = ", ".join(f"{v} {k}" for k, v in counts.items() if v)
                bar.update(task, advance=1, note=note)
                if lines:  # the points finish in any order: each named by its folder
                    params = ", ".join(f"{k}={v:g}" for k, v in result["params"].items())
                    done = sum(counts.values())
                    print(
                        f"{done}/{len(points)} done: {Path(result['project']).name} ({params}): "
                        f"{said}",
                        file=sys.stderr,
                        flush=True,
                    )

            results = run_points(
                points,
                samples=args.samples,
                seed=args.seed,
                trials=args.trials,
                workers=workers,
                scheduler=args.scheduler,
                on_result=advance,
            )
        run = {
            "workers": None if args.scheduler else workers,
            "scheduler": args.scheduler,
            "samples": args.samples,
            "seed": args.seed,
            "trials_per_point": args.trials,
            "wall_s": round(time.perf_counter() - t0, 2),
        }
        data = sweep_json([a.key for a in axes], results, provenance=provenance(project), run=run)
        command = "payload sweep " + " ".join(
            [*(f"--set {shlex.quote(s)}" for s in args.set)]
            + ([f"--trials {args.trials}"] if args.trials else [])
            + ([f"--samples {args.samples}"] if args.samples != DEFAULT_SAMPLES else [])
            + ([f"--seed {args.seed}"] if args.seed else [])
            + [f"--out {args.out or out}"]
        )
        paths = write_sweep(data, out, command)
    if args.json:
        emit_json({**data, "project": str(project.root), "out_dir": str(out)})
    else:
        sys.stdout.write(sweep_markdown(data, command, []))
        print(f"wrote {paths['md']}, {paths['json']} and {len(paths) - 2} plot(s)")
    raised = [p for p in results if (p.get("trials") or {}).get("errors")]
    if raised:  # written and reported; then exit 1, as `payload trials run` does
        names = ", ".join(Path(p["project"]).name for p in raised)
        raise CheckFailed(f"trials raised an error in {names}: {raised[0]['error']}")
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``payload sweep``."""
    del groups
    p = sub.add_parser(
        "sweep",
        help="a design sweep on Dask: every combination of --set values, each a project",
    )
    p.add_argument(
        "--set",
        action="append",
        required=True,
        metavar="KEY=V1,V2|A:B:N",
        help="a dotted design key and its values (list, or N values from A to B); repeat",
    )
    p.add_argument("--trials", type=int, default=0, help="trials per point (default 0)")
    p.add_argument(
        "--samples",
        type=int,
        default=DEFAULT_SAMPLES,
        help=f"reach samples per point (default {DEFAULT_SAMPLES:,})",
    )
    p.add_argument("--seed", type=int, default=0, help="reach and trial seed (default 0)")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=int,
        default=None,
        help="local Dask worker processes (default: one per core, at most one per point)",
    )
    where.add_argument("--scheduler", help="existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--out",
        help="sweep folder, one project per point (default: a new runs/sweep-NNNN in the project)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_sweep)


__all__ = ["register"]
