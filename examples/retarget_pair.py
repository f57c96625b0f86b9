"""Retarget one hand's thumb and index to finger pair L: the retargeting example of
docs/retargeting.md.

Run it from the project root (``python examples/retarget_pair.py``; a few seconds, about
20 s more the first time, while the solver compiles). The operator's
features come from thumb and index points in the calibrated wrist frame: a pinch (15 mm
apart), an open hand (90 mm) and the pose being retargeted (50 mm). It prints one JSON
object: the calibrated opening, the commanded span, the solved joints and their span.
"""

from __future__ import annotations

import json

import numpy as np

from payload.retarget import (
    PairFeatures,
    PairRetargeter,
    calibrate,
    features_from_points,
    pair_range,
)


def hand_features(span: float) -> PairFeatures:
    """Thumb (finger 1) and index (finger 2) tips ``span`` apart across the wrist [m]."""
    thumb = np.array([0.03, -span / 2, -0.08])
    index = np.array([0.03, span / 2, -0.08])
    thumb_dip = thumb + np.array([0.0, -0.01, 0.025])  # distal joints above, a little outside
    index_dip = index + np.array([0.0, 0.01, 0.025])
    return features_from_points(thumb, index, thumb_dip, index_dip)


pinch_features = hand_features(0.015)  # the operator's calibrated pinch
open_features = hand_features(0.090)  # and open hand
human_features = hand_features(0.050)  # the pose to retarget

r = PairRetargeter(pair="L")  # compiled on first use, then cached on disk
cal = calibrate(pinch_features, open_features, pair_range(r.kinematics))
targets, q_ref = cal.command(human_features)  # human features in the calibrated wrist frame
q, info = r.solve(targets, q_ref=q_ref)  # warm-started from the last command

print(
    json.dumps(
        {
            "pair": "L",
            "opening": cal.opening(human_features.span),
            "span_min_m": cal.range.span_min,
            "span_max_m": cal.range.span_max,
            "target_span_m": targets.span,
            "joints": r.kinematics.desc.joints,
            "q": [float(v) for v in q],
            "span_m": r.kinematics.features(q).span,
        }
    )
)
