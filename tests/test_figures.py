"""Trial figures: the phase legend follows the recording's own time order."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from payload.trials.figures import phase_spans, phases_in_time_order


def test_phase_legend_is_in_time_order_not_declaration_order() -> None:
    seq = (
        ["calibration"] * 3
        + ["acquisition"] * 2
        + ["translation"] * 4
        + ["turn"] * 2
        + ["translation"] * 3
        + ["braking"] * 2
        + ["arrival"] * 2
    )
    phase = np.array(seq)
    assert phases_in_time_order(phase) == [
        "calibration",
        "acquisition",
        "translation",
        "turn",
        "braking",
        "arrival",
    ]
    # the legend lists each phase once, in the order of the spans' first appearance
    t = np.arange(len(seq)) * 0.02
    firsts = list(dict.fromkeys(name for name, _, _ in phase_spans(t, phase)))
    assert firsts == phases_in_time_order(phase)


# -- the campaign figure (issue 30) ----------------------------------------------------
SOURCES = Path(__file__).resolve().parents[1] / "docs" / "sources.md"


def _paper_from_sources() -> list[tuple[float, float, float]]:
    """The paper's (median, min, max) per metric, in the paper's order, read from the
    results row of docs/sources.md (in this repository; not the package's own table)."""
    import re

    lines = SOURCES.read_text(encoding="utf-8").splitlines()
    row = next(ln for ln in lines if ln.startswith("| results of ten trials |"))
    found = re.findall(r"([\d.]+) (?:s|m|mm) \(([\d.]+) to ([\d.]+)\)", row)
    assert len(found) == 5, row
    return [tuple(float(v) for v in m) for m in found]


def test_the_campaign_figure_draws_every_trial_beside_the_papers_median_and_range(tmp_path):
    import json

    from matplotlib.collections import LineCollection, PathCollection
    from matplotlib.image import imread
    from test_trials import fixture_synthetic_trial

    from payload.trials.campaign import run_campaign
    from payload.trials.campaign_figure import OURS, PAPER, campaign_figure
    from payload.trials.summary import METRIC_KEYS, METRIC_LABELS, write_summary

    results = run_campaign(fixture_synthetic_trial, [4, 6], tmp_path, workers=0, progress=False)
    summary = write_summary(results, tmp_path)
    img = imread(tmp_path / "fig_campaign.png")
    assert img.shape[1] > 1000 and img[..., :3].std() > 0.05  # drawn, not a blank canvas
    per_trial = [json.loads(p.read_text()) for p in sorted(tmp_path.glob("trial-*/metrics.json"))]
    paper = _paper_from_sources()
    fig = campaign_figure(summary, METRIC_LABELS)
    assert len(fig.axes) == len(METRIC_KEYS)
    for i, (ax, key) in enumerate(zip(fig.axes, METRIC_KEYS)):
        dots = next(c for c in ax.collections if isinstance(c, PathCollection)).get_offsets()
        want = sorted(m[key] for m in per_trial)
        assert np.allclose(sorted(np.asarray(dots)[:, 1]), want)
        assert np.all(np.abs(np.asarray(dots)[:, 0] - OURS) < 0.2)
        bars = {}
        for c in ax.collections:
            if isinstance(c, LineCollection):
                (x0, lo), (_, hi) = c.get_segments()[0]
                bars[round(float(x0), 3)] = (lo, hi)
        assert np.allclose(bars[OURS], (min(want), max(want)))
        assert np.allclose(bars[PAPER], paper[i][1:])
    # the summary unchanged: the figure is left as it is
    stamp = (tmp_path / "fig_campaign.png").stat().st_mtime_ns
    write_summary(results, tmp_path)
    assert (tmp_path / "fig_campaign.png").stat().st_mtime_ns == stamp


def _title_on_page(summary: dict, labels: dict) -> str:
    """The campaign figure's title as drawn, after checking that it lies inside the page,
    above every panel's own title, with every word of the summary's title."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from payload.trials.campaign_figure import campaign_figure

    fig = campaign_figure(summary, labels)
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    title = fig._suptitle
    box, page = title.get_window_extent(renderer), fig.bbox
    assert page.x0 <= box.x0 and box.x1 <= page.x1, (box, page)
    assert page.y0 <= box.y0 and box.y1 <= page.y1, (box, page)
    for ax in fig.axes:
        assert box.y0 >= ax.title.get_window_extent(renderer).y1 - 0.5, ax.get_title()
    assert " ".join(title.get_text().split()).startswith(" ".join(summary["title"].split()))
    return title.get_text()


def test_a_long_campaign_title_stays_on_the_page_above_the_panels() -> None:
    """The committed campaigns' titles (their setups in words) ran past both edges of the
    `safe` ones' figures: wrapped, each drawn title lies inside its page, above the
    panels' titles; on a one-panel figure the same title wraps over several lines."""
    import json

    from payload.trials.summary import METRIC_LABELS

    root = SOURCES.parents[1] / "analyses" / "campaign"
    summaries = sorted(root.glob("*/summary.json"))
    assert len(summaries) >= 6
    for path in summaries:
        _title_on_page(json.loads(path.read_text(encoding="utf-8")), METRIC_LABELS)
    summary = json.loads((root / "single-safe-delay1s" / "summary.json").read_text())
    one = dict(list(METRIC_LABELS.items())[:1])
    assert len(_title_on_page(summary, one).splitlines()) >= 4


def test_a_trial_figure_without_contact_names_the_contact_it_was_scored_with(
    tmp_path: Path, monkeypatch
) -> None:
    """Fig. 3 of a trial without a contact interval said "no confirmed contact" whatever
    the definition it was scored with: a rescoring's figure (here: runs of at least 1 s,
    no gaps bridged) names that definition's contact, as its title already does."""
    from test_trials import fixture_synthetic_trial

    from payload.trials import figures
    from payload.trials.metrics import CONFIRM_MAX_GAP_S, CONFIRM_MIN_S, compute_metrics
    from payload.trials.recorder import read_recording

    fixture_synthetic_trial(3, tmp_path, "none")
    rec = read_recording(tmp_path / "log.mcap")
    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, *a: drawn.append(fig))
    for lo, gap in ((1.0, 0.0), (CONFIRM_MIN_S, CONFIRM_MAX_GAP_S)):
        metrics = compute_metrics(rec, min_interval_s=lo, max_gap_s=gap)
        figures.plot_ctb_body_frame(rec, "unused.png", metrics)
    said = [[t.get_text() for t in fig.axes[3].texts] for fig in drawn]
    assert said == [["no contact (>= 1 s, gaps <= 0 s)"], ["no confirmed contact"]]


# -- the --max-time cap's label (a new user's capped trial: the label sat on the curve) --
def _fig3(rec, monkeypatch):
    """Fig. 3 of ``rec`` as drawn (not written), on an Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from payload.trials import figures

    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, *a: drawn.append(fig))
    figures.plot_ctb_body_frame(rec, "unused.png")
    FigureCanvasAgg(drawn[0]).draw()
    return drawn[0]


def _covers(box, line) -> bool:
    """Whether the line, as drawn (its data through the axes' transform to pixels, each
    segment sampled every 0.1 px or finer), enters the text's box."""
    xy = line.get_transform().transform(line.get_xydata())
    steps = max(2, int(np.ceil(np.abs(np.diff(xy, axis=0)).max() / 0.1)) + 1)
    s = np.linspace(0.0, 1.0, steps)[:, None, None]
    pts = (xy[:-1] + s * (xy[1:] - xy[:-1])).reshape(-1, 2)
    inside = (pts[:, 0] >= box.x0) & (pts[:, 0] <= box.x1)
    return bool(np.any(inside & (pts[:, 1] >= box.y0) & (pts[:, 1] <= box.y1)))


@pytest.mark.parametrize(
    ("shape", "contact_from"),
    [
        ("rises to the top right", 100),  # the old label's corner, with the t0 line
        ("fills the panel", None),  # no corner is free
    ],
)
def test_the_cap_label_never_covers_the_curve(tmp_path: Path, monkeypatch, shape, contact_from):
    """A trial the --max-time cap stopped says so in Fig. 3's top panel: the label's box
    (matplotlib's window extent) meets no point of the body-x curve nor of the t0 line as
    drawn (their data through the axes' transform), and lies inside the panel. The rising
    curve crosses the top right corner, where the label used to be."""
    from test_trials import recording_with_offsets

    from payload.trials.figures import CAP_LABEL

    n = 600
    if shape == "rises to the top right":
        x = [0.0 if i < 400 else 40.0 * (i - 400) / 200 for i in range(n)]
    else:
        x = [20.0 * math.sin(1.3 * i) for i in range(n)]
    contact = [contact_from is not None and i >= contact_from for i in range(n)]
    rec = recording_with_offsets([(v, 0.0, 0.0) for v in x], contact)
    rec.meta["ended_by"] = "max_time"
    fig = _fig3(rec, monkeypatch)
    ax = fig.axes[0]
    renderer = fig.canvas.get_renderer()
    (label,) = [t for t in ax.texts if t.get_text() == CAP_LABEL]
    box = label.get_window_extent(renderer)
    curve, *marks = ax.get_lines()
    assert len(curve.get_xdata()) == n
    assert ax.bbox.x0 <= box.x0 and box.x1 <= ax.bbox.x1, (box, ax.bbox)
    assert ax.bbox.y0 <= box.y0 and box.y1 <= ax.bbox.y1, (box, ax.bbox)
    assert not _covers(box, curve), (shape, box)
    if contact_from is not None:  # the position at t0, a horizontal line across the panel
        (t0_line,) = [ln for ln in marks if list(ln.get_xdata()) == [0, 1]]  # axes' width
        assert not _covers(box, t0_line), box
    if shape == "rises to the top right":  # the test sees an overlap where there is one
        spot = {"ha": "right", "va": "top", "fontsize": 8}  # the old label's
        old = ax.text(0.99, 0.95, CAP_LABEL, transform=ax.transAxes, **spot)
        assert _covers(old.get_window_extent(renderer), curve)
