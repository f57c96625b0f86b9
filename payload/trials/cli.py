"""Command line of the trials: ``payload trial``, ``payload trials
run|summarize|convert|compare`` and ``payload export lerobot`` (contract in docs/cli.md).

This module registers them all and holds the commands on recordings already made
(``trials convert|compare``, ``export lerobot``); ``payload trial`` is
:mod:`payload.trials.trial_cli`, ``trials run|summarize`` :mod:`payload.trials.campaign_cli`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from payload.cliutil import (
    CheckFailed,
    add_deprecated,
    add_replay,
    command_project,
    emit_json,
    out_folder,
    results_folder,
    warn,
)
from payload.folders import other_results
from payload.safeio import cannot_write_in
from payload.trials.campaign_cli import _cmd_trials_run, _cmd_trials_summarize
from payload.trials.setup_options import TrialsCliError, _max_time_argument, _setup_arguments
from payload.trials.trial_cli import _cmd_trial


def _cmd_export_lerobot(args: argparse.Namespace) -> int:
    from payload.trials.lerobot import export_lerobot, resolve_runs

    runs = [Path(r) for r in args.runs]
    if args.task is not None and not args.task.strip():
        raise TrialsCliError("--task: an episode's task text cannot be empty")
    if not args.out:
        resolve_runs(runs)  # a run that is not there says so before a folder is numbered
    out_folder(args.out, holding=other_results())
    # a dataset's --out needs no project (the recordings are named); without it the
    # numbered folder goes in the project's runs/
    project = command_project(args) if not args.out else None
    with results_folder(args.out, project, "lerobot") as out:
        info = export_lerobot(
            runs, out, task=args.task, overwrite=args.force,
            progress=not args.json and sys.stderr.isatty(),
            unfinished=args.include_unfinished,
        )  # fmt: skip
    if args.json:  # "out_dir": the trials' and campaigns' name for it ("path" kept)
        emit_json({**info, "out_dir": info["path"]})
    else:
        print(
            f"wrote LeRobot v3 dataset {info['path']}: {info['episodes']} episode(s), "
            f"{info['frames']} frames at {info['fps']} Hz ({info['duration_s']:.1f} s)"
            + _left_out_words(info["left_out"])
        )
    return 0


def _left_out_words(left_out: list[dict[str, str]]) -> str:
    """The export line's tail: how many runs were left out, unfinished and unreadable."""
    from payload.trials.lerobot import UNFINISHED, UNREADABLE

    kinds = [item["kind"] for item in left_out]
    parts = [f"{n} {kind} run(s)" for kind in (UNFINISHED, UNREADABLE) if (n := kinds.count(kind))]
    return f"; {' and '.join(parts)} left out" if parts else ""


def _cmd_trials_convert(args: argparse.Namespace) -> int:
    from payload.trials.convert import convert_dir

    info = convert_dir(Path(args.dir), force=args.force)
    if args.json:
        emit_json(info)
    else:
        for line in info["messages"]:
            print(line)
    return 0


def _check_comparison_out(given: str, *, force: bool) -> None:
    """``trials compare --out``: a new file, or with ``--force`` an earlier comparison
    (its first line is a comparison's); never a folder (``given`` ending in a separator
    names one, made or not), nor any other file."""
    from payload.trials.compare import COMPARISON_OPENING

    out = Path(given)
    if out.is_dir() or given.endswith("/"):
        raise TrialsCliError(f"--out {given}: is a folder; give the comparison's file name")
    problem = cannot_write_in(out.parent) if out.parent.is_dir() else None
    if problem is not None:
        raise TrialsCliError(f"--out {out}: cannot write in {out.parent} ({problem})")
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
    from payload.trials.compare import compare_markdown, compare_runs, shown_name

    steps = args.steps or args.require_identical
    if args.out:  # before the comparison (--steps reads every recording)
        _check_comparison_out(args.out, force=args.force)
    result = compare_runs(Path(args.run_a), Path(args.run_b), steps=steps)
    text = compare_markdown(result)
    for row in result["trials"]:  # said on stderr too: a --json reader sees no table
        a, b = row["seed_a"], row["seed_b"]
        if a is not None and b is not None and a != b:
            warn(f"{shown_name(row)}: seed {a} in A and seed {b} in B: different sessions")
    if args.out:
        replace_file(Path(args.out), text)
    if args.json:
        emit_json(result)
    else:
        print(text, end="")
        if args.out:  # where the table went, below it
            print(f"wrote {args.out}")
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
        "--seed",
        type=int,
        default=None,
        help="trial seed (default 0; a replay: its source's); given with --replay it labels "
        "the run and seeds only what the recording does not fix (a bare hands.jsonl's CTB "
        "offset, --link-delay's jitter)",
    )
    add_replay(
        p,
        "replay this recording's hands (a trial's log.mcap or a hands.jsonl) instead of the "
        "synthetic operator",
    )
    add_deprecated(
        p,
        "--operator",
        # what the warning advises too: both of the old spelling's uses
        "--replay FILE (or, for the synthetic operator, no option: it is the default)",
        "operator",
        nargs="+",
        metavar=("synthetic|replay", "F"),
    )
    p.add_argument(
        "--out",
        help="trial folder (default: a new runs/trial-NNNN[-k] in the project; a replay: "
        "runs/replay-NNNN[-k])",
    )
    _max_time_argument(p, "the session's")
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
    _max_time_argument(r, "each trial's session")
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
        "the contact definition; a trial scored as its metrics.json says: not written)",
    )
    s.add_argument(
        "--force", action="store_true", help="replace summary or rescoring files that differ"
    )
    s.add_argument(
        "--min-contact-s",
        type=float,
        default=None,
        metavar="S",
        help="rescore, skipping contact runs shorter than this [s] (paper: 0; default: "
        "as recorded)",
    )
    s.add_argument(
        "--max-gap-s",
        type=float,
        default=None,
        metavar="S",
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
    cm.add_argument("--out", metavar="FILE", help="also write the Markdown table to this file")
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
        help="export the recordings of unfinished runs too: aborted, cut short, stopped by "
        "the --max-time cap, or replays of such runs (left out by default, each named in a "
        "warning)",
    )
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_cmd_export_lerobot)
