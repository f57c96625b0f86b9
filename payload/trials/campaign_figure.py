"""The campaign figure: each metric's spread over the trials beside the paper's.

One panel per metric the paper summarises (:data:`~payload.trials.summary_fields.METRIC_LABELS`):
every trial as a dot, this campaign's median as a bar with its range as a whisker, and
beside it the paper's median and range (Sec. IV, ten trials). Written by the campaign
summary as ``fig_campaign.png`` beside ``summary.md``.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from payload.folders import CAMPAIGN_FIGURE, tagged
from payload.trials.figures import save_figure
from payload.trials.summary_fields import (
    CAP_STOPPED,
    CONFIRMED_WORDS,
    definition_words,
    statistic_rows,
)

OURS, PAPER = 0.0, 1.0
"""x positions of this campaign's column and the paper's in every panel."""


def campaign_figure(
    summary: dict[str, Any], labels: dict[str, str], title: str | None = None
) -> Figure:
    """The figure of a campaign summary (:func:`~payload.trials.summary.summarize`).

    Args:
        summary: The summary: ``trials`` (per-trial values), a ``{"median", "min",
            "max"}`` per metric, and ``paper`` (the paper's figures).
        labels: Metric key -> panel title, in panel order
            (:data:`~payload.trials.summary_fields.METRIC_LABELS`, or
            :func:`~payload.trials.summary_fields.metric_labels` of the summary's
            contact definition).
        title: The figure's title (default: the summary's ``title``, else "Campaign").

    Returns:
        The figure: one axis per metric; in each, the trials' values are the first
        scatter collection (x = :data:`OURS`), the paper's median and range the error bar
        at x = :data:`PAPER`. The first contact interval of a summary none of whose
        trials has one is not drawn (n = 0), as its table says n/a, and its column says why
        (``no confirmed contact``, as Fig. 3 says it); the title names a
        contact definition other than the confirmed one (a rescoring's).
    """
    trials = [t for t in summary.get("trials", []) if not t.get("error")]
    fig = Figure(figsize=(3.0 * len(labels), 4.2), layout="constrained")
    axes = fig.subplots(1, len(labels))
    n_ok = summary.get("success", 0)
    n_capped = int(summary.get("capped") or 0)
    capped = f", {n_capped} {CAP_STOPPED}" if n_capped else ""
    words = definition_words(summary.get("contact_definition"))
    scored = "" if words == CONFIRMED_WORDS else f", scored with {words.contact}"
    _fit_width(
        fig.suptitle(
            f"{title or summary.get('title') or 'Campaign'}\n{n_ok}/{summary.get('n', 0)} "
            f"succeeded{scored}{capped} (paper {summary['paper']['success']}/"
            f"{summary['paper']['n']}); dots: trials, bar: median, whisker: range"
        )
    )
    rng = np.random.default_rng(0)  # a fixed jitter: the same summary draws the same figure
    for ax, (key, label) in zip(np.atleast_1d(axes), labels.items()):
        # the trials the median is over: one without an interval is n/a, as in the table
        shown = statistic_rows(trials, key)
        values = np.array([t[key] for t in shown if _finite(t.get(key))], dtype=float)
        jitter = rng.uniform(-0.12, 0.12, len(values))
        ax.scatter(OURS + jitter, values, s=18, color="#1f77b4", zorder=3, label="trials")
        _median_range(ax, OURS, summary.get(key), "#1f77b4")
        if not len(values):  # an empty column says why, as Fig. 3 does
            why = words.none if trials else "no scored trial"
            ax.text(OURS, 0.5, why.replace(" (", "\n(", 1), transform=ax.get_xaxis_transform(),
                    ha="center", va="center", fontsize=8, color="#1f77b4")  # fmt: skip
        _median_range(ax, PAPER, summary["paper"].get(key), "#d62728")
        ax.set_xticks([OURS, PAPER], [f"this run\n(n = {len(values)})", "paper\n(n = 10)"])
        ax.set_xlim(-0.6, 1.6)
        # a contact definition's numbers on a line of their own (not wrapped between a
        # number and its unit)
        ax.set_title(label.replace(" (", "\n(", 1), fontsize=9, wrap=True)
        ax.grid(axis="y", alpha=0.3)
    return fig


TITLE_WIDTH = 0.96
"""The share of the figure's width a title may take."""


def _fit_width(text: Text) -> None:
    """Wrap ``text``'s lines at spaces until its rendered width is within
    :data:`TITLE_WIDTH` of its figure's (a long setup's title ran past both edges)."""
    fig = text.get_figure()
    renderer = FigureCanvasAgg(fig).get_renderer()
    lines = text.get_text().split("\n")
    chars = max(len(line) for line in lines)
    while chars > 20 and text.get_window_extent(renderer).width > TITLE_WIDTH * fig.bbox.width:
        chars = int(chars * 0.9)
        text.set_text(
            "\n".join(
                textwrap.fill(line, chars, break_long_words=False, break_on_hyphens=False)
                for line in lines
            )
        )


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and bool(np.isfinite(value))


def _median_range(ax: Any, x: float, stat: dict[str, Any] | None, color: str) -> None:
    """A bar at the median with a whisker from the minimum to the maximum."""
    if not stat or stat.get("median") is None:
        return
    med, lo, hi = stat["median"], stat["min"], stat["max"]
    ax.errorbar(
        [x], [med], yerr=[[med - lo], [hi - med]], fmt="_", markersize=24, color=color,
        capsize=6, lw=1.5, zorder=4,
    )  # fmt: skip


def campaign_figure_path(out_dir: str | Path, tag: str | None = None) -> Path:
    """``out_dir/fig_campaign.png``, or ``fig_campaign.<tag>.png`` for a rescoring."""
    return Path(out_dir) / tagged(CAMPAIGN_FIGURE, tag)


def write_campaign_figure(
    summary: dict[str, Any],
    labels: dict[str, str],
    out_dir: str | Path,
    tag: str | None = None,
    dpi: int = 110,
) -> Path:
    """Draw :func:`campaign_figure` into :func:`campaign_figure_path` (atomically)."""
    figure = campaign_figure(summary, labels)
    return save_figure(figure, campaign_figure_path(out_dir, tag), dpi)


__all__ = ["CAMPAIGN_FIGURE", "campaign_figure", "campaign_figure_path", "write_campaign_figure"]
