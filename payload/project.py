"""Design projects: the folder a command works on, and where its files live.

A design project is a folder holding ``cad/design.toml``. Its generated models go to
its own ``urdf/`` and ``cad/meshes/``, its reports to ``analyses/`` and its trials to
``runs/``. Commands find the project like ``git`` does (:func:`find_project`): an
explicit ``--project DIR``, else the ``PAYLOAD_PROJECT`` environment variable, else the
current directory and its parents. The package never reads or writes models in its own
source tree; it ships only the default design (:func:`default_design_text`).

:func:`provenance` is the one place that says what a result was computed from (design
hash, package version, git commit), for reports, trials, campaigns and sweeps.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from payload.errors import PayloadError

ENV_VAR = "PAYLOAD_PROJECT"
"""Environment variable naming the project folder (after ``--project``, before the cwd)."""

DESIGN_FILE = "cad/design.toml"
"""Where a project keeps its design, relative to its root."""

DISTRIBUTION = "astrobee-payload"

SOURCES = "docs/sources.md"
"""Where the workbench cites the figures it takes from outside (papers, NASA's data),
relative to its source tree's root; its default design and its reports cite it so."""

__all__ = [
    "DESIGN_FILE",
    "ENV_VAR",
    "SOURCES",
    "Project",
    "ProjectError",
    "current_project",
    "default_design_text",
    "find_project",
    "is_project_design",
    "package_version",
    "project_of",
    "provenance",
    "workbench_root",
]


class ProjectError(PayloadError):
    """No design project where one is needed, or a project folder is unusable."""


@dataclass(frozen=True)
class Project:
    """A design project and the folders of its files (all absolute).

    Attributes:
        root: The project folder.
        design_path: Its design file, ``root/cad/design.toml``.
        urdf_dir: Generated URDF, MJCF and scene, ``root/urdf``.
        meshes_dir: Generated STL meshes, ``root/cad/meshes``.
        analyses_dir: Reports, ``root/analyses``.
        runs_dir: Trials and campaigns, ``root/runs``.
    """

    root: Path
    design_path: Path
    urdf_dir: Path
    meshes_dir: Path
    analyses_dir: Path
    runs_dir: Path

    @classmethod
    def at(cls, root: str | Path) -> Project:
        """The project rooted at ``root`` (not checked: see :func:`find_project`)."""
        r = Path(root).expanduser().resolve()
        return cls(
            root=r,
            design_path=r / DESIGN_FILE,
            urdf_dir=r / "urdf",
            meshes_dir=r / "cad" / "meshes",
            analyses_dir=r / "analyses",
            runs_dir=r / "runs",
        )

    @property
    def urdf(self) -> Path:
        """The payload URDF, ``urdf/payload.urdf``."""
        return self.urdf_dir / "payload.urdf"

    @property
    def mjcf(self) -> Path:
        """The payload MJCF, ``urdf/payload.xml``."""
        return self.urdf_dir / "payload.xml"

    @property
    def scene(self) -> Path:
        """The MuJoCo scene including the payload, ``urdf/scene.xml``."""
        return self.urdf_dir / "scene.xml"

    def is_project(self) -> bool:
        """Whether ``root`` holds a design file."""
        return self.design_path.is_file()

    def relative(self, path: str | Path) -> str:
        """``path`` relative to the root when inside it (POSIX), else as given."""
        try:
            return Path(path).resolve().relative_to(self.root).as_posix()
        except (ValueError, OSError):
            return str(path)


def _search_up(start: Path) -> Project | None:
    for folder in (start, *start.parents):
        if (folder / DESIGN_FILE).is_file():
            return Project.at(folder)
    return None


def enclosing_project(folder: str | Path) -> Project | None:
    """The project ``folder`` lies in (``folder`` itself or its nearest parent holding
    ``cad/design.toml``), or None."""
    return _search_up(Path(folder).resolve())


def find_project(explicit: str | Path | None = None, *, cwd: str | Path | None = None) -> Project:
    """The project a command works on.

    Searched in order: ``explicit`` (``--project DIR``), the ``PAYLOAD_PROJECT``
    environment variable, then ``cwd`` (default: the current directory) and each parent.

    Raises:
        ProjectError: ``explicit`` or ``PAYLOAD_PROJECT`` names a folder without
            ``cad/design.toml``, or no folder from ``cwd`` upward holds one.
    """
    for value, what in ((explicit, "--project"), (os.environ.get(ENV_VAR) or None, ENV_VAR)):
        if value is None:
            continue
        project = Project.at(value)
        if not project.is_project():
            where = Path(value).expanduser()
            why = (
                "no such folder"
                if not where.exists()
                else "a file, not a folder"
                if not where.is_dir()
                else f"not a design project (no {DESIGN_FILE} there)"
            )
            raise ProjectError(f"{what} {value}: {why}")
        return project
    start = Path(cwd) if cwd is not None else Path.cwd()
    found = _search_up(start.resolve())
    if found is None:
        raise ProjectError(
            f"not inside a design project: no {DESIGN_FILE} in {start.resolve()} or any "
            "parent (use --project DIR, PAYLOAD_PROJECT, or `payload new DIR`)"
        )
    return found


def current_project() -> Project:
    """The project of this process (``PAYLOAD_PROJECT``, else the cwd upward).

    What library functions use when given neither a project nor explicit paths.

    Raises:
        ProjectError: No project found.
    """
    return find_project(None)


def project_of(design_file: str | Path) -> Project | None:
    """The project containing ``design_file`` (its folder or the nearest parent holding
    ``cad/design.toml``), or ``None`` when it lies in no project."""
    return _search_up(Path(design_file).expanduser().resolve().parent)


def is_project_design(design_file: str | Path) -> bool:
    """Whether ``design_file`` is a project's own ``cad/design.toml`` (symlinks and ``~``
    resolved), the one file whose models and reports go to that project."""
    owner = project_of(design_file)
    resolved = Path(design_file).expanduser().resolve()
    return owner is not None and owner.design_path.resolve() == resolved


def default_design_text() -> str:
    """The packaged default design (``payload/data/design.toml``) as text."""
    from importlib import resources  # loaded here: every command imports this module

    return resources.files("payload").joinpath("data", "design.toml").read_text(encoding="utf-8")


def workbench_root() -> Path | None:
    """The workbench's source tree, whose :data:`SOURCES` its reports cite (the checkout
    of an editable install), or ``None`` when the package is installed without it."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / SOURCES).is_file() else None


def package_version() -> str:
    """The installed version of the ``astrobee-payload`` distribution."""
    from importlib import metadata  # loaded here: every command imports this module

    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare tree
        from payload import __version__

        return __version__


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(root), *args],
            capture_output=True,
            text=True,
            timeout=20,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_state(root: str | Path, design: str | Path | None = None) -> tuple[str | None, bool | None]:
    """``(commit, dirty)`` of the git work tree holding ``root``, or ``(None, None)``.

    ``dirty`` is true when a tracked file differs from the commit (untracked files,
    such as ``runs/``, do not count), and when ``design``, the design file a result was
    computed from, is not in the commit at all: a project made inside another's work
    tree (a sweep's points under ``runs/``, ``payload new`` in a subfolder) or a design
    file from outside it. The commit alone does not give that result back.
    """
    r = Path(root)
    if _git(r, "rev-parse", "--is-inside-work-tree") != "true":
        return None, None
    commit = _git(r, "rev-parse", "HEAD")
    status = _git(r, "status", "--porcelain", "--untracked-files=no")
    if status is None:
        return commit, None
    if design is not None and not status:
        # in the commit, ls-tree names it; untracked or ignored: nothing; outside the
        # work tree: an error
        status = not _git(r, "ls-tree", "--name-only", "HEAD", "--", str(Path(design).resolve()))
    return commit, bool(status)


def provenance(project: Project | None, design_path: str | Path | None = None) -> dict[str, Any]:
    """What a result was computed from.

    Args:
        project: The project it belongs to (``None``: no project, no git state).
        design_path: The design file actually read (default: the project's).

    Returns:
        ``{"project", "design", "design_sha256", "package_version", "git_commit",
        "git_dirty"}``: the project root, the design file (relative to the root when
        inside it), the SHA-256 of that file's bytes, the package version, and the
        commit and dirty flag of the project's git work tree (``None`` outside one).
    """
    if design_path is None:
        if project is None:
            raise ProjectError("provenance: need a project or a design file")
        design_path = project.design_path
    path = Path(design_path)
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ProjectError(f"cannot read design file {path} ({exc.strerror})") from exc
    commit, dirty = git_state(project.root, path) if project is not None else (None, None)
    return {
        "project": str(project.root) if project is not None else None,
        "design": project.relative(path) if project is not None else str(path),
        "design_sha256": digest,
        "package_version": package_version(),
        "git_commit": commit,
        "git_dirty": dirty,
    }
