"""Trial figures: the phase legend follows the recording's own time order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
