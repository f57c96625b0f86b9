"""Process-wide numerics settings that make results independent of the machine's cores."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

_LIMIT_LOCK = threading.Lock()
_LIMIT_USERS = 0
_LIMITER: Any = None


@contextlib.contextmanager
def single_threaded_numerics() -> Iterator[None]:
    """Limit BLAS and OpenMP to one thread while any user in this process runs.

    Multi-threaded BLAS sums in a different order, so a result can differ in its last
    bits with the thread count; trials and the retargeter's span ranges run under this so
    every process and machine gets the same numbers.

    The limit covers the BLAS libraries loaded when the first user enters, so SciPy's
    (which the trials and span ranges use: linear programs, SLSQP) is loaded here first.

    The limit is process-wide, so it is counted: the first trial to enter sets it and
    the last to leave restores it (a thread leaving early must not lift the limit under
    a trial still running in another thread).
    """
    global _LIMIT_USERS, _LIMITER
    # SciPy ships its own OpenBLAS, loaded with scipy.linalg; a library loaded after the
    # limit is set escapes it, so it is loaded first (nothing imports SciPy at start-up)
    import scipy.linalg  # noqa: F401
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


__all__ = ["single_threaded_numerics"]
