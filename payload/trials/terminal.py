"""A campaign on the terminal: a line per finished trial and the headline summary.

``payload trials run`` prints :func:`trial_line` for each trial as it finishes when its
output is not a terminal (a pipe, a log, CI), and :func:`summary_terminal` at the end: one
headline line (:func:`summary_headline`), then each metric's median and range beside the
paper's. The definitions and the per-trial table stay in ``summary.md``
(:func:`payload.trials.summary_markdown.summary_markdown`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from payload.schema import ENDED_BY_CAP
from payload.trials.summary_fields import (
    CAP_STOPPED,
    METRIC_KEYS,
    PAPER_RESULTS,
    definition_words,
    metric_labels,
)
from payload.trials.summary_markdown import _DIGITS, _fmt, _run_lines, _stat_text, count_note

_SHORT = {
    "duration_s": ("duration", "s"),
    "net_displacement_m": ("displacement", "m"),
    "rms_mm": ("RMS", "mm"),
    "peak_mm": ("peak", "mm"),
    "contact_s": ("contact", "s"),
}
"""Short names and units of the metrics for terminal lines."""


def summary_headline(summary: dict[str, Any]) -> str:
    """The campaign in one line, the paper beside it: successes under the contact
    definition the trials were scored with (the workbench's confirmed contact, unless
    rescored), then each metric's median.

    ``10/10 succeeded (confirmed contact); paper 10/10; RMS median 33.2 mm (paper 35.6); ...``
    """
    paper = summary.get("paper", PAPER_RESULTS)
    n = summary["n"]
    words = definition_words(summary.get("contact_definition"))
    parts = [f"{summary['success']}/{n} succeeded ({words.contact})"]
    lit = summary.get("literal") or {}
    if lit.get("success") is not None:
        parts[0] = parts[0][:-1] + f"; paper-literal {lit['success']}/{n})"
    parts.append(f"paper {paper['success']}/{paper['n']}")
    if summary.get("errors"):
        parts.append(f"{summary['errors']} error(s)")
    if summary.get("capped"):
        parts.append(f"{summary['capped']} {CAP_STOPPED}")
    for key in ("rms_mm", "peak_mm", "duration_s"):
        name, unit = _SHORT[key]
        stat, d = summary.get(key), _DIGITS[key]
        if stat and stat.get("median") is not None:
            parts.append(
                f"{name} median {stat['median']:.{d}f} {unit} (paper {paper[key]['median']:.{d}f})"
            )
    return "; ".join(parts)


def summary_terminal(summary: dict[str, Any], title: str | None = None) -> str:
    """What ``payload trials run`` prints: the headline, the title, then each metric's
    median and range beside the paper's (the definitions and the per-trial table are left
    to ``summary.md``, :func:`summary_markdown`)."""
    paper = summary.get("paper", PAPER_RESULTS)
    words = definition_words(summary.get("contact_definition"))  # the trials' own contact
    labels = metric_labels(summary.get("contact_definition"))
    width, column = max(len(labels[k]) for k in METRIC_KEYS), 46
    lines = [summary_headline(summary), title or "Cargo-transport campaign"]
    lines.append(f"  {'':{width}}  {f'this campaign ({words.contact})':<{column}}paper")
    for key in METRIC_KEYS:
        ours = _stat_text(summary, key, words.none) + count_note(summary, key)
        theirs = _fmt(paper[key], _DIGITS[key])
        lines.append(f"  {labels[key]:{width}}  {ours:<{column}}{theirs}")
    lines += [ln for ln in _run_lines(summary.get("run")) if ln]
    return "\n".join(lines)


def trial_line(result: dict[str, Any], done: int, total: int) -> str:
    """One line for a finished trial of a campaign (its progress when not on a terminal):
    ``[3/10] seed 2: succeeded; RMS 33.1 mm; duration 80.2 s; wall 19.8 s``."""
    head = f"[{done}/{total}] seed {result.get('seed')}: "
    wall = result.get("wall_s")
    tail = "" if wall is None or not math.isfinite(wall) else f"; wall {wall:.1f} s"
    if result.get("error"):
        return head + f"error: {str(result['error']).splitlines()[0]}{tail}"
    parts = ["succeeded" if result.get("success") else "failed"]
    if result.get("ended_by") == ENDED_BY_CAP:  # why, when a cap cut the session short
        parts[0] += f" ({CAP_STOPPED})"
    for key in ("rms_mm", "duration_s"):
        name, unit = _SHORT[key]
        value = result.get(key)
        if value is not None and math.isfinite(float(value)):
            parts.append(f"{name} {float(value):.{_DIGITS[key]}f} {unit}")
    return head + "; ".join(parts) + tail


def trial_line_printer(total: int) -> Callable[[dict[str, Any]], None]:
    """A callback printing :func:`trial_line` on stdout (flushed) as each trial finishes."""
    done = [0]

    def on_trial(result: dict[str, Any]) -> None:
        done[0] += 1
        print(trial_line(result, done[0], total), flush=True)

    return on_trial


__all__ = ["summary_headline", "summary_terminal", "trial_line", "trial_line_printer"]
