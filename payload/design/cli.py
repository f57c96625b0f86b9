"""``payload new``, ``payload build`` and ``payload summary``: a design project's own commands."""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from payload.cliutil import CheckFailed, add_json, command_project, emit_json
from payload.errors import DesignError, PayloadError, not_text
from payload.project import Project, ProjectError, is_project_design, project_of


def _cmd_build(args: argparse.Namespace) -> int:
    from payload.design import load_design, stale_files, write

    if args.root:  # hidden: generate into any folder (tests), no project involved
        design, root = load_design(args.design), Path(args.root)
    else:
        if args.design and not args.check:
            load_design(args.design)  # an invalid design says what is wrong first
            _check_own_design(Path(args.design))
        project = command_project(args, args.design)
        design, root = load_design(args.design or project.design_path), project.root
    t0 = time.perf_counter()
    if args.check:
        stale = stale_files(design, root)
        if stale:
            if args.root or not args.design:
                hint = "run `payload build`"
            elif is_project_design(Path(args.design)):  # its own project's, wherever run
                hint = f"run `payload build --design {args.design}`"
            else:
                hint = (
                    "it is not a project's design, and the project's models follow its own "
                    "cad/design.toml: give it a project of its own to build it"
                )
            raise CheckFailed(
                f"stale: {', '.join(stale)} ({len(stale)} generated file(s) do not match "
                f"{design.source}; {hint})"
            )
        print(f"generated files match {design.source} ({time.perf_counter() - t0:.2f} s)")
        _say_stale_reports(args)
        return 0
    result = write(design, root)
    dt = time.perf_counter() - t0
    n, written = len(result.files), len(result.written)
    if written:
        kept = f"; the other {n - written} already matched it" if written < n else ""
        print(f"wrote {written} of {n} files under {root} from {design.source} in {dt:.2f} s{kept}")
    else:
        print(f"the {n} generated files under {root} already match {design.source}: none written")
    if result.removed:  # a renamed or dropped part's mesh: nothing reads it any more
        print(f"removed {', '.join(result.removed)} (no part of the design makes it)")
    _say_stale_reports(args)
    return 0


def stale_reports(analyses: Path, design: Path) -> list[str]:
    """The reports in ``analyses`` (``envelope.json``, ``reach.json``) made from another
    version of the design file ``design`` (their provenance's ``design_sha256`` is not the
    file's): derived files that no longer follow their source. An unreadable report, or
    one without a digest, is not counted (nothing says what it was made from)."""
    import hashlib
    import json

    from payload.folders import REPORT_FILES

    digest = hashlib.sha256(design.read_bytes()).hexdigest()
    stale = []
    for name in REPORT_FILES:
        try:
            made = json.loads((analyses / name).read_text())["provenance"]["design_sha256"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if made != digest:
            stale.append(name)
    return stale


def _say_stale_reports(args: argparse.Namespace) -> None:
    """A note when the project's reports were made from another version of its design
    file (``build`` follows the models only; the reports follow it when they are run)."""
    if args.root:
        return
    project = command_project(args, args.design, announce=False)
    stale = stale_reports(project.analyses_dir, project.design_path)
    if stale:
        names = ", ".join(f"analyses/{name}" for name in stale)
        print(f"note: {names} made from another version of {project.design_path}: `payload "
              "report all` brings the reports up to date")  # fmt: skip


def _check_own_design(design: Path) -> None:
    """Building writes a design's models into its own project, so the design must be a
    project's ``cad/design.toml``.

    Raises:
        PayloadError: The file is not a project's ``cad/design.toml``.
    """
    if not is_project_design(design):
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


def _source_design_text(source: str | Path) -> str:
    """The design text of ``--from``: a project folder or a design file inside a project.

    Raises:
        ProjectError: ``source`` is neither (the line names ``--from``).
    """
    src = Path(source)
    if src.is_file():
        if project_of(src) is None:
            raise ProjectError(f"--from {source}: not a design project's design file")
        path = src
    else:
        project = Project.at(src)
        if not project.is_project():
            raise ProjectError(f"--from {source}: not a design project (no cad/design.toml there)")
        path = project.design_path
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:  # a mesh or another binary file of the project
        raise ProjectError(f"--from {path}: {not_text(exc, 'TOML')}") from None
    except OSError as exc:  # unreadable, or a folder named design.toml
        raise ProjectError(f"--from {path}: cannot read it ({exc.strerror or exc})") from None
    from payload.design import load_design

    try:  # the copy would fail to build: said of the design it came from
        load_design(path)
    except DesignError as exc:
        raise ProjectError(f"--from {path}: its design is not valid: {exc}") from None
    return text


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
    if target.exists() and not target.is_dir():
        raise ProjectError(f"{target}: a file, not a folder; `payload new` needs a new folder")
    if target.exists() and any(target.iterdir()):
        raise ProjectError(f"{target}: not an empty folder; `payload new` needs a new one")
    text = default_design_text() if source is None else _source_design_text(source)
    created = not target.exists()
    project = Project.at(target)
    try:
        project.design_path.parent.mkdir(parents=True, exist_ok=True)
        project.design_path.write_text(text, encoding="utf-8")
    except OSError as exc:  # a read-only or someone else's folder, a file on the way
        if created:
            shutil.rmtree(project.root, ignore_errors=True)
        raise ProjectError(
            f"{target}: cannot make the project there ({exc.strerror or exc}); "
            "`payload new` needs a folder it can create and write"
        ) from None
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
    if getattr(args, "project", None) is not None:  # it would be ignored: say so instead
        raise ProjectError(
            f"--project {args.project}: `payload new` makes the project at DIR "
            f"({args.dir}); to start from another project's design use --from PROJECT"
        )
    from payload.project import enclosing_project

    t0 = time.perf_counter()
    outer = enclosing_project(Path(args.dir).resolve().parent)
    project, n = new_project(args.dir, args.source)
    print(f"project: {project.root}")
    if outer is not None:  # made on purpose or not, the nesting decides what commands see
        print(
            f"note: inside the project at {outer.root}: commands run in {project.root} work "
            f"on the new project, those run outside it on {outer.root}"
        )
    print(
        f"new design project from {args.source or 'the packaged default design'}: "
        f"{project.relative(project.design_path)} and {n} generated files in "
        f"{time.perf_counter() - t0:.2f} s"
    )
    print(f"next: edit {project.design_path}, then run `payload report all` in {project.root}")
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    """Add ``new``, ``build`` and ``summary``."""
    del groups
    p = sub.add_parser("new", help="a new design project, built and ready")
    p.add_argument("dir", metavar="DIR", help="folder of the new project (new or empty)")
    p.add_argument(
        "--from",
        dest="source",
        metavar="PROJECT",
        help="copy this project's design (default: the packaged default design)",
    )
    # taken only to say why it does not apply (the project is DIR): not in the help
    p.add_argument("--project", metavar="DIR", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
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
    add_json(p)
    p.set_defaults(func=_cmd_summary)


__all__ = ["new_project", "register"]
