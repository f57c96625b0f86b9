"""The ``payload`` command line (contract in DESIGN.md).

Every subcommand lives in a ``register(subparsers)`` function; a subcommand's
handler returns the exit code. Errors print one line on stderr and exit 2 (bad
input) or 1 (failed check).

A command that works on a design project calls :func:`command_project` once: it
finds the project (``--project DIR``, ``PAYLOAD_PROJECT``, the cwd upward, or the
project holding ``--design F``), prints ``project: <root>`` as the first line of
terminal output, and exports ``PAYLOAD_PROJECT`` for the rest of the command so
library defaults and worker processes use the same project. Its JSON carries
``"project"``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from payload.errors import PayloadError, RunAborted
from payload.project import ENV_VAR, Project, ProjectError, find_project, project_of

# Modules providing ``register(sub, groups)``; each adds its own subcommands to the top
# level (``sub``) or to a shared group (``groups["bench"]``, ``groups["report"]``,
# ``groups["export"]``). Every module must exist: none is skipped.
COMMAND_MODULES: tuple[str, ...] = (
    "payload.cli",
    "payload.retarget.cli",
    "payload.envelope.cli",
    "payload.sim.cli",
    "payload.teleop.cli",
    "payload.trials.cli",
    "payload.review.cli",
    "firmware_interface.cli",
    "payload.sweep.cli",
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


def command_project(args: argparse.Namespace, design: str | Path | None = None) -> Project:
    """The design project of this command, resolved once per command.

    ``design`` (a ``--design F``) selects the project holding F, so a command never
    writes another project's models; ``--project`` must then agree with it. A design
    file in no project applies to the project found as usual. Prints
    ``project: <root>`` unless the command prints JSON (``args.json``), and exports it
    as ``PAYLOAD_PROJECT`` until :func:`main` returns.

    Raises:
        ProjectError: No project, or ``--design`` and ``--project`` disagree.
    """
    cached = getattr(args, "_project", None)
    if cached is not None:
        return cached
    explicit = getattr(args, "project", None)
    if design is not None:
        owner = project_of(design)
        if owner is None:
            project = find_project(explicit)
        elif explicit is not None and find_project(explicit).root != owner.root:
            raise ProjectError(
                f"--design {design} belongs to project {owner.root}, not --project {explicit}"
            )
        else:
            project = owner
    else:
        project = find_project(explicit)
    args._project = project
    os.environ[ENV_VAR] = str(project.root)
    if not getattr(args, "json", False):
        print(f"project: {project.root}", flush=True)
    return project


def _cmd_build(args: argparse.Namespace) -> int:
    from payload.design import load_design, stale_files, write

    if args.root:  # hidden: generate into any folder (tests), no project involved
        design, root = load_design(args.design), Path(args.root)
    else:
        if args.design and not args.check:
            _check_own_design(Path(args.design))
        project = command_project(args, args.design)
        design, root = load_design(args.design or project.design_path), project.root
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


def _check_own_design(design: Path) -> None:
    """Building writes a design's models into its own project, so the design must be a
    project's ``cad/design.toml``.

    Raises:
        PayloadError: The file is not a project's ``cad/design.toml``.
    """
    owner = project_of(design)
    if owner is None or owner.design_path != design.expanduser().resolve():
        raise PayloadError(
            f"{design}: not a design project's cad/design.toml, so its models have no project "
            "to go to; nothing written (make one with `payload new DIR`, or compare with "
            "--check)"
        )


def _cmd_summary(args: argparse.Namespace) -> int:
    from payload.design import load_design
    from payload.design.summary import print_summary, summarize

    project = command_project(args, args.design)
    design = load_design(args.design or project.design_path)
    summary = summarize(design)
    if args.json:
        emit_json({**summary, "project": str(project.root)})
    else:
        print_summary(summary)
    return 0


def new_project(directory: str | Path, source: str | Path | None = None) -> tuple[Project, int]:
    """Create a design project in ``directory`` and build its models.

    Args:
        directory: The new project's folder: must not exist, or be empty.
        source: A project (or its design file) whose design is copied; ``None``: the
            packaged default design.

    Returns:
        The project and the number of generated files.

    Raises:
        ProjectError: ``directory`` is a non-empty folder or a file, or ``source`` is
            not a project.
        DesignError: The copied design is invalid (the folder is removed again).
    """
    from payload.design import load_design, write
    from payload.project import default_design_text

    target = Path(directory)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise ProjectError(f"{target}: not an empty folder; `payload new` needs a new one")
    if source is not None:
        src = Path(source)
        src_project = project_of(src) if src.is_file() else find_project(src)
        if src_project is None:
            raise ProjectError(f"--from {source}: not a design project")
        text = (src if src.is_file() else src_project.design_path).read_text(encoding="utf-8")
    else:
        text = default_design_text()
    created = not target.exists()
    project = Project.at(target)
    project.design_path.parent.mkdir(parents=True, exist_ok=True)
    project.design_path.write_text(text, encoding="utf-8")
    try:
        result = write(load_design(project.design_path), project.root)
    except PayloadError:
        if created:
            shutil.rmtree(project.root, ignore_errors=True)
        else:
            for child in list(project.root.iterdir()):
                shutil.rmtree(child) if child.is_dir() else child.unlink()
        raise
    return project, len(result.files)


def _cmd_new(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    project, n = new_project(args.dir, args.source)
    print(f"project: {project.root}")
    print(
        f"new design project from {args.source or 'the packaged default design'}: "
        f"{project.relative(project.design_path)} and {n} generated files in "
        f"{time.perf_counter() - t0:.2f} s"
    )
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    p = sub.add_parser("new", help="a new design project, built and ready")
    p.add_argument("dir", metavar="DIR", help="folder of the new project (new or empty)")
    p.add_argument(
        "--from",
        dest="source",
        metavar="PROJECT",
        help="copy this project's design (default: the packaged default design)",
    )
    p.set_defaults(func=_cmd_new)

    p = sub.add_parser("build", help="regenerate urdf/ and cad/meshes/ from the design")
    p.add_argument(
        "--design", help="design TOML (default: cad/design.toml); builds the project holding it"
    )
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
    from payload import __version__

    parser = argparse.ArgumentParser(
        prog="payload", description="Four-finger Astrobee payload workbench"
    )
    parser.add_argument("--version", action="version", version=f"payload {__version__}")
    parser.add_argument(
        "--project",
        metavar="DIR",
        help="design project to work on (default: $PAYLOAD_PROJECT, else the current "
        "directory or the nearest parent holding cad/design.toml)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups = _Groups(sub)
    for name in COMMAND_MODULES:  # every one is part of the package: a missing one is a bug
        module = importlib.import_module(name)
        register_fn: Callable[..., None] = module.register
        register_fn(sub, groups)
    _add_project_option(parser)
    _strict(parser)
    return parser


def _add_project_option(parser: argparse.ArgumentParser) -> None:
    """Accept ``--project DIR`` after any (sub)command too: ``payload build --project X``."""
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        for child in action.choices.values():
            if not any("--project" in a.option_strings for a in child._actions):
                child.add_argument(
                    "--project",
                    metavar="DIR",
                    default=argparse.SUPPRESS,
                    help="design project to work on (see `payload --help`)",
                )
            _add_project_option(child)


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
    saved = os.environ.get(ENV_VAR)
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
    finally:  # command_project exported the project for this command only
        if saved is None:
            os.environ.pop(ENV_VAR, None)
        else:
            os.environ[ENV_VAR] = saved


if __name__ == "__main__":  # pragma: no cover
    # run the imported module's main so its exception classes are the ones raised
    from payload.cli import main as _main

    sys.exit(_main())
