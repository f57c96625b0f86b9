"""``payload review --watch``: a review page that follows the design file as it is saved.

A :class:`LiveReview` rebuilds, on every save of ``cad/design.toml``, the generated
models (:func:`payload.design.build.write`), the envelope check and the review scene,
and keeps each build's commands keyed by what they set (:func:`payload.review.page.command_key`).
The page (:func:`payload.review.page.live_html`) polls ``/update?have=V``; the answer
holds only the commands that differ from version ``V`` (and deletes of nodes gone), so
a changed finger length re-sends that finger's meshes and poses, not the vehicle. An
invalid design keeps the last good scene and sends its one-line error instead.
"""

from __future__ import annotations

import base64
import errno
import json
import secrets
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

from meshcat.commands import Delete

from payload.errors import PayloadError, port_in_use_hint
from payload.review.errors import ReviewError
from payload.review.page import command_key, live_html, packed
from payload.review.scene import Scene, mpath

POLL_S = 0.1
"""How often the design file's modification time is read [s]."""
KEPT_VERSIONS = 4
"""Builds remembered, so a page a few versions behind still gets only the changes."""
CAMERA_KEY = ("set_property:position", "/Cameras/default/rotated/<object>")
"""The camera's position: sent with the first build only, so a rebuild keeps the view."""


@dataclass
class Build:
    """One build of the scene.

    Attributes:
        version: Build number (0 first).
        commands: ``(key, base64 blob)`` in send order; key from :func:`command_key`.
        overlay: The overlay as the page reads it.
    """

    version: int
    commands: list[tuple[tuple[str, str, bytes], str]]
    overlay: dict[str, Any]


def encode(scene: Scene) -> list[tuple[tuple[str, str, bytes], str]]:
    """The scene's commands as ``(key, base64 blob)``, the last per key, in send order."""
    out: dict[tuple[str, str], tuple[tuple[str, str, bytes], str]] = {}
    for command in scene.all_commands():
        blob = packed(command)
        key = command_key(command, blob)
        out.pop(key[:2], None)
        out[key[:2]] = (key, base64.b64encode(blob).decode("ascii"))
    return list(out.values())


class LiveReview:
    """The builds of a design project's review and the error of the last failed one.

    Args:
        design: The design file.
        build: Builds the scene from the design file (raises :class:`PayloadError` on an
            invalid design); it also regenerates the models.
    """

    def __init__(self, design: Path, build: Callable[[], Scene]) -> None:
        self.design = Path(design)
        self._build = build
        self._lock = threading.Lock()
        self.builds: list[Build] = []
        self.error: str | None = None
        self.stamp: tuple[int, int] | None = None
        self._notes: list[str] = []
        self.session = secrets.token_hex(8)
        """This review's own name: a page that was open on another review (an earlier one
        on the same port, whose versions count from 0 too) reloads when it changes."""

    def notes(self) -> list[str]:
        """The last good build's notes (design, verdict, findings)."""
        return list(self._notes)

    def _stamp(self) -> tuple[int, int] | None:
        try:
            st = self.design.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def rebuild(self) -> str | None:
        """Build the scene now; returns the error line of an invalid design (else None)."""
        self.stamp = self._stamp()
        try:
            scene = self._build()
        except (PayloadError, ValueError, OSError) as exc:
            text = str(exc)  # a design file error names the file itself: once, not twice
            named = text.startswith(f"{self.design}: ")
            with self._lock:
                self.error = text if named else f"{self.design}: {text}"
            return self.error
        version = self.builds[-1].version + 1 if self.builds else 0
        build = Build(version, encode(scene), scene.overlay.as_json())
        with self._lock:
            self.builds = [*self.builds[-(KEPT_VERSIONS - 1) :], build]
            self.error = None
            self._notes = list(scene.notes)
        return None

    def changed(self) -> bool:
        """Whether the design file was saved since the last build."""
        return self._stamp() not in (None, self.stamp)

    def update(self, have: int) -> dict[str, Any]:
        """What a page holding build ``have`` (-1: none) needs to show the latest one; its
        ``session`` names this review (a page that held another's reloads)."""
        with self._lock:
            error, builds = self.error, list(self.builds)
        none = {"commands": [], "overlay": None, "error": error, "session": self.session}
        if not builds:
            return {"version": -1, **none}
        last = builds[-1]
        if have == last.version:
            return {"version": have, **none}
        old = next((b for b in builds if b.version == have), None)
        if old is None:
            commands = [blob for _, blob in last.commands]
        else:
            before = {key for key, _ in old.commands}
            commands = [
                blob for key, blob in last.commands if key not in before and key[:2] != CAMERA_KEY
            ]
            now = {key[1] for key, _ in last.commands if key[0] == "set_object"}
            for key, _ in old.commands:
                if key[0] == "set_object" and key[1] not in now:
                    gone = packed(Delete(mpath(key[1])))
                    commands.append(base64.b64encode(gone).decode("ascii"))
        return {
            "version": last.version,
            "commands": commands,
            "overlay": last.overlay,
            "error": error,
            "session": self.session,
        }

    def watch(self, stop: threading.Event, log: Callable[[str], None] = print) -> None:
        """Rebuild on every save of the design file until ``stop`` is set."""
        while not stop.wait(POLL_S):
            if not self.changed():
                continue
            t0 = time.perf_counter()
            err = self.rebuild()
            if err is not None:
                log(f"error: {err}")
            else:
                seconds = time.perf_counter() - t0
                log(f"rebuilt in {seconds:.1f} s (version {self.builds[-1].version})")
                for line in self.notes():  # the new verdict and findings (the file is known)
                    if not line.startswith("design: "):
                        log(line)


def _handler(live: LiveReview) -> type[BaseHTTPRequestHandler]:
    page = live_html().encode("utf-8")

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            url = urlparse(self.path)
            if url.path in ("/", "/index.html"):
                self._send(page, "text/html; charset=utf-8")
            elif url.path == "/update":
                have = parse_qs(url.query).get("have", ["-1"])[0]
                try:
                    body = live.update(int(have))
                except ValueError:
                    self.send_error(400, "have: expected an integer")
                    return
                self._send(json.dumps(body).encode("utf-8"), "application/json")
            else:
                self.send_error(404)

        def _send(self, body: bytes, kind: str) -> None:
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args: Any) -> None:
            return

    return Handler


def serve(live: LiveReview, port: int = 0, host: str = "127.0.0.1") -> ThreadingHTTPServer:
    """Serve the live page and its updates on ``host:port`` (0: any free port), in a thread.

    Returns:
        The server (``server.server_address`` has the port; ``shutdown()`` stops it).

    Raises:
        ReviewError: The address cannot be bound (the port is in use, say).
    """
    try:
        server = ThreadingHTTPServer((host, port), _handler(live))
    except OSError as exc:
        why = "in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        raise ReviewError(
            f"--port {port}: cannot listen on {host}:{port}: {why} {port_in_use_hint('review')}"
        ) from None
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True, name="review-http").start()
    return server


def run(
    live: LiveReview,
    port: int,
    on_ready: Callable[[str], None] | None = None,
    watch: bool = True,
) -> int:
    """Serve (and with ``watch``, follow the design file) until Ctrl-C; returns 0."""
    server = serve(live, port)
    url = f"http://{server.server_address[0]}:{server.server_address[1]}/"
    print(f"review: {url}")
    if on_ready is not None:
        on_ready(url)
    what = f"watching {live.design}" if watch else "serving the review"
    print(f"{what}; Ctrl-C to stop", file=sys.stderr)
    stop = threading.Event()
    try:
        if watch:
            live.watch(stop)
        else:
            stop.wait()
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        server.shutdown()
        server.server_close()
    print("stopped", file=sys.stderr)
    return 0


__all__ = ["Build", "LiveReview", "encode", "run", "serve"]
