"""The live Quest server: the WebXR page at ``/``, its WebSocket at ``/ws``, ``/status``.

One asyncio server (``websockets``) answers both plain HTTP (the page's own files and the
status document, through ``process_request``) and the WebSocket. Security:

- it binds 127.0.0.1 by default (a Quest over USB reaches it through ``adb reverse``);
  any other address needs TLS and a session token;
- the token (when required) must come as ``?token=`` on the page, ``/status`` and
  ``/ws``; the ``Origin`` of a WebSocket must be the page's own origin, and on a local
  bind the ``Host`` must be a loopback name (no DNS rebinding);
- only the files of the page (``payload/teleop/web``) are served, by exact name;
- every message is validated (:mod:`payload.teleop.messages`); a refused message or
  connection is counted in ``/status`` and changes nothing else;
- a token, when one is used, is at least :data:`MIN_TOKEN_CHARS` characters (an empty
  or short one is refused, never taken as "no authentication");
- one operator at a time: the first connection to send hand frames (the one that
  calibrates) holds control; the others watch read-only (their frames are refused and
  counted ``not_holder``) until the holder disconnects, hands over (``release``) or leaves
  VR (``xr_end``; a safe stop's reason says which);
  every connection is told its role (``control`` messages) whenever it changes;
- each connection may send at most :data:`RATE_LIMIT_HZ` messages a second (twice the
  fastest headset's frame rate; the excess is dropped before parsing and counted
  ``rate_limited``), and at most :data:`MAX_CLIENTS` connections are open at once.

The WebSocket sends the page ``hello`` (the scene), ``ping`` (clock synchronisation) and
``state`` messages (session state, calibration prompt, vehicle, payload, safe-stop
reasons).
"""

from __future__ import annotations

import asyncio
import errno
import hmac
import json
import logging
import mimetypes
import secrets
import socket
import ssl
import threading
from collections.abc import Callable
from http import HTTPStatus
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from payload.errors import PayloadError, port_in_use_hint
from payload.teleop.emulate import HANDS_JS, emulated_pose
from payload.teleop.live import HANDED_OVER, LEFT_VR, MAX_CLIENTS, LiveHub, now_ms
from payload.teleop.messages import (
    MAX_MESSAGE_BYTES,
    FrameMessage,
    MessageError,
    ReleaseMessage,
    XrEndMessage,
    parse_message,
)

log = logging.getLogger(__name__)

WEB_DIR = Path(__file__).parent / "web"
"""The page's files, installed with the package (package data)."""

LOCAL_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})
WIRE_LIMIT = 1024 * 1024  # the WebSocket layer closes above this; 64 KiB..1 MiB are counted
STATE_PERIOD_S = 0.05  # state messages to the page at 20 Hz
SYNC_PINGS = 6  # clock pings right after connecting, then one every SYNC_PERIOD_S
SYNC_PERIOD_S = 2.0
MIN_TOKEN_CHARS = 16  # new_token() makes 22 (128 bits)
HEADSET_MAX_HZ = 120.0  # the fastest display rate of the Quest headsets (one frame each)
RATE_LIMIT_HZ = 2.0 * HEADSET_MAX_HZ
RATE_BURST = 0.5 * RATE_LIMIT_HZ  # messages a connection may send at once (0.5 s worth):
# a browser that stalled (a loaded machine, a Wi-Fi hiccup) flushes its queued frames at
# once; a sustained flood above the rate is still dropped after half a second
DESKTOP_FILES = ("iwer.js", HANDS_JS.name, "desktop.js")
"""The desktop mode's scripts, as served (``/iwer.js``, ...), in their loading order."""
DESKTOP_SCRIPTS = b"".join(f'<script src="/{name}"></script>\n'.encode() for name in DESKTOP_FILES)
"""The desktop mode's scripts, before the page's: iwer, the emulated Quest and its hands
(the tests' emulated headset's, with :func:`~payload.teleop.emulate.emulated_pose` put
before it as it is served), the keys."""


NO_TOKEN = "missing or wrong token"
TOKEN_HINT = "open the address `payload teleop serve` printed, with its ?token= (new each run)"


class ServerError(PayloadError):
    """The server cannot be set up as asked (insecure bind, port in use)."""


def check_address(host: str, port: int) -> None:
    """Raise :class:`ServerError` now if ``host:port`` cannot be bound (a port in use, an
    address not of this machine), as :meth:`TeleopServer.start` would: a command checks it
    before its long set-up. Port 0 (any free port) always can be."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
        probes = 0
        for family, kind, proto, _, address in infos:
            try:
                probe = socket.socket(family, kind, proto)
            except OSError:  # a family this kernel lacks (IPv6): the server skips it too
                continue
            probes += 1
            with probe:
                # as asyncio's server binds: SO_REUSEADDR (a closed port's TIME_WAIT is free)
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    probe.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                probe.bind(address)
        if not probes:
            raise OSError(f"no address family of {host!r} can be used here")
    except OSError as exc:
        raise _unbound(host, port, exc) from None


def _unbound(host: str, port: int, exc: OSError) -> ServerError:
    """The error of an address that cannot be bound (an IPv6 host in brackets)."""
    where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    hint = ""
    if exc.errno == errno.EADDRINUSE:  # the likeliest: a server still running
        hint = " " + port_in_use_hint("`payload teleop serve`")
    return ServerError(f"cannot listen on {where}: {exc.strerror or exc}{hint}")


def is_local(host: str) -> bool:
    """Whether ``host`` is a loopback bind."""
    return host in LOCAL_HOSTS


def new_token() -> str:
    """A fresh session token (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


def page_files(web_dir: Path = WEB_DIR) -> dict[str, Path]:
    """URL path -> file for every file of the page (``/`` is ``index.html``)."""
    files = {
        f"/{p.name}": p for p in sorted(web_dir.iterdir()) if p.suffix in (".html", ".js", ".css")
    }
    if "/index.html" in files:
        files["/"] = files["/index.html"]
    return files


def _response(status: int, body: bytes, content_type: str) -> Response:
    headers = Headers(
        [
            ("Content-Type", content_type),
            ("Content-Length", str(len(body))),
            ("Cache-Control", "no-store"),
            ("X-Content-Type-Options", "nosniff"),
            ("Referrer-Policy", "no-referrer"),
            (
                "Content-Security-Policy",
                "default-src 'self'; connect-src 'self'; img-src 'self' data:; "
                "frame-ancestors 'none'",
            ),
            ("Connection", "close"),
        ]
    )
    return Response(status, HTTPStatus(status).phrase, headers, body)


def _text(status: int, text: str) -> Response:
    return _response(status, text.encode(), "text/plain; charset=utf-8")


class _Link:
    """One WebSocket connection: its sequence numbers and its clock offset."""

    def __init__(self) -> None:
        self.last_seq = -1
        self.last_t = float("-inf")
        self.pings: dict[int, float] = {}
        self.samples: list[tuple[float, float]] = []  # (round trip, offset) [ms]
        self.next_id = 0
        self.allowance = RATE_BURST  # token bucket of the rate limit [messages]
        self.checked = now_ms()

    def admit(self) -> bool:
        """Whether one more message fits the rate limit (token bucket)."""
        t = now_ms()
        self.allowance = min(RATE_BURST, self.allowance + (t - self.checked) * RATE_LIMIT_HZ / 1e3)
        self.checked = t
        if self.allowance < 1.0:
            return False
        self.allowance -= 1.0
        return True

    @property
    def offset_ms(self) -> float | None:
        """Page clock - server clock [ms], from the fastest recent round trip."""
        if not self.samples:
            return None
        return min(self.samples[-10:])[1]


class TeleopServer:
    """The HTTP + WebSocket server in front of a :class:`LiveHub`.

    Args:
        hub: Shared state with the teleoperation loop.
        host: Bind address (default loopback).
        port: TCP port (0 = any free port).
        ssl_context: TLS context; required unless the bind is local.
        token: Session token; required unless the bind is local (made when None).
        scene: What the page needs to draw the world (sent in ``hello``).
        web_dir: The page's folder.
        desktop: iwer's browser build: serve the desktop mode (an emulated headset driven
            by the keyboard, ``web/desktop/desktop.js``) with the page; None: never.
    """

    def __init__(
        self,
        hub: LiveHub,
        host: str = "127.0.0.1",
        port: int = 8765,
        *,
        ssl_context: ssl.SSLContext | None = None,
        token: str | None = None,
        scene: dict[str, Any] | None = None,
        web_dir: Path = WEB_DIR,
        desktop: Path | None = None,
    ) -> None:
        self.hub = hub
        self.host = host
        self.port = port
        self.local = is_local(host)
        if not self.local and ssl_context is None:
            raise ServerError(f"--host {host}: binding a non-local address requires TLS")
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise ServerError(
                f"session token: {len(token)} characters; at least {MIN_TOKEN_CHARS} needed"
            )
        self.ssl_context = ssl_context
        self.token = token if token is not None or self.local else new_token()
        self.scene = scene or {}
        self.files = page_files(web_dir)
        self.desktop = desktop is not None
        if desktop is not None:
            iwer, *ours = DESKTOP_FILES
            self.files[f"/{iwer}"] = desktop
            self.files.update({f"/{name}": web_dir / "desktop" / name for name in ours})
        self._server: Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # -- addresses -------------------------------------------------------------------------
    @property
    def scheme(self) -> str:
        return "https" if self.ssl_context is not None else "http"

    def url(self, host: str | None = None) -> str:
        """The page's address (with the token when one is required)."""
        h = host or ("localhost" if self.local else self.host)
        if ":" in h:
            h = f"[{h}]"
        query = f"/?token={self.token}" if self.token else "/"
        return f"{self.scheme}://{h}:{self.port}{query}"

    # -- HTTP ------------------------------------------------------------------------------
    def _authorised(self, request: Request, query: dict[str, list[str]]) -> str | None:
        """None when the request may proceed, else why not."""
        hosts = request.headers.get_all("Host")
        if len(hosts) != 1 or len(request.headers.get_all("Origin")) > 1:
            return "Host and Origin must each appear once"
        host = hosts[0]
        hostname = urlsplit(f"//{host}").hostname or ""
        if self.local and hostname not in LOCAL_HOSTS:
            return f"Host {host!r} is not a loopback name"
        if self.token:
            given = query.get("token", [""])[0]
            if not hmac.compare_digest(given.encode(), self.token.encode()):
                return NO_TOKEN
        return None

    def _origin_ok(self, request: Request) -> bool:
        origin = request.headers.get("Origin")
        host = request.headers.get("Host", "")
        return origin is not None and origin == f"{self.scheme}://{host}"

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        try:
            return self._route(connection, request)
        except Exception as exc:  # a request we did not foresee never takes the server down
            self.hub.drop("malformed")
            log.warning("teleop server: bad request from %s: %r", _peer(connection), exc)
            return _text(400, "bad request\n")

    def _route(self, connection: ServerConnection, request: Request) -> Response | None:
        parts = urlsplit(request.path)
        path, query = parts.path, parse_qs(parts.query)
        if path == "/ws":
            why = self._authorised(request, query)
            if why is None and not self._origin_ok(request):
                why = f"Origin {request.headers.get('Origin')!r} is not the page's"
            if why is not None:
                self.hub.drop("unauthorized")
                log.warning("teleop server: refused WebSocket from %s: %s", _peer(connection), why)
                return _text(403, "forbidden\n")
            if self.hub.status()["clients"] >= MAX_CLIENTS:
                self.hub.drop("connection_cap")
                return _text(503, f"at most {MAX_CLIENTS} connections\n")
            return None
        if path == "/status" or path == "/":
            why = self._authorised(request, query)
            if why is not None:
                self.hub.drop("unauthorized")
                log.warning("teleop server: refused %s from %s: %s", path, _peer(connection), why)
                if why == NO_TOKEN:  # a person typed the address: say what opens it
                    return _text(403, f"forbidden: {NO_TOKEN}; {TOKEN_HINT}\n")
                return _text(403, "forbidden\n")
            if path == "/status":
                body = json.dumps(self.hub.status()).encode()
                return _response(200, body, "application/json")
        file = self.files.get(path)
        if file is None:
            return _text(404, "not found\n")
        ctype = mimetypes.guess_type(file.name)[0] or "application/octet-stream"
        if file.suffix == ".js":
            ctype = "text/javascript"
        body = file.read_bytes()
        if self.desktop and path == f"/{HANDS_JS.name}":
            body = emulated_pose().encode() + body
        if self.desktop and file.name == "index.html":  # the emulated headset first
            body = body.replace(
                b'<script type="module"', DESKTOP_SCRIPTS + b'<script type="module"'
            )
        return _response(200, body, f"{ctype}; charset=utf-8")

    # -- WebSocket -------------------------------------------------------------------------
    async def _handler(self, ws: ServerConnection) -> None:
        conn_id = id(ws)
        link = _Link()
        self.hub.connect(conn_id)
        log.info("teleop server: page connected from %s", _peer(ws))
        hello = {"type": "hello", "scene": self.scene, "max_message_bytes": MAX_MESSAGE_BYTES,
                 "driver": self.hub.status()["driver"],
                 "hardware": self.hub.drives_hardware}  # fmt: skip
        tasks = []
        try:
            await ws.send(json.dumps(hello))
            tasks = [
                asyncio.create_task(self._sync(ws, link)),
                asyncio.create_task(self._push_state(ws, conn_id)),
            ]
            async for data in ws:
                self._receive(conn_id, link, data)
        except ConnectionClosed as exc:
            if exc.sent is not None and exc.sent.code == 1009:
                self.hub.drop("oversized")
        finally:
            for task in tasks:
                task.cancel()
            self.hub.disconnect(conn_id)
            log.info("teleop server: page disconnected (%s)", _peer(ws))

    def _receive(self, conn_id: int, link: _Link, data: str | bytes) -> None:
        if not link.admit():
            self.hub.drop("rate_limited")
            return
        try:
            msg = parse_message(data)
        except MessageError as exc:
            self.hub.drop(exc.kind)
            log.debug("teleop server: dropped a message: %s", exc)
            return
        if isinstance(msg, FrameMessage):
            if msg.seq <= link.last_seq or msg.t < link.last_t:
                self.hub.drop("out_of_order")
                return
            link.last_seq, link.last_t = msg.seq, msg.t
            self.hub.put(conn_id, msg, link.offset_ms)
            return
        if isinstance(msg, (ReleaseMessage, XrEndMessage)):
            why = LEFT_VR if isinstance(msg, XrEndMessage) else HANDED_OVER
            if self.hub.release(conn_id, why):
                log.info("teleop server: %s: control is free", why)
            return
        sent = link.pings.pop(msg.id, None)
        if sent is None:
            self.hub.drop("malformed")
            return
        received = now_ms()
        link.samples.append((received - sent, msg.t - 0.5 * (sent + received)))
        del link.samples[:-10]

    async def _sync(self, ws: ServerConnection, link: _Link) -> None:
        n = 0
        while True:
            link.pings[link.next_id] = now_ms()
            await ws.send(json.dumps({"type": "ping", "id": link.next_id}))
            link.next_id += 1
            n += 1
            for stale in [k for k in link.pings if k < link.next_id - 10]:
                del link.pings[stale]
            await asyncio.sleep(0.1 if n < SYNC_PINGS else SYNC_PERIOD_S)

    async def _push_state(self, ws: ServerConnection, conn_id: int) -> None:
        seen, told = -1, ""
        while True:
            role = self.hub.role(conn_id)
            if role != told:  # the role changed: this connection is told at once
                told = role
                await ws.send(json.dumps({"type": "control", "role": role}))
            with self.hub.lock:
                seq, snap, state = self.hub.snapshot_seq, self.hub.snapshot, self.hub.state
                driver = self.hub.driver
            if seq != seen:
                seen = seq
                msg = {"type": "state", "state": state, "driver": driver, **snap}
                await ws.send(json.dumps(msg))
            await asyncio.sleep(STATE_PERIOD_S)

    # -- running ---------------------------------------------------------------------------
    async def _main(self) -> None:
        try:
            self._server = await serve(
                self._handler,
                self.host,
                self.port,
                ssl=self.ssl_context,
                process_request=self._process_request,
                max_size=WIRE_LIMIT,
                server_header=None,
            )
        except OSError as exc:
            self._error = _unbound(self.host, self.port, exc)
            self._ready.set()
            return
        sock = next(iter(self._server.sockets))
        self.port = int(sock.getsockname()[1])
        self._ready.set()
        await self._server.wait_closed()

    def start(self) -> TeleopServer:
        """Serve from a background thread; returns once listening.

        Raises:
            ServerError: The address cannot be bound.
        """

        def run() -> None:
            self._loop = asyncio.new_event_loop()
            self._loop.run_until_complete(self._main())
            self._loop.close()

        self._thread = threading.Thread(target=run, name="teleop-server", daemon=True)
        self._thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        """Close every connection and stop listening."""
        if self._server is not None and self._loop is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        if self._thread is not None:
            self._thread.join(10)

    def call(self, fn: Callable[[], Any]) -> None:
        """Run ``fn`` on the server's event loop (e.g. to drop every connection)."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(fn)

    def close_clients(self) -> None:
        """Drop every WebSocket connection (the page reconnects by itself)."""
        if self._server is None:
            return
        for conn in list(self._server.connections):
            self.call(lambda c=conn: asyncio.ensure_future(c.close(1001, "server drop")))

    def __enter__(self) -> TeleopServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _peer(conn: ServerConnection) -> str:
    try:
        addr = conn.remote_address
    except Exception:
        return "?"
    return f"{addr[0]}:{addr[1]}" if addr else "?"
