"""``payload teleop serve`` and ``payload bench teleop``: the live Quest interface composed
with the trial-layer live session.

The teleoperation package provides the server, the options and the terminal output
(:mod:`payload.teleop.cli`); the session it drives records a trial, so it is composed
here, one layer up, and handed down as a factory.
"""

from __future__ import annotations

import argparse
from typing import Any

from payload.teleop.cli import (
    bench,
    bench_arguments,
    bench_filter,
    bench_filter_arguments,
    serve,
    serve_arguments,
)


def _live_session(*args: Any, **kwargs: Any) -> Any:
    from payload.trials.live import LiveSession

    return LiveSession(*args, **kwargs)


def _scored(result: dict[str, Any]) -> None:
    """A recorded live session once scored: what was written, and the trial's summary as
    ``payload trial`` prints it."""
    from payload.folders import SCORED
    from payload.trials.summary import print_trial_summary

    print(f"  scored: {', '.join(SCORED)} written")
    print_trial_summary(result)


def _cmd_serve(args: argparse.Namespace) -> int:
    return serve(args, _live_session, _scored)


def _cmd_bench(args: argparse.Namespace) -> int:
    return bench(args, _live_session)


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``teleop serve``, ``bench teleop`` and ``bench filter``."""
    teleop = sub.add_parser("teleop", help="the live Quest (WebXR) interface")
    tsub = teleop.add_subparsers(dest="teleop_command", required=True, metavar="WHAT")
    p = tsub.add_parser("serve", help="serve the WebXR page, its WebSocket and /status")
    serve_arguments(p)
    p.set_defaults(func=_cmd_serve)

    b = groups["bench"].add_parser(
        "teleop", help="latency of the live interface through an emulated Quest 3"
    )
    bench_arguments(b)
    b.set_defaults(func=_cmd_bench)

    f = groups["bench"].add_parser("filter", help="the base safety filter's cost per step")
    bench_filter_arguments(f)
    f.set_defaults(func=bench_filter)


__all__ = ["register"]
