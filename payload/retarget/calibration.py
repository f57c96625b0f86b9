"""Pinch-to-open calibration: human thumb-index features -> robot pair targets.

Two steps:

1. :func:`pair_range` (:mod:`payload.retarget.span_range`) finds, once per hand and
   pair, what the robot pair can do: its minimum and maximum fingertip span and a
   one-parameter family of postures ``q_ref(l)`` (the posture reference) whose span
   is ``l``; with ``collisions``, restricted to configurations that keep the hand's
   self-collision margin.

2. :func:`calibrate` takes the operator's pinch and open features (thumb = finger 1,
   index = finger 2, in the calibrated wrist frame) and returns a
   :class:`PairCalibration`: the opening ``alpha = (l_h - l_pinch) / (l_open - l_pinch)``
   (clipped to [0, 1]) maps to the span ``l_min + alpha (l_max - l_min)``, so the
   calibrated pinch and open poses give the robot's minimum and maximum span exactly;
   directions are rotated by the rotation that best aligns the human's direction
   features at the two poses with the robot's at ``q_ref(l_min)`` and ``q_ref(l_max)``
   (Wahba's problem, SVD); the centre follows the robot's centre along the same
   opening plus the human's deviation from the calibrated centre, rotated and scaled.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.retarget.errors import RetargetError
from payload.retarget.features import N_FEATURES, PairFeatures, as_feature_vector
from payload.retarget.span_range import (  # noqa: F401  (old import paths)
    PairRange,
    _compute_pair_range,
    _front_constraints,
    _pair_range_cached,
    pair_range,
)
from payload.vecmath import read_only

__all__ = [
    "MIN_OPENING",
    "OpeningError",
    "PairCalibration",
    "PairRange",
    "calibrate",
    "pair_range",
    "wahba_rotation",
]


def wahba_rotation(human: np.ndarray, robot: np.ndarray) -> np.ndarray:
    """Rotation R minimising ``sum |robot_i - R human_i|^2`` over unit vectors, (3, 3).

    Args:
        human: Vectors in the human wrist frame, shape (k, 3).
        robot: Matching vectors in the robot pair frame, shape (k, 3).
    """
    b = np.asarray(robot).T @ np.asarray(human)
    u, _, vt = np.linalg.svd(b)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    return u @ s @ vt


@dataclass(frozen=True)
class PairCalibration:
    """The mapping from human thumb-index features to one robot pair's targets.

    Attributes:
        range: The robot pair's span range and posture family.
        human_pinch: The operator's calibrated pinch features (wrist frame).
        human_open: The operator's calibrated open features (wrist frame).
        rotation: Rotation from the wrist frame to the pair's base frame, (3, 3).
        centre_gain: Scale of the operator's centre motion onto the robot [-].
    """

    range: PairRange
    human_pinch: PairFeatures
    human_open: PairFeatures
    rotation: np.ndarray
    centre_gain: float

    def __post_init__(self) -> None:
        # read-only copies: the compiled targets copy some of these when built and read
        # the rest in place (a change afterwards would reach the two paths differently)
        for name in ("human_pinch", "human_open"):
            object.__setattr__(self, name, getattr(self, name).frozen())
        object.__setattr__(self, "rotation", read_only(self.rotation))

    def opening(self, human_span: float) -> float:
        """Calibrated opening in [0, 1] of a human span [m] (0 = pinch, 1 = open)."""
        lo, hi = self.human_pinch.span, self.human_open.span
        return min(max(float((human_span - lo) / (hi - lo)), 0.0), 1.0)  # np.clip's result

    def to_targets(self, human: PairFeatures | np.ndarray) -> PairFeatures:
        """Robot targets ``(l_bar, d_bar, c_bar, u_bar)`` for human features (wrist frame)
        (:meth:`_to_targets_numpy`, compiled for stacked features when it can be:
        :mod:`payload.retarget.targets_c`, the same bits).

        Raises:
            RetargetError: A NaN or infinite or malformed feature.
        """
        if isinstance(human, np.ndarray) and human.shape == (N_FEATURES,):
            kernel = self._kernel
            if kernel is not None:
                out = kernel(human)
                if out is not None:
                    return out
        return self._to_targets_numpy(human)

    @property
    def targets_kernel(self) -> Any:
        """The compiled :meth:`to_targets` (:mod:`payload.retarget.targets_c`, checked when
        first asked for), or None (the numpy code runs)."""
        return self._kernel

    @functools.cached_property
    def _kernel(self) -> Any:
        from payload.retarget.targets_c import compiled_targets

        return compiled_targets(self, self._to_targets_numpy)

    def _to_targets_numpy(self, human: PairFeatures | np.ndarray) -> PairFeatures:
        """:meth:`to_targets` in numpy."""
        h = PairFeatures.from_vector(as_feature_vector(human, "human features"))
        rg, rot = self.range, self.rotation
        alpha = self.opening(h.span)
        span = rg.span_min + alpha * (rg.span_max - rg.span_min)
        c_robot = (1.0 - alpha) * rg.pinch.centre + alpha * rg.open.centre
        c_human = (1.0 - alpha) * self.human_pinch.centre + alpha * self.human_open.centre
        centre = c_robot + self.centre_gain * rot @ (h.centre - c_human)
        distal = np.concatenate([rot @ h.distal[:3], rot @ h.distal[3:]])
        return PairFeatures(float(span), rot @ h.direction, centre, distal)

    def posture_reference(self, span: float) -> np.ndarray:
        """Posture reference ``q_ref`` consistent with a commanded span [m], shape (n,)."""
        return self.range.posture(span)

    def command(self, human: PairFeatures | np.ndarray) -> tuple[PairFeatures, np.ndarray]:
        """Targets and the matching posture reference for human features."""
        targets = self.to_targets(human)
        return targets, self.posture_reference(targets.span)


MIN_OPENING = 1e-3
"""How much wider [m] the human's open span must be than their pinch span for a pair's
calibration (a smaller difference would map noise onto the whole finger range)."""


class OpeningError(RetargetError):
    """An open span not :data:`MIN_OPENING` wider than the pinch span.

    Attributes:
        pinch_span: The pinch's thumb-index span [m].
        open_span: The opening's [m].
    """

    def __init__(self, pinch_span: float, open_span: float) -> None:
        self.pinch_span, self.open_span = pinch_span, open_span
        super().__init__(
            f"calibration: the open span ({open_span * 1e3:.1f} mm) must exceed the pinch span "
            f"({pinch_span * 1e3:.1f} mm) by at least {MIN_OPENING * 1e3:g} mm"
        )


def calibrate(
    pinch: PairFeatures | np.ndarray,
    open_: PairFeatures | np.ndarray,
    robot: PairRange,
    rotation: np.ndarray | None = None,
    centre_gain: float | None = None,
) -> PairCalibration:
    """Calibrate one pair from the operator's pinch and open poses.

    Args:
        pinch: Human thumb-index features at the calibration pinch (wrist frame).
        open_: Human features at the calibration full opening (wrist frame).
        robot: The robot pair's range (:func:`pair_range`).
        rotation: Wrist-to-pair-frame rotation (3, 3); ``None``: the Wahba alignment of
            the human's direction features (d, u_1, u_2) at the two poses with the
            robot's at its minimum- and maximum-span postures.
        centre_gain: Scale of the human centre motion; ``None``: the span ratio
            ``(l_max - l_min) / (l_open - l_pinch)``.

    Raises:
        OpeningError: An open span not larger than the pinch span by
            :data:`MIN_OPENING`.
        RetargetError: Non-finite features, or a rotation that is not a rotation matrix.
    """
    hp = PairFeatures.from_vector(as_feature_vector(pinch, "pinch features"))
    ho = PairFeatures.from_vector(as_feature_vector(open_, "open features"))
    if ho.span < hp.span + MIN_OPENING:
        raise OpeningError(hp.span, ho.span)
    if rotation is None:
        human = np.vstack(
            [v.reshape(-1, 3) for v in (hp.direction, hp.distal, ho.direction, ho.distal)]
        )
        rb = robot
        rob = np.vstack(
            [
                v.reshape(-1, 3)
                for v in (rb.pinch.direction, rb.pinch.distal, rb.open.direction, rb.open.distal)
            ]
        )
        rotation = wahba_rotation(human, rob)
    rotation = np.asarray(rotation, dtype=float)
    if (
        rotation.shape != (3, 3)
        or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
        or np.linalg.det(rotation) < 0
    ):
        raise RetargetError("calibration: rotation must be a 3x3 rotation matrix")
    if centre_gain is None:
        centre_gain = (robot.span_max - robot.span_min) / (ho.span - hp.span)
    if not np.isfinite(centre_gain) or centre_gain < 0:
        raise RetargetError("calibration: centre_gain must be finite and non-negative")
    return PairCalibration(robot, hp, ho, rotation, float(centre_gain))
