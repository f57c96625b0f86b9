"""``payload report all``: the models, the envelope, the reach and the design summary in
one run, led by one verdict line."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from payload.envelope import cli as report_cli

if TYPE_CHECKING:
    from payload.envelope.fit_results import EnvelopeAnalysis
    from payload.envelope.reach import ReachAnalysis


def _verdict(envelope: EnvelopeAnalysis, reach: ReachAnalysis) -> str:
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


def report_all(args: argparse.Namespace) -> int:
    """Run ``payload report all``; returns 0 when the design passes, else raises.

    Raises:
        CheckFailed: The stowed payload or the grasp check fails (exit 1).
    """
    from payload.cli import CheckFailed, emit_json
    from payload.design import load_design, models_follow_design
    from payload.design.summary import print_summary, summarize
    from payload.envelope.report import envelope_json, reach_json
    from payload.envelope.verdict import (
        envelope_verdict,
        reach_passed,
        reach_verdict,
    )

    project = report_cli._project(args)
    report_cli._check_reach_args(args)  # bad numbers: exit 2 before any work
    rebuilt = models_follow_design(project.design_path, project.root, json=args.json)
    envelope, env_paths, env_lines = report_cli.run_envelope(args)
    reach, reach_paths = report_cli.run_reach(args)
    design = load_design(report_cli._design_path(args))
    summary = summarize(design)
    env_ok, reach_ok = envelope.passed, reach_passed(reach)
    verdict = _verdict(envelope, reach)
    if args.json:
        record = report_cli._recorder(args)
        data: dict[str, Any] = {
            "passed": env_ok and reach_ok,
            "verdict": verdict.removeprefix("verdict: "),
            "models": {"rebuilt": rebuilt},
            "envelope": record(envelope_json(envelope)),
            "reach": record(reach_json(reach)),
            "summary": summary,
        }
        emit_json(report_cli._stdout_json(args, data))
    else:
        print(verdict)
        where = project.relative(project.design_path)
        print(f"models: {'rebuilt (above)' if rebuilt else 'match ' + where}")
        print("-- envelope")
        print(envelope_verdict(envelope))
        for line in [*env_lines, *report_cli.written_lines(env_paths, "envelope")]:
            print(line)
        print("-- reach")
        print(reach_verdict(reach))
        for line in [
            *report_cli.reach_lines(reach),
            *report_cli.written_lines(reach_paths, "reach"),
        ]:
            print(line)
        print("-- design summary")
        print_summary(summary)
    if not (env_ok and reach_ok):
        raise CheckFailed(verdict.removeprefix("verdict: FAILS: "))
    return 0


__all__ = ["report_all"]
