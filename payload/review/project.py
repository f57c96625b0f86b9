"""Where a review finds its design project: the design file and its generated models."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from payload.review.errors import ReviewError

DEFAULT_RATE = 10.0
"""Frames per second of trial time a trial replay shows by default [Hz] (``--rate``)."""

TRIAL_OPTION = "--trial"
"""The option that names a trial folder to replay (``payload review --trial DIR``)."""


@dataclass(frozen=True)
class ProjectFiles:
    """The files of one design project a review reads.

    Attributes:
        design: The design file (``cad/design.toml``).
        urdf: The generated URDF (``urdf/payload.urdf``); its meshes live in ``cad/meshes``.
        mjcf: The generated MJCF (``urdf/payload.xml``), for the trial world.
    """

    design: Path
    urdf: Path
    mjcf: Path

    def check(self) -> None:
        """Raise :class:`ReviewError` naming the first missing file."""
        for what, path in (("design file", self.design), ("generated URDF", self.urdf)):
            if not path.is_file():
                hint = "" if what == "design file" else "; run `payload build`"
                raise ReviewError(f"{what} not found: {path}{hint}")


def project_files(design: str | Path | None = None) -> ProjectFiles:
    """The design project of ``design`` (default: the current project's design file).

    A design file lives at ``<project>/cad/design.toml`` and its models under
    ``<project>/urdf``. This is the one place the review looks the project up.
    """
    if design is None:
        from payload.project import current_project

        project = current_project()
        urdf = project.urdf_dir / "payload.urdf"
        return ProjectFiles(project.design_path, urdf, urdf.with_name("payload.xml"))
    path = Path(design)
    root = path.resolve().parents[1]
    return ProjectFiles(path, root / "urdf" / "payload.urdf", root / "urdf" / "payload.xml")


def design_hash(path: str | Path) -> str:
    """SHA-256 of a design file, first 16 hex digits (what a trial recording stores)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def page_title(what: str, subject: str, design: str | Path) -> str:
    """A review page's title, one form for every page: ``<what> — <subject> (design
    <hash>)``, e.g. ``design review — <project>/cad/design.toml (design ...)`` or
    ``trial replay — <folder>/trial-0003 (design ...)``; the browser tab shows it too."""
    return f"{what} — {subject} (design {design_hash(design)})"


__all__ = ["DEFAULT_RATE", "ProjectFiles", "design_hash", "page_title", "project_files"]
