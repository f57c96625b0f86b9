"""A pair's span range: the retargeter's (:func:`payload.retarget.pair_range`).

The span range (eq. 2's fingertip separation l over the pair's joint box) has its
maximum with each fingertip kept in front of its finger's first joint along the
finger's rest direction (a finger may not curl back through the structure), and its
usable minimum where the pads touch. The reach report and the retargeter's
calibration read one number from one code path.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from payload.retarget.calibration import pair_range
from payload.retarget.features import PairKinematics


class SpanRange(NamedTuple):
    """Range of a pair's fingertip separation (eq. 2's l) over its joint space.

    Attributes:
        pair: Pair name.
        minimum: Smallest fingertip-point separation (below twice the pad radius the
            pads interpenetrate) [m].
        maximum: Largest separation with the fingertips in front of their first joints [m].
        q_min: The 8 pair joints (finger 1 then finger 2) where the pads touch [rad].
        q_max: The 8 pair joints at the maximum [rad].
    """

    pair: str
    minimum: float
    maximum: float
    q_min: np.ndarray
    q_max: np.ndarray


def span_range(pk: PairKinematics) -> SpanRange:
    """The pair's span range, from :func:`payload.retarget.pair_range`."""
    rng = pair_range(pk)
    return SpanRange(
        pk.name,
        rng.span_min_kinematic,
        rng.span_max,
        rng.postures[0].copy(),
        rng.postures[-1].copy(),
    )


__all__ = ["SpanRange", "span_range"]
