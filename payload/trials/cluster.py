"""The Dask client that campaigns and design sweeps run on."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

WORKER_CONFIG: dict[str, Any] = {"distributed.worker.profile.enabled": False}
"""Dask settings of the local cluster's workers (the nanny hands them to each worker)."""


@contextmanager
def _workers_ignore_ctrl_c() -> Iterator[None]:
    """Start the local cluster's processes with Ctrl-C ignored (inherited by the processes
    started meanwhile, kept across their interpreter's start): a Ctrl-C in the terminal
    reaches the whole process group, and each worker printed a KeyboardInterrupt
    traceback while this process stopped the campaign or sweep, which closes them. A
    Ctrl-C in the second or two the cluster takes to start is not seen (ignored, as the
    workers must inherit it; blocking it instead would not reach the processes the
    cluster's own loop thread starts): the next one is."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield  # signal dispositions are the main thread's to change
        return
    saved = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, saved)


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
        # machine (docs/speed-log.md, item 9). Nothing here reads its profiles, so it is off.
        with dask.config.set(WORKER_CONFIG), _workers_ignore_ctrl_c():
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                # no dashboard, but the scheduler still serves its HTTP routes (health,
                # metrics): on any free port, not Dask's default 8787, which another
                # campaign or sweep running at the same time holds (Dask then warns that
                # the port is in use and takes another one anyway)
                scheduler_kwargs={"dashboard_address": ":0"},
                silence_logs=logging.ERROR,
            )
        client = Client(cluster)
    else:
        check_scheduler(scheduler, error)
        try:
            client = Client(scheduler, timeout=10)
        except (OSError, TimeoutError) as exc:
            raise error(f"cannot reach Dask scheduler {scheduler}: {exc}") from None
        except ValueError as exc:  # an address Dask's parsers took and its client did not
            raise error(_not_an_address(scheduler, str(exc))) from None
    try:
        with client:
            yield client
    finally:
        if cluster is not None:
            cluster.close()


def check_scheduler(address: str | None, error: type[Exception]) -> None:
    """Refuse (``error``, one line) a ``--scheduler`` that is not a Dask scheduler address,
    before anything is made for the run (None: the local cluster)."""
    bad = None if address is None else _address_fault(address)
    if bad is not None:
        raise error(_not_an_address(str(address), bad))


def _not_an_address(address: str, why: str) -> str:
    return f"--scheduler {address}: not a Dask scheduler address ({why}); expected e.g. tcp://host:8786"


def _address_fault(address: str) -> str | None:
    """Why ``address`` is not a Dask scheduler address (None: it parses), found by Dask's
    own parsers before any connection is tried: a client made for an unparsable address
    raises only from its connection attempt, and in a process whose earlier client left
    Dask's event loop behind it can wait there for good."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import get_backend

    try:
        scheme, location = parse_address(address)
        get_backend(scheme)
        if scheme != "inproc":
            parse_host_port(location)
    except ValueError as exc:
        return str(exc)
    return None


__all__ = ["WORKER_CONFIG", "check_scheduler", "dask_client"]
