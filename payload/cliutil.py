"""What every command of the ``payload`` command line shares, below every command module.

A command module (``payload/<package>/cli.py``, ``firmware_interface/cli.py``) takes its
helpers from here, never from :mod:`payload.cli` (the dispatcher at the top):

- :class:`CheckFailed` (a check ran and failed: exit 1), :func:`emit_json` (``--json``
  prints exactly one JSON object);
- :func:`command_project`: the design project of a command, resolved once, printed as the
  first line (``project: <root>``) and exported as ``PAYLOAD_PROJECT`` for the command;
- the shared options of the vocabulary (docs/cli.md): :func:`add_json`, :func:`add_device`
  (a serial device), :func:`add_replay` (a recording), and :class:`DeprecatedAlias` for
  an old spelling kept for one release with a warning;
- :func:`default_out`: the numbered default folder of an ``--out`` left out;
  :func:`results_folder`: a command's results folder (its ``--out``, or that default),
  removed again when the command made it and fails before writing in it.

This module imports only the standard library, :mod:`payload.errors`, :mod:`payload.safeio`,
:mod:`payload.folders` and :mod:`payload.project`, so every
command (``--help`` and ``--version`` included) starts without the numerical stack.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from payload.errors import PayloadError, closest
from payload.folders import HANDS, RECORDING, held
from payload.project import (
    DESIGN_FILE,
    ENV_VAR,
    Project,
    ProjectError,
    find_project,
    is_project_design,
    project_of,
)
from payload.safeio import cannot_write_in

DESIGN_NAME = Path(DESIGN_FILE).name
"""The design file's name in a project's ``cad/`` folder."""


class CheckFailed(Exception):
    """A check ran and failed (exit 1)."""


class UsageError(PayloadError):
    """Bad command-line input shared by every command (exit 2)."""


def check_seconds(option: str, value: float | None, *, cap: bool = False) -> None:
    """Refuse a duration option that is not a positive number of seconds (``None``: not
    given). NaN and negative values are refused; infinity too, unless the option is a
    cap (``cap``: no cap, the run ends by itself).

    Raises:
        UsageError: ``"<option> must be a positive number of seconds, got <value>"``.
    """
    if value is None or (value > 0 and (cap or value != float("inf"))):
        return
    finite = "" if cap else "finite "
    raise UsageError(f"{option} must be a positive {finite}number of seconds, got {value}")


_RESOLVED: dict[str, Path] = {}
"""The design project the running command resolved (:func:`command_project`), until
:func:`payload.cli.main` returns (:func:`forget_project`)."""


def emit_json(obj: Any) -> None:
    """Print exactly one JSON object on stdout; a command that works on a design project
    (it resolved one with :func:`command_project`) carries its root as ``"project"``."""
    root = _RESOLVED.get("project")
    if root is not None and isinstance(obj, dict) and "project" not in obj:
        obj = {**obj, "project": str(root)}
    sys.stdout.write(json.dumps(obj, sort_keys=False) + "\n")


def forget_project() -> None:
    """End of a command: the next one resolves its own project (:func:`command_project`)."""
    _RESOLVED.clear()


def command_project(
    args: argparse.Namespace, design: str | Path | None = None, *, announce: bool = True
) -> Project:
    """The design project of this command, resolved once per command.

    ``design`` (a ``--design F``) selects the project holding F, so a command never
    writes another project's models; ``--project`` must then agree with it. A design
    file in no project applies to the project found as usual. Prints
    ``project: <root>`` unless the command prints JSON (``args.json``) or is told not to
    (``announce``: ``hw emulate``, whose first line is its pty's path), and exports it as
    ``PAYLOAD_PROJECT`` until :func:`payload.cli.main` returns.

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
    _RESOLVED["project"] = project.root
    os.environ[ENV_VAR] = str(project.root)
    if announce and not getattr(args, "json", False):
        print(f"project: {project.root}", flush=True)
    return project


def load_average() -> list[float]:
    """The machine's 1, 5 and 15 min load averages now, to two decimals: every bench's
    JSON carries them as ``load_average`` (a figure is read beside the load it ran at)."""
    return [round(x, 2) for x in os.getloadavg()]


def say_stage(line: str) -> None:
    """A set-up stage's line on stderr, before a stage that takes seconds or moves the
    servos (stdout keeps the result, or ``--json``'s object)."""
    print(f"{line} ...", file=sys.stderr, flush=True)


def warn(message: str) -> None:
    """One warning line on stderr (``payload: warning: ...``)."""
    print(f"payload: warning: {message}", file=sys.stderr, flush=True)


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose refusals are one line on stderr and exit 2, as every other
    bad input's (``payload trial: error: unrecognized arguments: --sede 3 (did you mean
    --seed?); see payload trial --help``): argparse printed the command's whole usage
    above it. A misspelt option or choice is matched against the parser's own."""

    _given: list[str] | None = None  # the arguments this parser was asked to parse

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self._given = None if args is None else list(args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        if message.startswith("the following arguments are required: "):
            # a misspelt option (--sett for --set) is the cause: argparse names only the
            # missing one, before the unrecognised it would have said after
            unknown = [
                a
                for a in self._given or []
                if a.startswith("--") and a.split("=", 1)[0] not in self._option_string_actions
            ]
            if unknown:
                message = f"unrecognized arguments: {' '.join(unknown)}"
        hint = self._did_you_mean(message)
        self.exit(2, f"{self.prog}: error: {message}{hint}; see {self.prog} --help\n")

    def _did_you_mean(self, message: str) -> str:
        import re

        choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)$", message)
        if choice:
            options = [c.strip().strip("'") for c in choice.group(2).split(",")]
            close = closest(choice.group(1), options)
            return f" (did you mean {close!r}?)" if close else ""
        if not message.startswith("unrecognized arguments: "):
            return ""
        known = {o[2:]: o for o in self._option_string_actions if o.startswith("--")}
        names = [w.split("=", 1)[0] for w in message.split(": ", 1)[1].split()]
        near = {  # the names without their dashes: "--" alone made --bogus near --out
            n: known[m] for n in names if n.startswith("--") and (m := closest(n[2:], known))
        }
        if len(near) == 1:
            return f" (did you mean {next(iter(near.values()))}?)"
        said = ", ".join(f"{m} for {n}" for n, m in near.items())
        return f" (did you mean {said}?)" if near else ""


OUR_LOGGERS = ("payload", "firmware_interface")
"""The workbench's loggers: their records name their part themselves ("finger chain:
..."); another library's record is prefixed with its logger's name."""


class _CommandLines(logging.Handler):
    """A command's log records on the stderr of the moment, as the command line's own
    lines: a warning as ``payload: warning: ...`` (:func:`warn`'s form), an error as
    ``payload: ...`` with its traceback when it carries one."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            ours = record.name.split(".", 1)[0] in OUR_LOGGERS
            text = record.getMessage() if ours else f"{record.name}: {record.getMessage()}"
            head = "payload: warning: " if record.levelno < logging.ERROR else "payload: "
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            print(head + text, file=sys.stderr, flush=True)
        except Exception:  # a logging handler never raises into the command
            self.handleError(record)


@contextlib.contextmanager
def log_lines() -> Iterator[None]:
    """For one command: log records of WARNING and above on stderr as the command line's
    lines (:class:`_CommandLines`; without it Python prints a bare message, with no
    ``payload: warning:``). A command that sets up its own logging (``teleop serve``'s
    status line) takes it off first (:func:`drop_log_lines`); the root logger's handlers
    are as before afterwards."""
    root = logging.getLogger()
    before = root.handlers[:]
    handler = _CommandLines()
    root.addHandler(handler)
    try:
        yield
    finally:
        for added in [h for h in root.handlers if h not in before]:
            root.removeHandler(added)
            if added is not handler:
                added.close()


def drop_log_lines() -> None:
    """Take :func:`log_lines`' handler off the root logger, for a command that formats its
    own records (then ``logging.basicConfig`` installs its handler)."""
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _CommandLines)]:
        root.removeHandler(handler)


class DeprecatedAlias(argparse.Action):
    """An old option spelling kept for one release: stores into the new option's ``dest``
    and prints one warning line naming the new spelling.

    Use through :func:`add_deprecated`.
    """

    def __init__(self, option_strings: Sequence[str], dest: str, new: str = "", **kw: Any):
        self.new = new
        super().__init__(option_strings, dest, **kw)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        warn(f"{option_string} is deprecated here; use {self.new} (the old spelling goes in a "
             "later release)")  # fmt: skip
        setattr(namespace, self.dest, values)


def add_deprecated(
    p: argparse.ArgumentParser, old: str, new: str, dest: str, **kw: Any
) -> argparse.Action:
    """Add ``old`` as a deprecated alias of the option ``new`` (same ``dest``).

    The alias's help says it is deprecated and names ``new``; using it prints a warning.
    """
    extra = kw.pop("help", "")
    text = f"deprecated spelling of {new}" + (f" ({extra})" if extra else "")
    return p.add_argument(
        old, dest=dest, action=DeprecatedAlias, new=new, default=argparse.SUPPRESS, help=text, **kw
    )


def add_json(p: argparse.ArgumentParser) -> None:
    """``--json``: print one JSON object on stdout."""
    p.add_argument("--json", action="store_true", help="print one JSON object")


def add_device(
    p: argparse.ArgumentParser,
    help: str = "serial device of the servo bus (or an emulator's pty)",
    *,
    old_port: bool = False,
) -> None:
    """``--device DEV``, the serial device; with ``old_port`` the earlier ``--port`` spelling
    is kept as a deprecated alias. A command that needs a device checks it with
    :func:`need_device` (argparse cannot require one of two spellings)."""
    p.add_argument("--device", metavar="DEV", default=None, help=help)
    if old_port:
        add_deprecated(p, "--port", "--device", "device", metavar="DEV")


def need_device(args: argparse.Namespace) -> str:
    """The ``--device`` of a command that needs one.

    Raises:
        UsageError: None given.
    """
    device = getattr(args, "device", None)
    if not device:
        raise UsageError("--device DEV is required (the servo bus's serial device or pty)")
    return str(device)


def add_replay(p: argparse.ArgumentParser, what: str) -> None:
    """``--replay FILE``: a recording to replay (``what`` says which files it takes)."""
    p.add_argument("--replay", metavar="FILE", default=None, help=what)


def replay_file(option: str, replay: Path) -> Path:
    """The recording a replay option names, or one line saying why it is not one (a
    trial's folder names the file in it to give)."""
    if replay.is_dir():
        inside = [n for n in (RECORDING, HANDS) if (replay / n).is_file()]
        hint = f": give {replay / inside[0]}" if inside else ""
        raise UsageError(f"{option}: {replay}: is a folder, not a recording{hint}")
    if not replay.exists():
        raise UsageError(f"{option}: {replay}: no such file")
    if not replay.is_file():
        raise UsageError(f"{option}: {replay}: not a regular file (a recording is one)")
    return replay


@contextlib.contextmanager
def kept_if_used(folder: Path, made: bool) -> Iterator[Path]:
    """``folder``, the results' folder of a command; one made for it (``made``: a numbered
    default, or an ``--out`` that did not exist) and still empty when the command fails
    is removed, so a failed command leaves nothing behind (nor uses up a number)."""
    try:
        yield folder
    except BaseException:
        if made and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise


def out_folder(
    value: str | Path | None, option: str = "--out", *, holding: tuple[str, ...] = ()
) -> Path | None:
    """A results folder option (``--out``) as given: None when left out. One line (a
    :class:`UsageError`, exit 2) when it names something that is not a folder, or a folder
    already holding any of the files ``holding`` (another command's results, which this
    command must not write among)."""
    if value is None or value == "":
        return None
    path = Path(value)
    for part in (path, *path.parents):  # a file on the way cannot hold a folder either
        if part.exists() and not part.is_dir():
            where = "" if part == path else f" ({part} is a file)"
            raise UsageError(f"{option} {value}: not a folder{where}")
    there = held(path, holding)
    if there:
        raise UsageError(
            f"{option} {value}: already holds {', '.join(there)}; choose another folder "
            "(results are never overwritten)"
        )
    for design, what in ((path / DESIGN_FILE, "folder"), (path / DESIGN_NAME, "cad/ folder")):
        if design.is_file() and is_project_design(design):  # a project's own files
            raise UsageError(
                f"{option} {value}: is a design project's {what}; results go in a folder of "
                "their own (left out: a new numbered one in the project's runs/)"
            )
    problem = _cannot_make(path)
    if problem is not None:
        raise UsageError(f"{option} {value}: cannot make the folder ({problem})")
    problem = cannot_write_in(path) if path.is_dir() else None
    if problem is not None:
        raise UsageError(f"{option} {value}: cannot write in the folder ({problem})")
    return path


def _cannot_make(path: Path) -> str | None:
    """Why the folder ``path`` could not be made (None: it exists, or it can be): tried
    before the work whose results go there, by making the missing folders and removing
    them again (the file system's own answer: permissions, read-only or virtual file
    systems, a name too long). Only folders that were not there are removed, and only
    while empty (another command making the same folder in that instant keeps it if it
    wrote in it)."""
    path = Path(os.path.abspath(path))  # "new/.." is the folder it names, no parent made
    missing = [p for p in (path, *path.parents) if not p.exists()]
    if not missing:
        return None
    try:
        path.mkdir(parents=True)
    except OSError as exc:
        return exc.strerror or str(exc)
    finally:
        for made in missing:  # deepest first; only what this probe made (and left empty)
            with contextlib.suppress(OSError):
                made.rmdir()
    return None


def default_out(project: Project, prefix: str) -> Path:
    """A new numbered folder ``runs/<prefix>-NNNN`` of ``project`` (created), for an
    ``--out`` left out."""
    from payload.safeio import numbered_folder

    return numbered_folder(project.runs_dir, prefix)


@contextlib.contextmanager
def results_folder(
    value: str | Path | None, project: Project | None, prefix: str, *, resolve: bool = False
) -> Iterator[Path]:
    """The results folder of a command: its ``--out`` (``value``; ``resolve``: as an
    absolute path) or, left out, a new numbered ``runs/<prefix>-NNNN`` of ``project``
    (:func:`default_out`; ``project`` may be None only with an ``--out``), kept only if
    used (:func:`kept_if_used`: a folder made for the command, the default or an ``--out``
    that did not exist, is removed if the command fails while it is still empty; an empty
    ``value`` is an ``--out`` left out). Callers check an ``--out`` with
    :func:`out_folder` first."""
    made = not value or not Path(value).exists()
    if value:
        out = Path(value).resolve() if resolve else Path(value)
    elif project is None:
        raise ValueError("results_folder: no --out and no project to number a folder in")
    else:
        out = default_out(project, prefix)
    with kept_if_used(out, made=made):
        yield out


__all__ = [
    "CheckFailed",
    "DeprecatedAlias",
    "OneLineParser",
    "UsageError",
    "add_deprecated",
    "add_device",
    "add_json",
    "add_replay",
    "command_project",
    "default_out",
    "drop_log_lines",
    "emit_json",
    "forget_project",
    "kept_if_used",
    "log_lines",
    "need_device",
    "out_folder",
    "replay_file",
    "results_folder",
    "warn",
]
