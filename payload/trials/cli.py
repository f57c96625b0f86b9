"""Command line of the trials: ``payload trial``, ``payload trials run|summarize`` and
``payload export lerobot`` (contract in DESIGN.md)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from payload.errors import PayloadError


class TrialsCliError(PayloadError):
    """Bad arguments to a trials command, or the trial runner is not available."""


def _run_trial_fn() -> Any:
    try:
        from payload.trials.runner import run_trial
    except ModuleNotFoundError as exc:
        if exc.name != "payload.trials.runner":
            raise
        raise TrialsCliError(
            "payload.trials.runner (the teleoperation trial loop, issue 6) is not installed yet"
        ) from None
    return run_trial


def _parse_operator(values: list[str]) -> tuple[str, Path | None]:
    if values == ["synthetic"]:
        return "synthetic", None
    if len(values) == 2 and values[0] == "replay":
        replay = Path(values[1])
        if not replay.is_file():
            raise TrialsCliError(f"--operator replay: {replay}: no such file")
        return "replay", replay
    raise TrialsCliError(
        f"--operator: expected 'synthetic' or 'replay FILE', got {' '.join(values)!r}"
    )


def _check_ctb(ctb: str) -> None:
    from payload.sim.world import CTB_MODELS

    if ctb not in CTB_MODELS:
        raise TrialsCliError(f"--ctb: expected one of {', '.join(CTB_MODELS)}, got {ctb!r}")


def _cmd_trial(args: argparse.Namespace) -> int:
    from payload.cli import command_project, emit_json

    if args.seed is not None and args.seed < 0:
        raise TrialsCliError(f"--seed must be >= 0, got {args.seed}")
    if args.max_time is not None and not args.max_time > 0:
        raise TrialsCliError(f"--max-time must be positive, got {args.max_time}")
    operator, replay = _parse_operator(args.operator)
    if operator == "synthetic":
        _setup_defaults(args)
    if args.ctb is not None:
        _check_ctb(args.ctb)
    project = command_project(args)
    out = Path(args.out) if args.out else None
    run_trial = _run_trial_fn()
    extra: dict[str, Any] = {"project": project}
    for name in _SETUP:
        if getattr(args, name) is not None:  # a replay: the others are its recording's
            extra[name] = getattr(args, name)
    if not args.json and sys.stderr.isatty():
        extra["progress"] = True
    if args.max_time is not None:
        extra["max_time"] = args.max_time
    if args.force:
        extra["force"] = True
    seed = args.seed if args.seed is not None or operator == "replay" else 0
    result = dict(run_trial(seed=seed, operator=operator, replay=replay, out_dir=out, **extra))
    out = Path(result.get("out_dir") or out)
    seed = result.get("seed", seed)
    if args.json:
        emit_json({**result, "project": str(project.root)})
        return 0
    from payload.trials.campaign import METRIC_KEYS, METRIC_LABELS

    print(f"trial seed {seed} ({operator}) -> {out}")
    given = ""
    if operator == "replay":
        names = [n for n in _SETUP if getattr(args, n) is not None]
        given = " (the recording's)"
        if names:
            given = f" (given: {', '.join(names)}; the rest the recording's)"
    modelled = "modelled" if result.get("retarget_collisions") else "off"
    print(
        f"  setup: CTB {result.get('ctb')}, {result.get('propulsion')} propulsion, "
        f"controller {result.get('controller')}, retargeting budget "
        f"{result.get('retarget_budget')}, self-collision "
        f"{modelled}{given}"
    )
    print(f"  success: {bool(result.get('success'))}")
    for key in METRIC_KEYS:
        value = result.get(key)
        shown = "n/a" if value is None else f"{value:.3f}"
        print(f"  {METRIC_LABELS[key]}: {shown}")
    return 0


def _cmd_trials_run(args: argparse.Namespace) -> int:
    from payload.cli import CheckFailed, command_project, emit_json
    from payload.project import provenance
    from payload.trials.campaign import (
        default_workers,
        run_campaign,
        runner_trial_fn,
        summary_markdown,
        trial_dir,
        write_summary,
    )

    if args.n < 1:
        raise TrialsCliError(f"--n must be >= 1, got {args.n}")
    if args.seed < 0:
        raise TrialsCliError(f"--seed must be >= 0, got {args.seed}")
    if args.workers is not None and args.workers < 0:
        raise TrialsCliError(f"--workers must be >= 0, got {args.workers}")
    _setup_defaults(args)
    _check_ctb(args.ctb)
    _run_trial_fn()  # fail here, once, if the runner is missing
    project = command_project(args)
    prov = provenance(project)
    out = Path(args.out)
    seeds = list(range(args.seed, args.seed + args.n))
    if not args.force:
        taken = [trial_dir(out, s) for s in seeds if any(trial_dir(out, s).glob("*"))]
        taken += [out / n for n in ("summary.json", "summary.md") if (out / n).exists()]
        if taken:
            raise TrialsCliError(
                f"{out}: already holds a campaign ({', '.join(p.name for p in taken[:4])}"
                f"{', ...' if len(taken) > 4 else ''}); pass --force to replace it or choose "
                "another --out"
            )
    workers = default_workers(args.n) if args.workers is None else args.workers
    t0 = time.perf_counter()
    results = run_campaign(
        runner_trial_fn(
            "synthetic",
            project.root,
            force=args.force,
            ctb=args.ctb,
            propulsion=args.propulsion,
            retarget_budget=args.retarget_budget,
            retarget_collisions=args.retarget_collisions,
            controller=args.controller,
        ),
        seeds,
        out,
        workers=workers,
        scheduler=args.scheduler,
        progress=not args.json and sys.stderr.isatty(),
    )
    run = {
        "workers": None if args.scheduler else workers,
        "scheduler": args.scheduler,
        "wall_s": time.perf_counter() - t0,
        "trial_wall_s": float(sum(r.get("wall_s") or 0.0 for r in results)),
    }
    title = (
        f"Cargo-transport campaign ({args.n} trials, CTB {args.ctb}, {args.propulsion}, "
        f"controller {args.controller}, retargeting budget {args.retarget_budget}"
        f"{', self-collision modelled' if args.retarget_collisions else ''})"
    )
    summary = write_summary(results, out, title=title, run=run, provenance=prov, force=args.force)
    if args.json:
        emit_json(
            {**summary, "wall_s": run["wall_s"], "out_dir": str(out), "project": str(project.root)}
        )
    else:
        print(summary_markdown(summary, title))
        print(f"wrote {out / 'summary.md'} and {out / 'summary.json'}")
    errors = [r for r in results if r.get("error")]
    if errors:
        first = errors[0]
        raise CheckFailed(
            f"{len(errors)} of {len(results)} trial(s) raised an error (seeds "
            f"{', '.join(str(r['seed']) for r in errors)}; first: {first['error']}; "
            "tracebacks in summary.json)"
        )
    return 0


def _cmd_trials_summarize(args: argparse.Namespace) -> int:
    from payload.cli import emit_json
    from payload.trials.campaign import (
        contact_tag,
        load_trial_results,
        summary_markdown,
        write_summary,
    )

    for name in ("min_contact_s", "max_gap_s"):
        value = getattr(args, name)
        if value is not None and value < 0:
            raise TrialsCliError(f"--{name.replace('_', '-')} must be >= 0")
    relaxed = args.min_contact_s is not None or args.max_gap_s is not None
    rescore = args.recompute or relaxed
    results = load_trial_results(
        args.dir,
        recompute=rescore,
        min_interval_s=args.min_contact_s,
        max_gap_s=args.max_gap_s,
        force=args.force,
    )
    previous = _previous_summary(Path(args.dir) / "summary.json")
    wall = {t.get("seed"): t.get("wall_s") for t in previous.get("trials", [])}
    budget = previous.get("retarget_budget")
    modelled = previous.get("retarget_collisions")
    for r in results:  # how long each trial took is known only from the campaign run
        if r.get("wall_s") is None and wall.get(r.get("seed")) is not None:
            r["wall_s"] = wall[r.get("seed")]
        # trials whose metrics.json lacks these: the campaign's summary says
        if isinstance(budget, str):
            r.setdefault("retarget_budget", budget)
        if isinstance(modelled, bool):
            r.setdefault("retarget_collisions", modelled)
    tag = None
    if rescore:  # a rescoring is written beside the originals, named by its definition
        defs = {
            (float(r.get("min_interval_s") or 0.0), float(r.get("max_gap_s") or 0.0))
            for r in results
            if not r.get("error")
        }
        tag = contact_tag(*defs.pop()) if len(defs) == 1 else "contact-mixed"
    summary = write_summary(
        results,
        args.dir,
        title=previous.get("title"),
        run=previous.get("run"),
        provenance=previous.get("provenance"),
        tag=tag,
        force=args.force,
    )
    if args.json:
        emit_json({**summary, "out_dir": str(args.dir)})
    else:
        print(summary_markdown(summary, previous.get("title")))
    return 0


def _previous_summary(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def _cmd_export_lerobot(args: argparse.Namespace) -> int:
    from payload.cli import emit_json
    from payload.trials.lerobot import export_lerobot

    info = export_lerobot(
        [Path(r) for r in args.runs],
        Path(args.out),
        task=args.task,
        overwrite=args.force,
        progress=not args.json and sys.stderr.isatty(),
    )
    if args.json:
        emit_json(info)
    else:
        print(
            f"wrote LeRobot v3 dataset {info['path']}: {info['episodes']} episode(s), "
            f"{info['frames']} frames at {info['fps']} Hz ({info['duration_s']:.1f} s)"
        )
    return 0


def _cmd_bench_recorder(args: argparse.Namespace) -> int:
    import tempfile

    import numpy as np

    from payload.cli import emit_json
    from payload.schema import CONTROL_DT
    from payload.trials.metrics import compute_metrics
    from payload.trials.recorder import TrialRecorder, random_step, read_recording

    if args.seconds <= 0:
        raise TrialsCliError(f"--seconds must be positive, got {args.seconds}")
    n = max(2, round(args.seconds / CONTROL_DT))
    rng = np.random.default_rng(0)
    steps = [random_step(rng, k * CONTROL_DT) for k in range(n)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.mcap"
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
    minutes = n / 50 / 60
    result = {
        "steps": n,
        "recorded_s": n / 50,
        "write_us_median": float(np.median(per_step) * 1e6),
        "write_us_p99": float(np.quantile(per_step, 0.99) * 1e6),
        "write_budget_fraction": float(np.median(per_step) / 0.02),
        "file_mb_per_min": size / 1e6 / minutes,
        "read_s_per_min": read_s / minutes,
        "metrics_s": metrics_s,
    }
    if args.json:
        emit_json(result)
    else:
        print(
            f"recorder, {n} steps ({n / 50:.0f} s at 50 Hz): write {result['write_us_median']:.0f}"
            f" us/step median ({result['write_us_p99']:.0f} us p99, "
            f"{100 * result['write_budget_fraction']:.2f} % of the 20 ms step), "
            f"{result['file_mb_per_min']:.1f} MB per minute, read "
            f"{result['read_s_per_min']:.2f} s per minute, metrics {1e3 * metrics_s:.1f} ms"
        )
    return 0


def _cmd_bench_trial(args: argparse.Namespace) -> int:
    from payload.cli import emit_json
    from payload.trials.bench import run_trial_bench

    if args.seed < 0:
        raise TrialsCliError(f"--seed must be >= 0, got {args.seed}")
    out = Path(args.out) if args.out else None
    if args.seconds is not None and args.seconds <= 0:
        raise TrialsCliError(f"--seconds must be positive, got {args.seconds}")
    result = run_trial_bench(args.seed, out_dir=out, pin=args.pin, max_time=args.seconds)
    if args.json:
        emit_json(result)
        return 0
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
            f"({result['mj_step_us']:.1f} us per 1 ms step): at most "
            f"{result['physics_only_realtime_factor']:.1f}x real time with nothing else"
        )
    return 0


def _cmd_trials_convert(args: argparse.Namespace) -> int:
    from payload.cli import emit_json
    from payload.trials.convert import convert_dir

    info = convert_dir(Path(args.dir), force=args.force)
    if args.json:
        emit_json(info)
    else:
        for line in info["messages"]:
            print(line)
    return 0


_SETUP = ("ctb", "propulsion", "retarget_budget", "retarget_collisions", "controller")
"""The trial setup flags' attribute names."""


def _setup_arguments(p: argparse.ArgumentParser, *, replay: bool = False) -> None:
    """The trial setup flags; with ``replay`` each left out means "the recording's" for a
    replay (``None`` here, resolved by the runner)."""
    from payload.profiles import PAPER, PROFILES
    from payload.sim.vehicle import DEFAULT_PROPULSION, PROPULSION_MODELS

    mine = "; a replay: its recording's unless given" if replay else ""
    p.add_argument(
        "--controller",
        choices=tuple(PROFILES),
        default=None,
        help=f"controller profile (default {PAPER}{mine}): 'paper' is the paper's "
        "controller (20-evaluation pair solves, no self-collision model); 'safe' adds the "
        "contact-aware self-collision model and the base safety filter; "
        "--retarget-budget and --[no-]retarget-collisions override it",
    )
    p.add_argument(
        "--ctb",
        default=None,
        help="CTB model: single (NASA's loaded single bag) or rigid (the rigid bag of "
        f"Morton et al.); default single{mine}",
    )
    p.add_argument(
        "--propulsion",
        choices=PROPULSION_MODELS,
        default=None,
        help=f"vehicle propulsion model (default {DEFAULT_PROPULSION}{mine})",
    )
    p.add_argument(
        "--retarget-budget",
        choices=("paper", "converged"),
        default=None,
        help="retargeting budget per pair solve: 'paper' (at most 20 residual evaluations, "
        "the paper's controller) or 'converged' (each start run to convergence); default: "
        f"the --controller profile's{mine}",
    )
    p.add_argument(
        "--retarget-collisions",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="model self-collision in the pair solves: no command closer than the design's "
        "margin (the pads of a pair excepted), the operator's opening mapped to the "
        f"collision-free span range (default: the --controller profile's{mine})",
    )


def _setup_defaults(args: argparse.Namespace) -> None:
    """Fill the setup flags left out with the defaults (synthetic trials, campaigns)."""
    from payload.trials.sources import trial_setup

    try:
        setup = trial_setup(**{n: getattr(args, n) for n in _SETUP})
    except PayloadError as exc:
        raise TrialsCliError(str(exc)) from None
    for name, value in setup.items():
        setattr(args, name, value)


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``trial``, ``trials run|summarize|convert``, ``export lerobot``, ``bench recorder``
    and ``bench trial``."""
    p = sub.add_parser("trial", help="one ISS cargo-transport trial")
    p.add_argument(
        "--seed", type=int, default=None, help="trial seed (default 0; a replay: its source's)"
    )
    p.add_argument(
        "--operator",
        nargs="+",
        default=["synthetic"],
        metavar=("synthetic|replay", "F"),
        help="'synthetic' (default) or 'replay FILE' (a recorded hand stream)",
    )
    p.add_argument("--out", help="trial folder (default: a new runs/trial-NNNN[-k] in the project)")
    p.add_argument(
        "--max-time",
        type=float,
        default=None,
        help="cap on the session length [s] (default: the runner's, 240 s)",
    )
    p.add_argument("--force", action="store_true", help="replace the trial already in --out")
    _setup_arguments(p, replay=True)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_trial)

    trials = sub.add_parser("trials", help="trial campaigns and their summaries")
    tsub = trials.add_subparsers(dest="trials_command", required=True, metavar="WHAT")
    r = tsub.add_parser("run", help="a campaign of N seeded trials on Dask, and its summary")
    r.add_argument("--n", type=int, required=True, help="number of trials")
    r.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    r.add_argument(
        "--workers",
        type=int,
        default=None,
        help="local Dask worker processes (default: one per core; 0 or 1: serial)",
    )
    r.add_argument("--scheduler", help="existing Dask scheduler, e.g. tcp://host:8786")
    r.add_argument("--out", required=True, help="campaign folder")
    r.add_argument("--force", action="store_true", help="replace a campaign already in --out")
    _setup_arguments(r)
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.set_defaults(func=_cmd_trials_run)

    s = tsub.add_parser("summarize", help="rebuild summary.md/json from the trial folders")
    s.add_argument("dir", help="campaign folder")
    s.add_argument(
        "--recompute",
        action="store_true",
        help="rescore every trial from its log.mcap (written beside the originals, named by "
        "the contact definition)",
    )
    s.add_argument(
        "--force", action="store_true", help="replace summary or rescoring files that differ"
    )
    s.add_argument(
        "--min-contact-s",
        type=float,
        default=None,
        help="rescore, skipping contact runs shorter than this [s] (paper: 0; default: "
        "as recorded)",
    )
    s.add_argument(
        "--max-gap-s",
        type=float,
        default=None,
        help="rescore, bridging contact-indicator dropouts up to this long [s] (paper: 0; "
        "default: as recorded)",
    )
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.set_defaults(func=_cmd_trials_summarize)

    c = tsub.add_parser(
        "convert", help="rewrite schema-1 (JSON) recordings in a folder as schema 3"
    )
    c.add_argument("dir", help="trial or campaign folder (every log.mcap below it)")
    c.add_argument("--force", action="store_true", help="convert even if a backup exists")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.set_defaults(func=_cmd_trials_convert)

    e = groups["export"].add_parser("lerobot", help="recordings as a LeRobot v3 dataset")
    e.add_argument("runs", nargs="+", metavar="RUN", help="log.mcap, trial or campaign folder")
    e.add_argument("--out", required=True, help="dataset folder")
    e.add_argument("--task", help="task text for every episode")
    e.add_argument("--force", action="store_true", help="replace an existing dataset")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_cmd_export_lerobot)

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
        "--seconds", type=float, default=None, help="cap the trial [s] (default: a whole trial)"
    )
    bt.add_argument("--pin", action="store_true", help="restrict the run to one CPU core (Linux)")
    bt.add_argument("--json", action="store_true", help="print one JSON object")
    bt.set_defaults(func=_cmd_bench_trial)
