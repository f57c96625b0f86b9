"""The ``payload`` command line (contract in docs/cli.md): the dispatcher at the top.

Every command lives in a command module's ``register(sub, groups)``; its handler returns
the exit code. Errors print one line on stderr and exit 2 (bad input) or 1 (failed check).
What the commands share (project resolution, ``--json`` output, check failures, the shared
options) lives in :mod:`payload.cliutil`, below every command module: no command module
imports this one.

Command modules load on first use. :data:`COMMANDS` names every command with its module
and its help, so ``payload --help`` (and ``payload bench --help``) list every command
without importing any command module, and ``payload <command>`` imports only the module
of that command. ``tests/test_cli.py`` checks the table against what the modules register.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, NamedTuple, NoReturn

from payload.cliutil import (
    CheckFailed,
    OneLineParser,
    command_project,
    emit_json,
    forget_project,
    log_lines,
)
from payload.errors import STOP_SIGNALS, PayloadError, RunAborted, Terminated
from payload.project import ENV_VAR

PROJECT_OPTION = "--project"
"""The one option every level takes (``payload --project DIR build``, ``payload build
--project DIR``), with its value."""

VERSION_OPTION = "--version"
"""The top level's own option (``payload --version``)."""


class Command(NamedTuple):
    """One command of the table: its words, the module registering it, its help line."""

    path: str
    module: str
    help: str


# One line per command: "words", module whose register() adds it, the help it registers.
# A command inside a shared group (bench, report, export) is "group name"; a command with
# subcommands of its own (hw, teleop, trials) is one line.
COMMANDS: tuple[Command, ...] = (
    Command("new", "payload.design.cli", "a new design project, built and ready"),
    Command("build", "payload.design.cli", "regenerate urdf/ and cad/meshes/ from the design"),
    Command("summary", "payload.design.cli", "DoF, joint ranges, masses and bounding boxes"),
    Command(
        "report envelope",
        "payload.envelope.cli",
        "stowed fit in the two lower bays, self-collision, deployment sweep",
    ),
    Command(
        "report reach",
        "payload.envelope.cli",
        "fingertip workspaces, pair spans, rail spacing, CTB grasp check",
    ),
    Command(
        "report all",
        "payload.envelope.cli",
        "models, envelope, reach and design summary in one run, one verdict line",
    ),
    Command(
        "review", "payload.review.cli", "Meshcat design review (and trial replay) in the browser"
    ),
    Command("bench filter", "payload.trials.live_cli", "the base safety filter's cost per step"),
    Command(
        "bench reach",
        "payload.envelope.cli",
        "the reach check against MuJoCo's collision, same run; the report's time",
    ),
    Command("trial", "payload.trials.cli", "one ISS cargo-transport trial"),
    Command("trials", "payload.trials.cli", "trial campaigns and their summaries"),
    Command("export lerobot", "payload.trials.cli", "recordings as a LeRobot v3 dataset"),
    Command(
        "sweep",
        "payload.sweep.cli",
        "a design sweep on Dask: every combination of --set values, each a project",
    ),
    Command("teleop", "payload.trials.live_cli", "the live Quest (WebXR) interface"),
    Command("hw", "firmware_interface.cli", "the Dynamixel hardware and its emulator"),
    Command(
        "bench retarget",
        "payload.retarget.cli",
        "production (CasADi) against reference (scipy) retargeting, same run",
    ),
    Command(
        "bench sim",
        "payload.sim.cli",
        "real-time factor of the full CTB scene under the 50 Hz loop",
    ),
    Command(
        "bench teleop",
        "payload.trials.live_cli",
        "latency of the live interface through an emulated Quest 3",
    ),
    Command("bench recorder", "payload.trials.bench_cli", "trial recorder cost and file size"),
    Command(
        "bench trial",
        "payload.trials.bench_cli",
        "a trial's real-time factor, time breakdown and log size",
    ),
    Command(
        "bench start",
        "payload.trials.bench_cli",
        "how quickly commands start, each in fresh processes",
    ),
    Command("bench hw", "firmware_interface.cli", "sync write + fast sync read cycle vs wire time"),
)
"""Every command: one line each (see docs/cli.md, "Adding a command")."""

GROUPS: dict[str, str] = {
    "bench": "benchmarks: speed, cost and latency (trial, sim, retarget, reach, hw, ...)",
    "report": "reports written into analyses/",
    "export": "export recordings",
}
"""Shared groups whose subcommands come from several modules."""

COMMAND_MODULES: tuple[str, ...] = tuple(dict.fromkeys(c.module for c in COMMANDS))
"""Every command module, in the table's order."""

__all__ = [
    "COMMANDS",
    "COMMAND_MODULES",
    "GROUPS",
    "CheckFailed",
    "Command",
    "build_parser",
    "command_project",
    "emit_json",
    "main",
    "registered_commands",
    "run",
]


class _Groups(dict):
    """Shared subcommand groups (``bench``, ``report``, ``export``), created on first use."""

    def __init__(self, sub: argparse._SubParsersAction) -> None:
        super().__init__()
        self._sub = sub

    def __missing__(self, name: str) -> argparse._SubParsersAction:
        group = self._sub.add_parser(name, help=GROUPS.get(name, name))
        self[name] = group.add_subparsers(dest=f"{name}_command", required=True, metavar="WHAT")
        return self[name]


def _register(module: str, sub: argparse._SubParsersAction, groups: _Groups) -> None:
    register_fn: Callable[..., None] = importlib.import_module(module).register
    register_fn(sub, groups)


def _placeholders(sub: argparse._SubParsersAction, groups: _Groups) -> None:
    """A parser with only its help line for every command no loaded module registered,
    so every command is listed; choosing one loads its module (:func:`main`)."""
    for cmd in COMMANDS:
        *group, name = cmd.path.split()
        target = groups[group[0]] if group else sub
        if name not in target.choices:
            target.add_parser(name, help=cmd.help).set_defaults(_lazy_module=cmd.module)


def build_parser(modules: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``payload`` parser.

    Args:
        modules: Command modules to load and register fully; the other commands are
            listed with their help only. ``None``: every module (the whole tree).
    """
    from payload import __version__

    parser = OneLineParser(prog="payload", description="Four-finger Astrobee payload workbench")
    parser.add_argument(VERSION_OPTION, action="version", version=f"payload {__version__}")
    parser.add_argument(
        PROJECT_OPTION,
        metavar="DIR",
        help="design project to work on (default: $PAYLOAD_PROJECT, else the current "
        "directory or the nearest parent holding cad/design.toml)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups = _Groups(sub)
    wanted = set(COMMAND_MODULES if modules is None else modules)
    if not wanted:  # listing only: the table's order
        _placeholders(sub, groups)
    for name in COMMAND_MODULES:  # every one is part of the package: a missing one is a bug
        if name in wanted:
            _register(name, sub, groups)
    _placeholders(sub, groups)
    _add_project_option(parser)
    _strict(parser)
    return parser


def registered_commands(module: str) -> dict[str, str]:
    """What ``module``'s ``register()`` adds: ``{"words": help}`` (for the table's test)."""
    root = argparse.ArgumentParser(add_help=False)
    sub = root.add_subparsers(dest="command")
    groups = _Groups(sub)
    _register(module, sub, groups)
    found: dict[str, str] = {}
    for choice in sub._choices_actions:
        if choice.dest not in groups:
            found[choice.dest] = choice.help or ""
    for name, group in groups.items():
        for choice in group._choices_actions:
            found[f"{name} {choice.dest}"] = choice.help or ""
    return found


def _tokens(argv: Sequence[str]) -> Iterator[tuple[int, str]]:
    """``argv``'s tokens with their places, but ``--project`` and its value (taken at
    every level, so never a command's word nor an option out of place)."""
    skip = False
    for k, token in enumerate(argv):
        if skip:
            skip = False
        elif token == PROJECT_OPTION:
            skip = True
        else:
            yield k, token


def _modules_for(argv: Sequence[str]) -> set[str]:
    """The command module ``argv`` selects (none for ``--help``, ``--version`` or a group's
    own help): the first words that are not options, matched against :data:`COMMANDS`."""
    words: list[str] = []
    for _, token in _tokens(argv):
        if not token.startswith("-"):
            words.append(token)
            if len(words) == 2:
                break
    for cmd in COMMANDS:
        parts = cmd.path.split()
        if words[: len(parts)] == parts:
            return {cmd.module}
    return set()


def _add_project_option(parser: argparse.ArgumentParser) -> None:
    """Accept ``--project DIR`` after any (sub)command too: ``payload build --project X``."""
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        for child in action.choices.values():
            if not any(PROJECT_OPTION in a.option_strings for a in child._actions):
                child.add_argument(
                    PROJECT_OPTION,
                    metavar="DIR",
                    default=argparse.SUPPRESS,
                    help="design project to work on (see `payload --help`)",
                )
            _add_project_option(child)


FOLDER_METAVAR = "DIR"
"""How the help names a folder: the contract's ``--out DIR`` (docs/cli.md, "One
vocabulary"), and a positional folder argument (``dir``)."""


def _strict(parser: argparse.ArgumentParser) -> None:
    """No abbreviated options anywhere (``--sample`` is not ``--samples``), and every
    (sub)command remembers its parser, so a wrong option prints that command's usage.
    An ``--out`` or a ``dir`` argument without a metavar of its own is shown as
    :data:`FOLDER_METAVAR` (argparse's default read ``--out OUT``, ``dir``)."""
    parser.allow_abbrev = False
    for action in parser._actions:
        if action.metavar is None and (
            "--out" in action.option_strings or (not action.option_strings and action.dest == "dir")
        ):
            action.metavar = FOLDER_METAVAR
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                child.set_defaults(_parser=child)
                _strict(child)


ANYWHERE = ("-h", "--help", PROJECT_OPTION)
"""Options every level of the command tree takes."""


def _parses(argv: Sequence[str]) -> bool:
    """Whether ``argv`` parses whole (no error, nothing left over), saying nothing."""
    import contextlib
    import io

    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            _, unknown = build_parser(_modules_for(argv)).parse_known_args(list(argv))
    except SystemExit:
        return False
    return not unknown


def _subcommands(words: list[str]) -> list[str]:
    """The subcommands the command ``words`` (a whole path of :data:`COMMANDS`) registers
    itself (``hw``'s ``check``, ``scan``...), from its module's parser; none for most."""
    parser: argparse.ArgumentParser = build_parser(_modules_for(words))
    for word in [*words, None]:
        found = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not found:
            return []
        if word is None:
            return list(found[0].choices)
        parser = found[0].choices[word]
    return []


def _option_before_command(argv: Sequence[str]) -> str | None:
    """What is wrong when a command's option comes before the command's name, at the top
    (``payload --samples 2000 report reach``: argparse took ``2000`` for the command) or
    in a group (``payload report --samples 2000 reach``), with the command line put in
    order when one parses; ``None`` when every option before the command is one its level
    takes (a misspelt command is argparse's to say)."""
    paths = [cmd.path.split() for cmd in COMMANDS]
    words: list[str] = []  # the command's words so far: a group's, until the command's
    at = None
    for k, token in _tokens(argv):
        if token.startswith("-"):
            name = token.split("=", 1)[0]
            if name not in ANYWHERE and not (name == VERSION_OPTION and not words):
                if words in paths:  # a whole command: its options, unless it has
                    subs = _subcommands(words)  # subcommands of its own (``hw check``)
                    if not subs:
                        return None
                    paths += [[*words, sub] for sub in subs]
                at = k  # an option before the command's last word
                break
        else:
            words.append(token)
            if not any(p[: len(words)] == words for p in paths):
                return None  # the whole command (its options follow), or not one
    if at is None:
        return None
    name, group, rest = argv[at].split("=", 1)[0], argv[:at], argv[at:]
    for j, token in enumerate(rest):  # the command line with the command's name first
        ordered = [*group, *rest[j:], *rest[:j]]
        named = any(p[: len(words) + 1] == [*words, token] for p in paths)
        if named and _parses(ordered):
            return f"{name} goes after the command: payload {' '.join(ordered)}"
    where = " ".join(["payload", *words, "COMMAND"])
    return f"{name} goes after the command's name ({where} {name} ...)"


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    argv = list(sys.argv[1:] if argv is None else argv)
    if (misplaced := _option_before_command(argv)) is not None:
        OneLineParser(prog="payload").exit(2, f"payload: error: {misplaced}\n")
    modules = _modules_for(argv)
    parser = build_parser(modules)
    args, unknown = parser.parse_known_args(argv)
    lazy = getattr(args, "_lazy_module", None)
    if lazy is not None and lazy not in modules:  # an order the word scan did not foresee
        parser = build_parser({lazy})
        args, unknown = parser.parse_known_args(argv)
    if unknown:  # the usage of the subcommand given, not the top level's (exits 2)
        getattr(args, "_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    return args


COMMAND_ENV: dict[str, str] = {"MUJOCO_GL": "disable"}
"""Environment every command runs with, unless the user set the variable: no command
renders with MuJoCo, and MuJoCo's import otherwise loads GLFW (which starts a Python
process to read the library's version), a tenth of a second or more in every process
that simulates, each Dask worker of a campaign included (they inherit it)."""


def _stdout_gone() -> bool:
    """Whether standard output is a pipe whose reader has gone (its write end polls as an
    error)."""
    import select

    try:
        poll = select.poll()
        poll.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poll.poll(0))
    except (OSError, ValueError, AttributeError):  # no such stream, or no poll here
        return False


def _terminate(signum: int, frame: Any) -> None:
    """SIGTERM or SIGHUP: stop as Ctrl-C stops, with every command's clean-up."""
    raise Terminated(signum)


def _terminated(exc: Terminated) -> int:
    """Say the command was stopped by a signal, and what it kept (the notes its clean-up
    added: a recording marked aborted, say); its exit code (128 + the signal)."""
    print(f"payload: terminated ({exc}){_kept(exc)}", file=sys.stderr)
    return 128 + exc.signum


def _kept(exc: BaseException) -> str:
    """What the command's clean-up said it kept (the exception's notes), after a "; "."""
    notes = getattr(exc, "__notes__", None) or []
    return "".join(f"; {note}" for note in notes)


def _default(signals: list[signal.Signals]) -> None:
    for signum in signals:
        signal.signal(signum, signal.SIG_DFL)


def run() -> NoReturn:
    """The ``payload`` console script and ``python -m payload``: :func:`main`, then exit.

    Before the interpreter shuts down, the objects still alive are moved out of the cyclic
    garbage collector's reach (``gc.freeze``): Python's shutdown otherwise ends with a
    full collection over a heap holding MuJoCo, Numba, SciPy and the rest, 0.3 to 0.4 s
    after a command on this machine (measured after ``report reach``), to free memory the
    process's exit frees anyway. Exit handlers (temporary folders, worker pools) still run
    and objects freed by reference counting are still finalized; the commands close
    their own files. Garbage in reference cycles is not, so when manifold3d (a nanobind
    extension) is loaded, it is collected first: nanobind reports every object of its
    still alive at exit as a leak, dozens of lines on stderr (after ``report reach`` the
    first import of matplotlib, in the figure's frames, leaves such cycles holding the
    geometry's solids); the collection costs about 0.05 s there.
    """
    # not where they are ignored (nohup); a forked worker (a multiprocessing pool's) keeps
    # the default: its pool ends it with SIGTERM
    taken = [s for s in STOP_SIGNALS if signal.getsignal(s) is signal.SIG_DFL]
    for signum in taken:
        signal.signal(signum, _terminate)
    os.register_at_fork(after_in_child=lambda: _default(taken))
    try:
        code = main()
    except Terminated as exc:  # outside the command's own handling: parsing the line
        code = _terminated(exc)
    except BrokenPipeError:
        if not _stdout_gone():  # another pipe broke: an error like any other
            raise
        # the reader of stdout went away (`payload ... | head`): end quietly, as a tool
        # SIGPIPE ends (128 + 13); what the command wrote to its files stands
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 141
    _default(taken)  # a signal during the shutdown below ends the process as it would
    if "manifold3d" in sys.modules:
        gc.collect()
    gc.freeze()
    sys.exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: parse ``argv`` (default ``sys.argv[1:]``), run the command, and
    return the exit code (the console script is :func:`run`)."""
    args = _parse(argv)
    forget_project()  # this command resolves its own (command_project)
    saved = os.environ.get(ENV_VAR)
    added = [k for k in COMMAND_ENV if k not in os.environ]
    os.environ.update({k: COMMAND_ENV[k] for k in added})
    try:
        with log_lines():
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
    except Terminated as exc:
        return _terminated(exc)
    except KeyboardInterrupt as exc:
        print(f"payload: interrupted{_kept(exc)}", file=sys.stderr)
        return 130
    finally:  # command_project exported the project for this command only
        forget_project()
        for k in added:
            os.environ.pop(k, None)
        if saved is None:
            os.environ.pop(ENV_VAR, None)
        else:
            os.environ[ENV_VAR] = saved


if __name__ == "__main__":  # pragma: no cover
    # run the imported module's main so its exception classes are the ones raised
    from payload.cli import main as _main

    sys.exit(_main())
