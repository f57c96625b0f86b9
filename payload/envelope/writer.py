"""Writing a report: Markdown, JSON and PNG in ``analyses/``, only when its figures changed.

A report is derived from the design, like the generated models: when the design changed,
its report follows (the files are replaced, each through a temporary file and a rename),
and the previous figures are kept beside it as ``<stem>.prev.json`` so the change can be
printed and compared. Recordings (trials, campaigns) are never replaced this way.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from payload.envelope.fit_results import EnvelopeAnalysis
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.markdown import cite_sources, envelope_markdown, reach_markdown
from payload.envelope.reach import ReachAnalysis
from payload.envelope.report_files import PROVENANCE_KEY
from payload.envelope.report_json import envelope_json, reach_json
from payload.safeio import replace_file, replacing

TIMING_KEYS = ("seconds", "timings_s")
"""JSON keys holding wall-clock timings: kept out of the committed report files."""


def _split_timings(obj: Any, path: str = "") -> tuple[Any, dict[str, Any]]:
    """(``obj`` without timing keys, the timings by dotted path)."""
    if not isinstance(obj, dict):
        return obj, {}
    kept, timings = {}, {}
    for key, value in obj.items():
        where = f"{path}.{key}" if path else key
        if key in TIMING_KEYS:
            timings[where] = value
        else:
            kept[key], inner = _split_timings(value, where)
            timings.update(inner)
    return kept, timings


def _same_figures(path: Path, text: str) -> bool:
    """Whether the file at ``path`` holds the same report as ``text``: byte for byte, or for
    JSON the same apart from its provenance (a new commit alone changes no figure), of the
    same design (a report follows its design file, its hash included)."""
    old = path.read_bytes()
    if old == text.encode():
        return True
    if path.suffix != ".json":
        return False
    try:
        before = json.loads(old)
    except ValueError:
        return False
    after = json.loads(text)
    if not isinstance(before, dict):
        return False
    design = [(d.pop(PROVENANCE_KEY, None) or {}).get("design_sha256") for d in (before, after)]
    return before == after and design[0] == design[1]


def _write_report(
    out_dir: Path,
    stem: str,
    markdown: str,
    data: dict[str, Any],
    draw: Callable[[Path], Any],
    force: bool,
) -> dict[str, Path]:
    """Write ``<stem>.md/.json/.png``, following the design.

    Timings go to ``<stem>.timing.json`` (not committed) every run. Identical ``md`` and
    ``json`` (provenance aside) leave all three files untouched unless ``force`` (which
    refreshes the provenance). Different ones replace the report, each file through a
    temporary file and a rename, after the previous ``<stem>.json`` is copied to
    ``<stem>.prev.json``.

    Returns:
        The paths written: ``png``, ``md``, ``json``, ``timing``, and ``prev`` when a
        report with other figures was replaced; only ``timing`` when nothing changed.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    committed, timings = _split_timings(data)
    texts = {
        out_dir / f"{stem}.md": markdown,
        out_dir / f"{stem}.json": json.dumps(committed, indent=2) + "\n",
    }
    paths = {"png": out_dir / f"{stem}.png", "md": out_dir / f"{stem}.md"}
    paths["json"] = out_dir / f"{stem}.json"
    paths["timing"] = out_dir / f"{stem}.timing.json"
    replace_file(paths["timing"], json.dumps(timings, indent=2) + "\n")
    same = [p for p, t in texts.items() if p.exists() and _same_figures(p, t)]
    if len(same) == len(texts) and paths["png"].exists() and not force:
        return {"timing": paths["timing"]}  # nothing but timings or provenance changed
    if paths["json"].exists() and paths["json"] not in same:
        paths["prev"] = out_dir / f"{stem}.prev.json"
        replace_file(paths["prev"], paths["json"].read_bytes())
    with replacing(paths["png"]) as tmp:
        draw(tmp)
    for path, text in texts.items():
        replace_file(path, text)
    return paths


def _draw_envelope(geom: PayloadGeometry, a: EnvelopeAnalysis, path: Path) -> None:
    """The envelope figure (matplotlib loads here: only a changed report is drawn)."""
    from payload.envelope.envelope_figure import envelope_figure

    envelope_figure(geom, a, path)


def _draw_reach(geom: PayloadGeometry, a: ReachAnalysis, path: Path) -> None:
    """The reach figure (matplotlib loads here: only a changed report is drawn)."""
    from payload.envelope.reach_figure import reach_figure

    reach_figure(geom, a, path)


def write_envelope(
    geom: PayloadGeometry,
    a: EnvelopeAnalysis,
    out_dir: Path,
    command: str,
    record: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    *,
    force: bool = False,
) -> dict[str, Path]:
    """Write ``envelope.md``, ``envelope.png`` and ``envelope.json`` into ``out_dir`` when
    the report changed (see :func:`_write_report`); returns the paths written. ``record``
    adds fields to the JSON (e.g. its provenance); ``force`` rewrites an unchanged report."""
    a.extra["stage_upper"] = geom.tree.joint_map["stage"].upper
    return _write_report(
        out_dir,
        "envelope",
        cite_sources(envelope_markdown(a, command, "envelope.png"), a.design_source, out_dir),
        envelope_json(a) if record is None else record(envelope_json(a)),
        lambda path: _draw_envelope(geom, a, path),
        force,
    )


def write_reach(
    geom: PayloadGeometry,
    a: ReachAnalysis,
    out_dir: Path,
    command: str,
    t_start: float | None = None,
    record: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    *,
    force: bool = False,
) -> dict[str, Path]:
    """Write ``reach.md``, ``reach.png`` and ``reach.json`` into ``out_dir`` when the
    report changed (see :func:`_write_report`); returns the paths written.

    Args:
        geom: Collision geometry.
        a: The analysis.
        out_dir: Output directory (created).
        command: The command that reproduces the report.
        t_start: ``time.perf_counter()`` at the command's start: when given, ``a.seconds``
            becomes the wall time up to the writing.
        record: Adds fields to the JSON (e.g. its provenance).
        force: Rewrite the report even when its figures did not change.
    """
    if t_start is not None:
        a.seconds = time.perf_counter() - t_start
    return _write_report(
        out_dir,
        "reach",
        cite_sources(reach_markdown(a, command, "reach.png"), a.design_source, out_dir),
        reach_json(a) if record is None else record(reach_json(a)),
        lambda path: _draw_reach(geom, a, path),
        force,
    )


__all__ = [
    "PROVENANCE_KEY",
    "TIMING_KEYS",
    "write_envelope",
    "write_reach",
]
