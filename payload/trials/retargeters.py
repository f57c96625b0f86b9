"""The trials' retargeters, built once per thread."""

from __future__ import annotations

import threading
from typing import Any

from payload.numerics import single_threaded_numerics
from payload.project import Project, current_project
from payload.retarget.calibration import PairRange, pair_range
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.hand import load_hand
from payload.retarget.objective import RetargetConfig

_LOCAL = threading.local()


def retargeting(
    project: Project | None = None, budget: str = "paper", collisions: bool = False
) -> tuple[dict[str, PairRetargeter], dict[str, PairRange]]:
    """Production retargeters (with this evaluation budget, see
    :attr:`RetargetConfig.budget <payload.retarget.RetargetConfig.budget>`, and with
    self-collision modelled when ``collisions``: no command inside the design's margin, the
    calibration's span range restricted to collision-free postures) and pair ranges for our
    hand on ``project``'s URDF (default: the current project), built once per thread, URDF
    and design content, resolved hand, budget and collision setting.

    A retargeter holds its solver's buffers and warm start, so concurrent trials (a Dask
    worker with several threads) each get their own; nothing here is shared between
    threads.
    """
    hand = load_hand(project=project or current_project())
    # everything the retargeters are built from: the URDF, the resolved hand (rest
    # posture, margin) and the design it names (pre-shape, structure boxes)
    design = hand.design.read_bytes() if hand.design is not None else b""
    collisions = bool(collisions)
    key = (hand.urdf, hand.urdf.read_bytes(), repr(hand), design, budget, collisions)
    built: dict[Any, Any] = getattr(_LOCAL, "retargeting", None) or {}
    _LOCAL.retargeting = built
    cached = built.get(key)
    if cached is None:
        # single-threaded like the trials themselves, so every process finds the same ranges
        with single_threaded_numerics():
            config = RetargetConfig(budget=budget, collisions=collisions)
            retargeters = {
                pair: PairRetargeter(hand, pair=pair, config=config) for pair in ("L", "R")
            }
            ranges = {
                pair: pair_range(r.kinematics, collisions=r.collisions)
                for pair, r in retargeters.items()
            }
        cached = built[key] = (retargeters, ranges)
    return cached
