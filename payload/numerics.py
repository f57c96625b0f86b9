"""Process-wide numerics settings that make results independent of the machine's cores."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from typing import Any

THREAD_VARIABLES: tuple[str, ...] = (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
)
"""What OpenBLAS, OpenMP, MKL and BLIS read their thread counts from when they load."""

_LIMIT_LOCK = threading.Lock()
_LIMIT_USERS = 0
_LIMITER: Any = None
_SAVED_VARIABLES: dict[str, str | None] = {}


@contextlib.contextmanager
def single_threaded_numerics() -> Iterator[None]:
    """Limit BLAS and OpenMP to one thread while any user in this process runs.

    Multi-threaded BLAS sums in a different order, so a result can differ in its last
    bits with the thread count; trials and the retargeter's span ranges run under this so
    every process and machine gets the same numbers.

    The limit covers the BLAS libraries loaded when the first user enters; one loaded
    later inside it (SciPy's, which a trial imports only on a cache miss: the
    propulsion's linear programs, the span range's SLSQP) starts single-threaded, since
    the variables its threads are read from when it loads (:data:`THREAD_VARIABLES`) say
    1 meanwhile. So SciPy need not be loaded here (a tenth of a second a process). Such a
    library keeps its one thread after the limit (threadpoolctl restores the libraries it
    limited on entry only); the variables are the process's, so a subprocess started
    inside the limit inherits them (a Dask worker's trials are single-threaded anyway).

    The limit is process-wide, so it is counted: the first trial to enter sets it and
    the last to leave restores it (a thread leaving early must not lift the limit under
    a trial still running in another thread).
    """
    global _LIMIT_USERS, _LIMITER, _SAVED_VARIABLES
    from threadpoolctl import threadpool_limits

    with _LIMIT_LOCK:
        if _LIMIT_USERS == 0:
            _LIMITER = threadpool_limits(limits=1)
            _SAVED_VARIABLES = {name: os.environ.get(name) for name in THREAD_VARIABLES}
            os.environ.update(dict.fromkeys(THREAD_VARIABLES, "1"))
        _LIMIT_USERS += 1
    try:
        yield
    finally:
        with _LIMIT_LOCK:
            _LIMIT_USERS -= 1
            if _LIMIT_USERS == 0:
                _LIMITER.restore_original_limits()
                _LIMITER = None
                for name, value in _SAVED_VARIABLES.items():
                    if value is None:
                        os.environ.pop(name, None)
                    else:
                        os.environ[name] = value


__all__ = ["THREAD_VARIABLES", "single_threaded_numerics"]
