"""The trials' retargeters, built once per thread, and single-threaded numerics."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

from payload.project import Project, current_project
from payload.retarget.calibration import PairRange, pair_range
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.hand import load_hand
from payload.retarget.objective import RetargetConfig

_LOCAL = threading.local()


def retargeting(
    project: Project | None = None, budget: str = "paper"
) -> tuple[dict[str, PairRetargeter], dict[str, PairRange]]:
    """Production retargeters (with this evaluation budget, see
    :attr:`RetargetConfig.budget <payload.retarget.RetargetConfig.budget>`) and pair ranges
    for our hand on ``project``'s URDF (default: the current project), built once per
    thread, URDF content and budget.

    A retargeter holds its solver's buffers and warm start, so concurrent trials (a Dask
    worker with several threads) each get their own; nothing here is shared between
    threads.
    """
    hand = load_hand(project=project or current_project())
    key = (hand.urdf, hand.urdf.read_bytes(), budget)
    built: dict[Any, Any] = getattr(_LOCAL, "retargeting", None) or {}
    _LOCAL.retargeting = built
    cached = built.get(key)
    if cached is None:
        # single-threaded like the trials themselves, so every process finds the same ranges
        with single_threaded_numerics():
            config = RetargetConfig(budget=budget)
            retargeters = {
                pair: PairRetargeter(hand, pair=pair, config=config) for pair in ("L", "R")
            }
            ranges = {
                pair: pair_range(r.kinematics, collisions=r.collisions)
                for pair, r in retargeters.items()
            }
        cached = built[key] = (retargeters, ranges)
    return cached


_LIMIT_LOCK = threading.Lock()
_LIMIT_USERS = 0
_LIMITER: Any = None


@contextlib.contextmanager
def single_threaded_numerics() -> Iterator[None]:
    """Limit BLAS and OpenMP to one thread while any trial in this process runs.

    The limit is process-wide, so it is counted: the first trial to enter sets it and
    the last to leave restores it (a thread leaving early must not lift the limit under
    a trial still running in another thread).
    """
    global _LIMIT_USERS, _LIMITER
    from threadpoolctl import threadpool_limits

    with _LIMIT_LOCK:
        if _LIMIT_USERS == 0:
            _LIMITER = threadpool_limits(limits=1)
        _LIMIT_USERS += 1
    try:
        yield
    finally:
        with _LIMIT_LOCK:
            _LIMIT_USERS -= 1
            if _LIMIT_USERS == 0:
                _LIMITER.restore_original_limits()
                _LIMITER = None
