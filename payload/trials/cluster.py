"""The Dask client that campaigns and design sweeps run on."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def dask_client(workers: int, scheduler: str | None, error: type[Exception]) -> Iterator[Any]:
    """A Dask client: on a local cluster of ``workers`` one-thread processes, or on the
    existing ``scheduler`` (e.g. ``tcp://host:8786``). Closed, with its local cluster, on
    exit.

    Raises:
        error: The scheduler cannot be reached (one line naming it).
    """
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler is None:
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
    try:
        with client:
            yield client
    finally:
        if cluster is not None:
            cluster.close()


__all__ = ["dask_client"]
