"""The Dask client that campaigns and design sweeps run on."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

WORKER_CONFIG: dict[str, Any] = {"distributed.worker.profile.enabled": False}
"""Dask settings of the local cluster's workers (the nanny hands them to each worker)."""


@contextmanager
def dask_client(workers: int, scheduler: str | None, error: type[Exception]) -> Iterator[Any]:
    """A Dask client: on a local cluster of ``workers`` one-thread processes, or on the
    existing ``scheduler`` (e.g. ``tcp://host:8786``). Closed, with its local cluster, on
    exit.

    Raises:
        error: The scheduler cannot be reached (one line naming it).
    """
    import dask
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler is None:
        # The workers' statistical profiler samples the running task's stack every 10 ms
        # while holding the GIL: 19.3/18.3 s against 15.8/16.1 s a trial on this 2-core
        # machine (docs/speed.md, item 9). Nothing here reads its profiles, so it is off.
        with dask.config.set(WORKER_CONFIG):
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout=10)
        except (OSError, TimeoutError) as exc:
            raise error(f"cannot reach Dask scheduler {scheduler}: {exc}") from None
        except ValueError as exc:  # not an address: "missing port number", a bad protocol
            raise error(
                f"--scheduler {scheduler}: not a Dask scheduler address ({exc}); "
                "expected e.g. tcp://host:8786"
            ) from None
    try:
        with client:
            yield client
    finally:
        if cluster is not None:
            cluster.close()


__all__ = ["WORKER_CONFIG", "dask_client"]
