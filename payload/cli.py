"""The ``payload`` command line (contract in DESIGN.md).

Every subcommand lives in a ``register(subparsers)`` function; a subcommand's
handler returns the exit code. Errors print one line on stderr and exit 2 (bad
input) or 1 (failed check).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from payload.errors import PayloadError, RunAborted

# Modules providing ``register(sub, groups)``; each adds its own subcommands to the top
# level (``sub``) or to a shared group (``groups["bench"]``, ``groups["report"]``,
# ``groups["export"]``). A module not written yet is skipped.
COMMAND_MODULES: tuple[str, ...] = (
    "payload.cli",
    "payload.retarget.cli",
    "payload.envelope.cli",
    "payload.sim.cli",
    "payload.teleop.cli",
    "payload.trials.cli",
    "payload.review.cli",
    "firmware_interface.cli",
)
GROUPS: dict[str, str] = {
    "bench": "benchmarks: production against reference, same run",
    "report": "reports written into analyses/",
    "export": "export recordings",
}


class CheckFailed(Exception):
    """A check ran and failed (exit 1)."""


def emit_json(obj: Any) -> None:
    """Print exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, sort_keys=False) + "\n")


def _cmd_build(args: argparse.Namespace) -> int:
    from payload.design import load_design, stale_files, write
    from payload.design.build import PROJECT_ROOT

    design = load_design(args.design)
    root = Path(args.root) if args.root else PROJECT_ROOT
    if args.design and not args.root and not args.check:
        root = _project_of(Path(args.design))  # F's own project, never this one's models
    t0 = time.perf_counter()
    if args.check:
        stale = stale_files(design, root)
        if stale:
            raise CheckFailed(
                f"stale: {', '.join(stale)} ({len(stale)} generated file(s) do not match "
                f"{design.source}; run `payload build`)"
            )
        print(f"generated files match {design.source} ({time.perf_counter() - t0:.2f} s)")
        return 0
    result = write(design, root)
    dt = time.perf_counter() - t0
    print(f"wrote {len(result.files)} files under {root} in {dt:.2f} s")
    return 0


def _project_of(design: Path) -> Path:
    """The design project whose ``cad/design.toml`` this is (where its models belong).

    Raises:
        PayloadError: The file is not a project's ``cad/design.toml``.
    """
    p = design.resolve()
    if p.name == "design.toml" and p.parent.name == "cad":
        return p.parent.parent
    raise PayloadError(
        f"{design}: not a design project's cad/design.toml, so its models have no project "
        "to go to; nothing written (make one with `payload new DIR`, or compare with "
        "--check)"
    )


def _cmd_summary(args: argparse.Namespace) -> int:
    from payload.design import load_design
    from payload.design.summary import print_summary, summarize

    design = load_design(args.design)
    summary = summarize(design)
    if args.json:
        emit_json(summary)
    else:
        print_summary(summary)
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    p = sub.add_parser("build", help="regenerate urdf/ and cad/meshes/ from the design")
    p.add_argument("--design", help="design TOML (default: cad/design.toml)")
    p.add_argument("--check", action="store_true", help="exit 1 naming every stale file")
    p.add_argument("--root", help=argparse.SUPPRESS)
    p.set_defaults(func=_cmd_build)

    p = sub.add_parser("summary", help="DoF, joint ranges, masses and bounding boxes")
    p.add_argument("--design", help="design TOML (default: cad/design.toml)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_summary)


class _Groups(dict):
    """Shared subcommand groups (``bench``, ``report``, ``export``), created on first use."""

    def __init__(self, sub: argparse._SubParsersAction) -> None:
        super().__init__()
        self._sub = sub

    def __missing__(self, name: str) -> argparse._SubParsersAction:
        group = self._sub.add_parser(name, help=GROUPS.get(name, name))
        self[name] = group.add_subparsers(dest=f"{name}_command", required=True, metavar="WHAT")
        return self[name]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="payload", description="Four-finger Astrobee payload workbench"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups = _Groups(sub)
    for name in COMMAND_MODULES:
        try:
            spec = importlib.util.find_spec(name)
        except ModuleNotFoundError:
            spec = None
        if spec is None:
            continue
        module = importlib.import_module(name)
        register_fn: Callable[..., None] = module.register
        register_fn(sub, groups)
    _strict(parser)
    return parser


def _strict(parser: argparse.ArgumentParser) -> None:
    """No abbreviated options anywhere (``--sample`` is not ``--samples``), and every
    (sub)command remembers its parser, so a wrong option prints that command's usage."""
    parser.allow_abbrev = False
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                child.set_defaults(_parser=child)
                _strict(child)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``payload`` console script; returns the exit code."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the usage of the subcommand given, not the top level's (exits 2)
        getattr(args, "_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return int(args.func(args) or 0)
    except CheckFailed as exc:
        print(f"payload: check failed: {exc}", file=sys.stderr)
        return 1
    except RunAborted as exc:
        print(f"payload: aborted: {exc}", file=sys.stderr)
        return 1
    except PayloadError as exc:
        print(f"payload: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("payload: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    # run the imported module's main so its exception classes are the ones raised
    from payload.cli import main as _main

    sys.exit(_main())
