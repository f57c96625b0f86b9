"""Meshcat servers for a review: start one, or attach to a running one (``--zmq-url``)."""

from __future__ import annotations

import contextlib
import io
from typing import Any

from meshcat.commands import Delete

from payload.review.scene import ROOT, ReviewError, mpath

ANSWER_TIMEOUT_MS = 5000
"""How long an existing server has to answer before ``--zmq-url`` gives up [ms]."""


def check_server(zmq_url: str) -> None:
    """Raise :class:`ReviewError` unless a meshcat server answers at ``zmq_url``."""
    import zmq

    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, ANSWER_TIMEOUT_MS)
    try:
        sock.connect(zmq_url)
        sock.send(b"url")
        sock.recv()
    except zmq.error.Again:
        raise ReviewError(f"--zmq-url {zmq_url}: no meshcat server answers there") from None
    except zmq.error.ZMQError as exc:
        raise ReviewError(f"--zmq-url {zmq_url}: {exc}") from None
    finally:
        sock.close()


def open_viewer(zmq_url: str | None = None, quiet: bool = True) -> Any:
    """A meshcat ``Visualizer``: a new server (``zmq_url`` None) or an existing one.

    A new server runs as a child process until :func:`close_viewer` (or the end of this
    process). An existing server's scene under :data:`ROOT` is cleared first.
    """
    import meshcat

    if zmq_url is not None:
        check_server(zmq_url)
    out = io.StringIO()
    with contextlib.redirect_stdout(out) if quiet else contextlib.nullcontext():
        try:
            vis = meshcat.Visualizer(zmq_url=zmq_url)
        except RuntimeError as exc:
            raise ReviewError(f"cannot start a meshcat server: {exc}") from exc
    if zmq_url is not None:
        vis.window.send(Delete(mpath(ROOT)))
    return vis


def close_viewer(vis: Any) -> None:
    """Stop the server :func:`open_viewer` started (nothing for an attached one)."""
    proc = getattr(vis.window, "server_proc", None)
    if proc is not None and proc.poll() is None:
        proc.kill()
        proc.wait()


__all__ = ["check_server", "close_viewer", "open_viewer"]
