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
