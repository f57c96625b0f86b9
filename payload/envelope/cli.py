"""``payload report envelope``, ``payload report reach`` and ``payload report all``.

The runs behind the commands (arguments to written report) are
:mod:`payload.envelope.cli_runs`; this module holds the commands' options, verdicts,
JSON output and exit codes.
"""

from __future__ import annotations

import argparse
import statistics
from typing import TYPE_CHECKING, Any

from payload.cliutil import CheckFailed, emit_json, load_average
from payload.envelope import MIN_SAMPLES, REACH_SAMPLES
from payload.envelope.cli_runs import (
    _check_reach_args,
    _design_path,
    _load,
    _models_follow,
    _project,
    _recorder,
    _refuse_foreign_reports,
    _stdout_json,
    reach_lines,
    run_envelope,
    run_reach,
    written_lines,
)
from payload.errors import first_of

if TYPE_CHECKING:
    from payload.envelope.fit import EnvelopeAnalysis
    from payload.envelope.reach import ReachAnalysis

BENCH_CHECK_SAMPLES = 10_000
"""``payload bench reach``: the samples both checks run on, by default."""
BENCH_RUNS = 3
"""``payload bench reach``: the timed reports, by default."""


def _cmd_envelope(args: argparse.Namespace) -> int:
    from payload.envelope.markdown import assumption_line
    from payload.envelope.report import envelope_json
    from payload.envelope.verdict import envelope_verdict

    analysis, paths, lines = run_envelope(args)
    if args.json:
        emit_json(_stdout_json(args, _recorder(args)(envelope_json(analysis))))
    else:
        print(envelope_verdict(analysis))
        print(assumption_line(analysis))
        for line in [*lines, *written_lines(paths, "envelope")]:
            print(line)
    if not analysis.passed:
        failures = analysis.given.failures()
        raise CheckFailed("stowed payload: " + first_of(failures, 3))
    return 0


def _cmd_reach(args: argparse.Namespace) -> int:
    analysis, paths = run_reach(args)  # before the imports below: see run_reach
    from payload.envelope.report import reach_json
    from payload.envelope.verdict import reach_passed, reach_verdict

    if args.json:
        data = {**_recorder(args)(reach_json(analysis)), **_reach_verdict_fields(analysis)}
        emit_json(_stdout_json(args, data))
    else:
        print(reach_verdict(analysis))
        for line in [*reach_lines(analysis), *written_lines(paths, "reach")]:
            print(line)
    if not reach_passed(analysis):
        raise CheckFailed("reach: " + reach_verdict(analysis).split("FAILS: ", 1)[1])
    return 0


def _reach_verdict_fields(reach: ReachAnalysis) -> dict[str, Any]:
    """The reach's verdict in its ``--json`` objects (``report reach``, ``report all``'s
    ``reach``): ``passed`` (what the exit code says) and ``verdict`` (the line's text). The
    report file holds the analysis only, as before."""
    from payload.envelope.verdict import reach_passed, reach_verdict

    return {
        "passed": reach_passed(reach),
        "verdict": reach_verdict(reach).removeprefix("verdict: "),
    }


def _all_verdict(envelope: EnvelopeAnalysis, reach: ReachAnalysis) -> str:
    """The one verdict line: ``verdict: passes: ...`` or ``verdict: FAILS: ...``."""
    from payload.envelope.fit_results import clearance_text
    from payload.envelope.verdict import (
        envelope_verdict,
        reach_passed,
        reach_verdict,
        sampling_caveat,
    )

    env_ok, reach_ok = envelope.passed, reach_passed(reach)
    if env_ok and reach_ok:
        given = envelope.given
        tightest = given.tightest
        thinnest = {
            p.name: min(g.feature.thickness for g in p.grasps if g.closes) for p in reach.pairs
        }
        closes = ", ".join(f"{name} down to {t * 1e3:.1f} mm" for name, t in thinnest.items())
        return (
            f"verdict: passes: the stowed payload {given.fits_words} (min clearance "
            f"{clearance_text(tightest.clearance)}, {tightest.name}{given.tight_tail}); every "
            f"pair closes on a CTB feature ({closes}){sampling_caveat(reach)}"
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
    _refuse_foreign_reports(args, "envelope", "reach")  # and another's reports, before both
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
            "reach": {**record(reach_json(reach)), **_reach_verdict_fields(reach)},
            "summary": summary,
        }
        emit_json(_stdout_json(args, data))
    else:
        print(verdict)
        where = project.relative(project.design_path)
        print(f"models: {'rebuilt (above)' if rebuilt else 'match ' + where}")
        from payload.envelope.markdown import assumption_line

        print(assumption_line(envelope))  # both reports' (the bays)
        print("-- envelope")
        print(envelope_verdict(envelope))
        for line in [*env_lines, *written_lines(env_paths, "envelope")]:
            print(line)
        print("-- reach")
        print(reach_verdict(reach))
        for line in [
            *reach_lines(reach, assumption=False),
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
        raise ReachError(f"--check-samples must be >= 1, got {args.check_samples}")
    if args.runs < 1:
        raise ReachError(f"--runs must be >= 1, got {args.runs}")
    project = _project(args)
    _models_follow(args)
    _, vehicle, geom = _load(args)
    r = run_reach_bench(
        geom, vehicle, project.root, project.analyses_dir, samples=args.samples,
        check_samples=args.check_samples, runs=args.runs, seed=args.seed,
        aim_samples=REACH_SAMPLES,
    )  # fmt: skip
    if args.json:
        emit_json({**r, "load_average": load_average()})
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
        "figures changed is always replaced: reports follow the design), or replace files "
        "in --out that are not this design's report",
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
        help="run the stowed-posture search even when the given posture stows",
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
        default=REACH_SAMPLES,
        help=f"sampled configurations, at least {MIN_SAMPLES:,} (default {REACH_SAMPLES:,})",
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
        default=REACH_SAMPLES,
        help=f"samples of the timed report, at least {MIN_SAMPLES:,} (default {REACH_SAMPLES:,})",
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
