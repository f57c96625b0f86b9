"""Trial figures: the phase legend follows the recording's own time order."""

from __future__ import annotations

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
