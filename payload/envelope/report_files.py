"""Which report files a folder holds, and whose: a report JSON's provenance names the design
file it came from, so a report is never written over another design's (or over files that
are no report at all).
"""

from __future__ import annotations

import json
from pathlib import Path

PROVENANCE_KEY = "provenance"
"""What a report was computed from (commit, version, design): recorded, but not a figure."""

REPORT_FILES = (".md", ".png", ".json", ".timing.json")
"""The suffixes (after its stem) of the files that writing a report replaces."""


def report_design(path: Path) -> Path | None:
    """The design file (absolute) that the report JSON at ``path`` says it came from, or
    None when the file is no report (not JSON, or no provenance naming a design).

    A report's ``provenance.design`` is relative to ``provenance.project`` (absolute when
    outside it or in no project, ``project`` null); a report in its project's own
    ``analyses/`` leaves ``project`` out: the folder's parent is the project's root."""
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    prov = data.get(PROVENANCE_KEY) if isinstance(data, dict) else None
    design = prov.get("design") if isinstance(prov, dict) else None
    if not isinstance(design, str) or not design:
        return None
    root = prov.get("project", str(path.resolve().parent.parent))
    return (Path(root) / design if isinstance(root, str) else Path(design)).resolve()


def report_paths(out_dir: Path, stem: str) -> list[Path]:
    """The files of report ``stem`` that ``out_dir`` holds (:data:`REPORT_FILES`' order)."""
    return [out_dir / f"{stem}{s}" for s in REPORT_FILES if (out_dir / f"{stem}{s}").exists()]


def foreign_report(out_dir: Path, stem: str, design: Path) -> str | None:
    """Why writing report ``stem`` of ``design`` into ``out_dir`` would replace files that
    are not that report (another design's report, or files that are no report at all), or
    None when it replaces nothing else (none of them there, or ``design``'s own)."""
    there = report_paths(out_dir, stem)
    if not there:
        return None
    design = design.resolve()
    data = out_dir / f"{stem}.json"
    if not data.exists():
        return f"holds {there[0].name}, not a report of {design} (no {stem}.json saying so)"
    owner = report_design(data)
    if owner is None:
        return f"holds {stem}.json, not a report (no provenance naming its design file)"
    if owner != design:
        return f"holds {stem}.json, the report of {owner}, not of {design}"
    return None


__all__ = ["PROVENANCE_KEY", "REPORT_FILES", "foreign_report", "report_design", "report_paths"]
