"""Command line of the trial benches: ``payload bench recorder`` (the recorder's cost and
file size), ``payload bench trial`` (a whole trial's real-time factor, where its time
goes and its overhead over the physics) and ``payload bench start`` (how quickly the
commands start; docs/speed.md)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from payload.cliutil import check_seconds, command_project, emit_json, load_average, out_folder
from payload.errors import RunAborted
from payload.folders import RECORDING, other_results
from payload.trials.setup_options import (
    TrialsCliError,
    _check_physics_dt,
    _physics_dt_argument,
    seed_problem,
)


def _cmd_bench_recorder(args: argparse.Namespace) -> int:
    import tempfile

    import numpy as np

    from payload.schema import CONTROL_DT
    from payload.trials.metrics import compute_metrics
    from payload.trials.recorder import TrialRecorder, random_step, read_recording

    check_seconds("--seconds", args.seconds)
    n = max(2, round(args.seconds / CONTROL_DT))
    rng = np.random.default_rng(0)
    steps = [random_step(rng, k * CONTROL_DT) for k in range(n)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / RECORDING
        per_step = np.empty(n)
        with TrialRecorder(path) as rec:
            for k, step in enumerate(steps):
                t0 = time.perf_counter()
                rec.write(step)
                per_step[k] = time.perf_counter() - t0
        size = path.stat().st_size
        t0 = time.perf_counter()
        recording = read_recording(path)
        read_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        compute_metrics(recording)
        metrics_s = time.perf_counter() - t0
    recorded_s = n * CONTROL_DT
    minutes = recorded_s / 60
    result = {
        "steps": n,
        "recorded_s": recorded_s,
        "write_us_median": float(np.median(per_step) * 1e6),
        "write_us_p99": float(np.quantile(per_step, 0.99) * 1e6),
        "write_budget_fraction": float(np.median(per_step) / CONTROL_DT),
        "file_mb_per_min": size / 1e6 / minutes,
        "read_s_per_min": read_s / minutes,
        "metrics_s": metrics_s,
        "load_average": load_average(),
    }
    if args.json:
        emit_json(result)
    else:
        print(
            f"recorder, {n} steps ({recorded_s:.0f} s at {1 / CONTROL_DT:g} Hz): write "
            f"{result['write_us_median']:.0f} us/step median ({result['write_us_p99']:.0f} us "
            f"p99, {100 * result['write_budget_fraction']:.2f} % of the "
            f"{1e3 * CONTROL_DT:g} ms step), "
            f"{result['file_mb_per_min']:.1f} MB per minute, read "
            f"{result['read_s_per_min']:.2f} s per minute, metrics {1e3 * metrics_s:.1f} ms"
        )
    return 0


def _cmd_bench_trial(args: argparse.Namespace) -> int:
    from payload.trials.bench import run_trial_bench, run_trial_bench_repeated

    if (problem := seed_problem(args.seed)) is not None:
        raise TrialsCliError(f"--seed {problem}")
    # the bench writes a trial: never over one, nor among a campaign's files
    out = out_folder(args.out, holding=other_results())
    check_seconds("--seconds", args.seconds, cap=True)
    if args.repeat < 1:
        raise TrialsCliError(f"--repeat must be >= 1, got {args.repeat}")
    if args.repeat > 1 and out is not None:
        raise TrialsCliError("--out keeps one trial's folder: give it without --repeat")
    from payload.design import models_follow_design

    _check_physics_dt(args.physics_dt)
    project = command_project(args)  # the trial flies this project's models
    models_follow_design(project.design_path, project.root, json=args.json)
    options = {
        "pin": args.pin, "max_time": args.seconds, "physics_dt": args.physics_dt,
        "warm": args.warm,
    }  # fmt: skip
    if args.repeat == 1:
        result = run_trial_bench(args.seed, out_dir=out, **options)
    else:

        def said(i: int, run: dict) -> None:
            print(
                f"bench run {i + 1} of {args.repeat}: overhead ratio "
                f"{run['overhead_ratio']:.3f}, {run['wall_seconds']:.2f} s wall, mj_step "
                f"{run['mj_step_us']:.1f} us a step, load average {run['load_average'][0]:.2f}"
                + (", with kernels' full self-checks" if run.get("full_checks") else ""),
                file=sys.stderr,
            )

        try:
            result = run_trial_bench_repeated(args.seed, args.repeat, progress=said, **options)
        except RuntimeError as exc:
            raise RunAborted(str(exc)) from None
    if args.json:
        emit_json(result)
        return 0
    if args.repeat > 1:
        print(
            f"{args.repeat} runs, each in a fresh process: overhead ratio median "
            f"{result['overhead_ratio_median']:.3f} (least {result['overhead_ratio_min']:.3f}, "
            f"greatest {result['overhead_ratio_max']:.3f}); "
            + ("the median run:" if args.repeat % 2 else "the lower of the two middle runs:")
        )
    if args.warm:
        print(
            "warm: the trial's second run in this process (the first, untimed, did the "
            "imports, the kernels' loads and checks and the caches, as a campaign worker's "
            "earlier trials have)"
        )
    print(
        f"trial seed {args.seed}: {result['sim_seconds']:.1f} s simulated in "
        f"{result['wall_seconds']:.1f} s wall ({result['realtime_factor']:.1f}x real time; "
        f"{result['cpu_seconds']:.1f} CPU s, {result['cpu_realtime_factor']:.1f}x per CPU "
        f"second), log {result['log_bytes_per_sim_minute'] / 1e6:.2f} MB per simulated minute"
    )
    for stage, wall in result["breakdown"].items():
        print(f"  {stage:10s} {wall:7.2f} s wall {result['breakdown_cpu'][stage]:7.2f} s CPU")
    if result["mj_step_us"] is not None:
        print(
            f"  of physics, mujoco.mj_step alone: {result['mj_step_seconds']:.2f} s wall "
            f"({result['mj_step_us']:.1f} us per {1e3 * result['physics_dt']:g} ms step): at "
            f"most {result['physics_only_realtime_factor']:.1f}x real time with nothing else"
        )
        print(
            f"  physics floor {result['physics_floor_s']:.2f} s; overhead ratio "
            f"{result['overhead_ratio']:.2f} (wall time over the physics floor)"
        )
    from payload.native import NATIVE_ENV

    kernels = result.get("kernels") or {}
    in_numpy = sorted(name for name, how in kernels.items() if how != "compiled")
    why = f"{NATIVE_ENV}=0" if os.environ.get(NATIVE_ENV) == "0" else "the log says why"
    print(
        f"  compiled kernels: {len(kernels) - len(in_numpy)} of {len(kernels)}"
        + (f"; in numpy: {', '.join(in_numpy)} ({why})" if in_numpy else "")
    )
    full = result.get("full_checks") or []
    if full:
        names = ", ".join(dict.fromkeys(full))
        print(
            f"  {len(full)} full kernel self-checks in this run ({names}): no check stamp "
            "yet, as after a change to the code or the environment; the figures above "
            "include them (a run that lists none is the steady one)"
        )
    env = result.get("environment") or {}
    print(
        f"  ran on: Python {env.get('python')}, numpy {env.get('numpy')} (OpenBLAS kernels "
        f"{env.get('openblas_core')}), MuJoCo {env.get('mujoco')}, load average "
        f"{result['load_average'][0]:.2f}"
    )
    if out is not None:  # where the measured trial was kept (otherwise a temporary folder)
        print(f"  the trial kept in {out}")
    return 0


def _cmd_bench_start(args: argparse.Namespace) -> int:
    from payload.trials.startbench import (
        LABELS,
        NAMES,
        StartBenchError,
        check_names,
        run_start_bench,
    )

    if args.repeat < 1:
        raise TrialsCliError(f"--repeat must be >= 1, got {args.repeat}")
    only = tuple(n.strip() for n in args.only.split(",") if n.strip()) if args.only else None
    if args.only and not only:  # "," names nothing: a run that measures nothing
        raise TrialsCliError(
            f"--only {args.only!r}: names no measure (there are: {', '.join(NAMES)})"
        )
    try:
        check_names(only)
    except ValueError as exc:
        raise TrialsCliError(f"--only: {exc}") from None
    project = command_project(args)  # its models are what the measured starts read
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=args.json)
    if not args.json:
        print(
            f"each measure in fresh processes, after one untimed run, {args.repeat} times ...",
            file=sys.stderr,
        )
    say = None if args.json else (lambda line: print(f"  {line}", file=sys.stderr))
    try:
        result = run_start_bench(project.root, args.repeat, say, only)
    except StartBenchError as exc:
        raise RunAborted(str(exc)) from None
    if args.json:
        emit_json({**result, "load_average": load_average()})
        return 0
    for name, label in LABELS.items():
        if name not in result["runs"]:
            continue
        runs = result["runs"][name]
        aim = result["aims"].get(name)
        print(
            f"{label:48s} {result[name]:6.3f} s (median; {min(runs):.3f} to {max(runs):.3f})"
            + (f", aim < {aim:g} s" if aim is not None else "")
        )
    print(f"load average {result['load'][0][0]:.2f} before, {result['load'][1][0]:.2f} after")
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``bench recorder``, ``bench trial`` and ``bench start``."""
    b = groups["bench"].add_parser("recorder", help="trial recorder cost and file size")
    b.add_argument("--seconds", type=float, default=60.0, help="recorded seconds (default 60)")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=_cmd_bench_recorder)

    bt = groups["bench"].add_parser(
        "trial", help="a trial's real-time factor, time breakdown and log size"
    )
    bt.add_argument("--seed", type=int, default=0, help="trial seed (default 0)")
    bt.add_argument("--out", help="keep the trial folder here (default: a temporary one)")
    bt.add_argument(
        "--seconds",
        type=float,
        default=None,
        metavar="S",
        help="cap the trial [s] (default: a whole trial; `payload trial`'s --max-time)",
    )
    bt.add_argument("--pin", action="store_true", help="restrict the run to one CPU core (Linux)")
    bt.add_argument(
        "--warm",
        action="store_true",
        help="run the trial once first, untimed, in the same process, and measure the "
        "second run: a campaign worker's later trial (default: a cold process, as "
        "`payload trial` runs)",
    )
    bt.add_argument(
        "--repeat",
        type=int,
        default=1,
        metavar="N",
        help="run the bench N times, each in a fresh process, and report the median run "
        "with every run's ratio (default 1)",
    )
    _physics_dt_argument(bt)
    bt.add_argument("--json", action="store_true", help="print one JSON object")
    bt.set_defaults(func=_cmd_bench_trial)

    bs = groups["bench"].add_parser(
        "start", help="how quickly commands start, each in fresh processes"
    )
    bs.add_argument(
        "--repeat",
        type=int,
        default=3,
        metavar="N",
        help="timed runs of each measure, after one untimed run (default 3)",
    )
    from payload.trials.startbench import NAMES  # light: the standard library's modules

    bs.add_argument(
        "--only",
        metavar="NAMES",
        help=f"measure only these, comma-separated ({', '.join(NAMES)})",
    )
    bs.add_argument("--json", action="store_true", help="print one JSON object")
    bs.set_defaults(func=_cmd_bench_start)


__all__ = ["register"]
