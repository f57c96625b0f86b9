"""Command line of the trials: ``payload trial``, ``payload trials run|summarize`` and
``payload export lerobot`` (contract in docs/cli.md)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from payload.cliutil import (
    CheckFailed,
    add_deprecated,
    add_replay,
    command_project,
    default_out,
    emit_json,
    kept_if_used,
    out_folder,
    warn,
)
from payload.folders import (
    CAMPAIGN_FIGURE,
    CAMPAIGN_FILES,
    HANDS,
    RECORDING,
    SUMMARY,
    SUMMARY_TEXT,
    TRIAL_FILES,
    held,
)
from payload.trials.setup_options import (
    _SETUP,
    TrialsCliError,
    _check_physics_dt,
    _link_and_zones,
    _setup_arguments,
    _setup_defaults,
)


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


def _replay_file(option: str, replay: Path) -> Path:
    """The recording a replay option names, or one line saying why it is not one (a
    trial's folder names the file in it to give)."""
    if replay.is_dir():
        inside = [n for n in (RECORDING, HANDS) if (replay / n).is_file()]
        hint = f": give {replay / inside[0]}" if inside else ""
        raise TrialsCliError(f"{option}: {replay}: is a folder, not a recording{hint}")
    if not replay.is_file():
        raise TrialsCliError(f"{option}: {replay}: no such file")
    return replay


def _parse_operator(args: argparse.Namespace) -> tuple[str, Path | None]:
    """The operator of ``payload trial``: ``--replay FILE``, else synthetic; or the
    deprecated ``--operator synthetic|replay FILE``.

    Raises:
        TrialsCliError: Both spellings, a bad ``--operator`` or no such file.
    """
    values = getattr(args, "operator", None)
    if values is None:
        if args.replay is None:
            return "synthetic", None
        return "replay", _replay_file("--replay", Path(args.replay))
    if args.replay is not None:
        raise TrialsCliError("--replay and --operator (its deprecated spelling): give one")
    if values == ["synthetic"]:
        return "synthetic", None
    if len(values) == 2 and values[0] == "replay":
        return "replay", _replay_file("--operator replay", Path(values[1]))
    raise TrialsCliError(
        f"--operator: expected 'synthetic' or 'replay FILE', got {' '.join(values)!r}"
    )


def _check_ctb(ctb: str) -> None:
    from payload.sim.world import CTB_MODELS

    if ctb not in CTB_MODELS:
        raise TrialsCliError(f"--ctb: expected one of {', '.join(CTB_MODELS)}, got {ctb!r}")


def _cmd_trial(args: argparse.Namespace) -> int:
    from payload.design import models_follow_design

    if args.seed is not None and args.seed < 0:
        raise TrialsCliError(f"--seed must be >= 0, got {args.seed}")
    if args.max_time is not None and not args.max_time > 0:
        raise TrialsCliError(f"--max-time must be positive, got {args.max_time}")
    _check_physics_dt(args.physics_dt)
    operator, replay = _parse_operator(args)
    if operator == "synthetic":
        _setup_defaults(args)
    if args.ctb is not None:
        _check_ctb(args.ctb)
    project = command_project(args)
    models_follow_design(project.design_path, project.root, json=args.json)
    out = out_folder(args.out)
    run_trial = _run_trial_fn()
    extra: dict[str, Any] = {"project": project, **_link_and_zones(args)}
    for name in _SETUP:
        if getattr(args, name) is not None:  # a replay: the others are its recording's
            extra[name] = getattr(args, name)
    if not args.json and sys.stderr.isatty():
        extra["progress"] = True
    if args.max_time is not None:
        extra["max_time"] = args.max_time
    if args.force:
        extra["force"] = True
    campaign = None
    if out is not None and out.name.startswith("trial-"):
        campaign = held(out.parent, CAMPAIGN_FILES) or None
    seed = args.seed if args.seed is not None or operator == "replay" else 0
    result = dict(run_trial(seed=seed, operator=operator, replay=replay, out_dir=out, **extra))
    out = Path(result.get("out_dir") or out)
    seed = result.get("seed", seed)
    if campaign:  # a campaign's trial, rerun: its summary describes what was there before
        warn(
            f"{out} is a trial of the campaign in {out.parent} ({', '.join(campaign)}), whose "
            f"summary no longer matches it: `payload trials summarize {out.parent} --force` "
            "brings it up to date"
        )
    if args.json:
        emit_json({**result, "project": str(project.root)})
        return 0
    print(f"trial seed {seed} ({operator}) -> {out}")
    given = ""
    if operator == "replay":
        names = [n for n in _SETUP if getattr(args, n) is not None]
        given = " (the recording's)"
        if names:
            given = f" (given: {', '.join(names)}; the rest the recording's)"
    from payload.trials.summary import print_trial_summary

    print_trial_summary(result, given)
    return 0


def _cmd_trials_run(args: argparse.Namespace) -> int:
    from payload.design import models_follow_design
    from payload.project import provenance
    from payload.trials.campaign import (
        default_workers,
        run_campaign,
        runner_trial_fn,
        trial_dir,
        write_summary,
    )
    from payload.trials.summary import trials_environment
    from payload.trials.terminal import summary_terminal, trial_line_printer

    if args.n < 1:
        raise TrialsCliError(f"--n must be >= 1, got {args.n}")
    if args.seed < 0:
        raise TrialsCliError(f"--seed must be >= 0, got {args.seed}")
    if args.workers is not None and args.workers < 0:
        raise TrialsCliError(f"--workers must be >= 0, got {args.workers}")
    from payload.trials.cluster import check_scheduler

    check_scheduler(args.scheduler, TrialsCliError)
    _check_physics_dt(args.physics_dt)
    _setup_defaults(args)
    _check_ctb(args.ctb)
    link_zones = _link_and_zones(args)
    _run_trial_fn()  # fail here, once, if the runner is missing
    project = command_project(args)
    models_follow_design(project.design_path, project.root, json=args.json)
    prov = provenance(project)
    made = args.out is None or not Path(args.out).exists()  # removed again if left empty
    out = out_folder(args.out) or default_out(project, "campaign")
    seeds = list(range(args.seed, args.seed + args.n))
    trial = held(out, TRIAL_FILES)
    if trial:  # --force replaces a campaign, never a trial
        raise TrialsCliError(
            f"{out}: holds a trial ({', '.join(trial)}); a campaign goes in a folder of its "
            "own (choose another --out)"
        )
    if not args.force:
        taken = [trial_dir(out, s) for s in seeds if any(trial_dir(out, s).glob("*"))]
        taken += [out / n for n in held(out, CAMPAIGN_FILES)]
        if taken:
            raise TrialsCliError(
                f"{out}: already holds a campaign ({', '.join(p.name for p in taken[:4])}"
                f"{', ...' if len(taken) > 4 else ''}); pass --force to replace it or choose "
                "another --out"
            )
    workers = default_workers(args.n) if args.workers is None else args.workers
    t0 = time.perf_counter()
    with kept_if_used(out, made=made):  # a scheduler not reached leaves no empty folder
        results = run_campaign(
            runner_trial_fn(
                "synthetic",
                project.root,
                force=args.force,
                **{name: getattr(args, name) for name in _SETUP},
                **link_zones,
            ),
            seeds,
            out,
            workers=workers,
            scheduler=args.scheduler,
            progress=not args.json and sys.stderr.isatty() and sys.stdout.isatty(),
            on_trial=None if args.json or sys.stdout.isatty() else trial_line_printer(len(seeds)),
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
        f"{', self-collision modelled' if args.retarget_collisions else ''}"
        f"{', base filter' if args.base_filter else ''}"
        f"{f', link delay {args.link_delay} s' if args.link_delay else ''}"
        f"{_physics_text(args.physics_dt)})"
    )
    # what the trials ran on, as each trial's process reported it (a scheduler's workers
    # may be other machines than this one)
    prov = {**prov, "environment": trials_environment(results)}
    summary = write_summary(results, out, title=title, run=run, provenance=prov, force=args.force)
    if args.force:  # the replaced campaign's rescorings would describe it still
        from payload.trials.scoring import rescorings

        for stale in rescorings(out, (*CAMPAIGN_FILES, CAMPAIGN_FIGURE)):
            stale.unlink()
    ours = {trial_dir(out, s).name for s in seeds}
    earlier = sorted(p.name for p in out.glob("trial-*") if p.is_dir() and p.name not in ours)
    if earlier:  # kept (recordings), but not this campaign's: said, not silently summarized
        more = f" and {len(earlier) - 3} more" if len(earlier) > 3 else ""
        warn(
            f"{out} also holds {', '.join(earlier[:3])}{more} from an earlier run, left out of "
            "this summary (`trials summarize` would take them in: move them away)"
        )
    if args.json:
        emit_json(
            {**summary, "wall_s": run["wall_s"], "out_dir": str(out), "project": str(project.root)}
        )
    else:
        print(summary_terminal(summary, title))
        figure = out / CAMPAIGN_FIGURE
        also = f", {figure}" if figure.is_file() else ""
        print(f"wrote {out / SUMMARY_TEXT} (definitions, the paper-literal column, every "
              f"trial){also} and {out / SUMMARY}")  # fmt: skip
    errors = [r for r in results if r.get("error")]
    if errors:
        first = errors[0]
        raise CheckFailed(
            f"{len(errors)} of {len(results)} trial(s) raised an error (seeds "
            f"{', '.join(str(r['seed']) for r in errors)}; first: {first['error']}; "
            f"tracebacks in {SUMMARY})"
        )
    return 0


def _physics_text(dt: float) -> str:
    """The title's note of a physics step other than the default (empty at 1 kHz)."""
    from payload.schema import PHYSICS_DT

    return "" if dt == PHYSICS_DT else f", physics step {1e3 * dt:g} ms"


def _cmd_trials_summarize(args: argparse.Namespace) -> int:
    from payload.trials.campaign import (
        contact_tag,
        load_trial_results,
        summary_markdown,
        write_summary,
    )
    from payload.trials.scoring import MIXED_TAG, UNSCORED_TAG

    for name in ("min_contact_s", "max_gap_s"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise TrialsCliError(f"--{name.replace('_', '-')} must be a number >= 0, got {value}")
    relaxed = args.min_contact_s is not None or args.max_gap_s is not None
    rescore = args.recompute or relaxed
    results = load_trial_results(
        args.dir,
        recompute=rescore,
        min_interval_s=args.min_contact_s,
        max_gap_s=args.max_gap_s,
        force=args.force,
    )
    previous = _previous_summary(Path(args.dir) / SUMMARY)
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
        if isinstance(previous.get("controller"), str):
            r.setdefault("controller", previous["controller"])
            r.setdefault("controller_overrides", previous.get("controller_overrides") or [])
    tag = None
    if rescore:  # a rescoring is written beside the originals, named by its definition
        defs = {
            (float(r.get("min_interval_s") or 0.0), float(r.get("max_gap_s") or 0.0))
            for r in results
            if not r.get("error")
        }
        tag = contact_tag(*defs.pop()) if len(defs) == 1 else MIXED_TAG if defs else UNSCORED_TAG
    prov = previous.get("provenance")
    if prov is None:  # no campaign summary before: what the trials themselves record
        from payload.trials.summary import trials_environment

        own = [r["provenance"] for r in results if isinstance(r.get("provenance"), dict)]
        prov = {**own[0], "environment": trials_environment(results)} if own else None
    summary = write_summary(
        results,
        args.dir,
        title=previous.get("title"),
        run=previous.get("run"),
        provenance=prov,
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
    from payload.trials.lerobot import export_lerobot, resolve_runs

    runs = [Path(r) for r in args.runs]
    if not args.out:
        resolve_runs(runs)  # a run that is not there says so before a folder is numbered
    out = out_folder(args.out, holding=(*TRIAL_FILES, *CAMPAIGN_FILES)) or default_out(
        command_project(args), "lerobot"
    )
    with kept_if_used(out, made=not args.out):
        info = export_lerobot(
            runs, out, task=args.task, overwrite=args.force,
            progress=not args.json and sys.stderr.isatty(),
            unfinished=args.include_unfinished,
        )  # fmt: skip
    if args.json:
        emit_json(info)
    else:
        print(
            f"wrote LeRobot v3 dataset {info['path']}: {info['episodes']} episode(s), "
            f"{info['frames']} frames at {info['fps']} Hz ({info['duration_s']:.1f} s)"
            + (f"; {len(info['left_out'])} unfinished run(s) left out" if info["left_out"] else "")
        )
    return 0


def _cmd_trials_convert(args: argparse.Namespace) -> int:
    from payload.trials.convert import convert_dir

    info = convert_dir(Path(args.dir), force=args.force)
    if args.json:
        emit_json(info)
    else:
        for line in info["messages"]:
            print(line)
    return 0


def _check_comparison_out(out: Path, *, force: bool) -> None:
    """``trials compare --out``: a new file, or with ``--force`` an earlier comparison
    (its first line is a comparison's); never a folder, nor any other file."""
    from payload.trials.compare import COMPARISON_OPENING

    if out.is_dir():
        raise TrialsCliError(f"--out {out}: is a folder; give the comparison's file name")
    if not out.exists():
        return
    with out.open("rb") as fh:
        earlier = fh.read(len(COMPARISON_OPENING)) == COMPARISON_OPENING.encode()
    if not earlier:
        raise TrialsCliError(
            f"--out {out}: exists and is not a comparison; --force replaces only an earlier "
            "comparison (choose another --out)"
        )
    if not force:
        raise TrialsCliError(
            f"--out {out}: holds an earlier comparison; pass --force to replace it or choose "
            "another --out"
        )


def _cmd_trials_compare(args: argparse.Namespace) -> int:
    from payload.safeio import replace_file
    from payload.trials.compare import compare_markdown, compare_runs

    steps = args.steps or args.require_identical
    result = compare_runs(Path(args.run_a), Path(args.run_b), steps=steps)
    text = compare_markdown(result)
    if args.out:
        _check_comparison_out(Path(args.out), force=args.force)
        replace_file(Path(args.out), text)
    if args.json:
        emit_json(result)
    else:
        print(text, end="")
    if args.require_identical and not result["identical"]:
        rows = result["trials"]
        differ = [r["trial"] for r in rows if not r["steps"]["identical"]]
        channels = [r["trial"] for r in rows if not r["channels"]["identical"]]
        others = sorted({m for r in rows for m in r["other_metrics"]})
        alone = result["only_a"] + result["only_b"]
        raise CheckFailed(
            f"the runs differ (steps differ in: {', '.join(differ) or 'none'}; other channels "
            f"in: {', '.join(channels) or 'none'}; other metrics: {', '.join(others) or 'none'}"
            f"; trials in one run only: {', '.join(alone) or 'none'}; metric table above)"
        )
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``trial``, ``trials run|summarize|convert|compare`` and ``export lerobot`` (the
    benches of the recorder and of a trial: :mod:`payload.trials.bench_cli`)."""
    p = sub.add_parser("trial", help="one ISS cargo-transport trial")
    p.add_argument(
        "--seed", type=int, default=None, help="trial seed (default 0; a replay: its source's)"
    )
    add_replay(
        p,
        "replay this recording's hands (a trial's log.mcap or a hands.jsonl) instead of the "
        "synthetic operator",
    )
    add_deprecated(
        p,
        "--operator",
        "--replay FILE (or, for the synthetic operator, no option: it is the default)",
        "operator",
        nargs="+",
        metavar=("synthetic|replay", "F"),
        help="'synthetic' or 'replay FILE'",
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
    r.add_argument(
        "--out", help="campaign folder (default: a new runs/campaign-NNNN in the project)"
    )
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

    cm = tsub.add_parser(
        "compare", help="two runs of the same seeds, seed by seed (metrics, and steps)"
    )
    cm.add_argument("run_a", metavar="RUN_A", help="reference campaign or trial folder")
    cm.add_argument("run_b", metavar="RUN_B", help="campaign or trial folder compared with it")
    cm.add_argument(
        "--steps",
        action="store_true",
        help="also compare every recorded step, every message of the other channels (their "
        "wall-clock timestamps aside) and every other metric, bit for bit",
    )
    cm.add_argument(
        "--require-identical",
        action="store_true",
        help="compare as --steps does and exit 1 unless both runs hold the same trials, "
        "with the same metrics, recorded steps and other channels' messages (their "
        "wall-clock timestamps aside) in every bit",
    )
    cm.add_argument("--out", help="also write the Markdown table to this file")
    cm.add_argument("--force", action="store_true", help="replace --out if it exists")
    cm.add_argument("--json", action="store_true", help="print one JSON object")
    cm.set_defaults(func=_cmd_trials_compare)

    e = groups["export"].add_parser("lerobot", help="recordings as a LeRobot v3 dataset")
    e.add_argument("runs", nargs="+", metavar="RUN", help="log.mcap, trial or campaign folder")
    e.add_argument("--out", help="dataset folder (default: a new runs/lerobot-NNNN in the project)")
    e.add_argument("--task", help="task text for every episode")
    e.add_argument("--force", action="store_true", help="replace an existing dataset")
    e.add_argument(
        "--include-unfinished",
        action="store_true",
        help="export the recordings of aborted or cut-short runs too (left out by default, "
        "each named in a warning)",
    )
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_cmd_export_lerobot)
