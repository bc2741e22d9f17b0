"""HTTP + WebSocket server of the viewer (runs on the destination rank, in its own thread).

``GET /`` serves the page, ``/viewer.js`` and ``/viewer.css`` its assets (shipped in the
package, no build step), ``/ws`` upgrades to a WebSocket that carries:

* server → browser: a ``hello`` JSON (choices and current settings), then per frame a JPEG
  (binary) and a ``stats`` JSON; each client gets the latest frame only, so a slow client
  drops frames instead of slowing the ranks;
* browser → server: ``input`` and ``settings`` messages (:mod:`state`); anything malformed is
  rejected, logged and answered with an ``error`` message, and the stream goes on. Messages
  over 64 KiB close that client's connection (the page reconnects); the job keeps running.

**Access.** Bound to loopback (the default), the server answers only requests whose ``Host``
is a loopback name (no DNS rebinding). Bound to anything else it requires a secret: a random
token, printed in the URL (``/?token=...``, as Jupyter does); the page sets it as a
``SameSite=Strict`` cookie, and every request — page, assets, WebSocket upgrade — without the
token (query or cookie) gets 403. The WebSocket upgrade also needs an ``Origin`` equal to the
page's own (``http://`` + the request's ``Host``), so a page of another site open in the same
browser cannot drive the camera; browsers always send ``Origin`` on WebSockets.

**Several browsers: all watch, one steers.** Every connected browser gets the stream. The
first one to connect is the *pilot*: only its ``input`` and ``settings`` messages are applied;
the others are *watchers*, whose control messages are answered with an ``error`` (not counted
as malformed). When the pilot closes, the longest-connected watcher becomes the pilot (it is
told by a ``role`` message; ``hello`` carries each browser's initial role).
"""

from __future__ import annotations

import asyncio
import errno
import hmac
import importlib.resources
import ipaddress
import json
import logging
import secrets
import socket
import threading
from http.cookies import SimpleCookie
from urllib.parse import parse_qs, urlsplit

from ...core.errors import ConfigError
from .state import MAX_MESSAGE, MessageError, ViewerState

__all__ = ["ViewerServer", "is_loopback", "check_port"]

log = logging.getLogger("massview.viewer")

_ASSETS = {"/": ("index.html", "text/html; charset=utf-8"), "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
           "/viewer.css": ("viewer.css", "text/css; charset=utf-8")}


COOKIE = "massview_token"


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses (127.0.0.0/8, ::1)."""
    h = host.strip("[]").lower()
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def _port_in_use(host: str, port: int) -> ConfigError:
    return ConfigError(f"port {port} on {host} is in use; pass --port another (e.g. --port 0 picks a free one)")


def check_port(host: str, port: int) -> None:
    """Raise ConfigError (one line: which port, what to pass instead) when ``port`` on ``host``
    cannot be bound because something holds it; checked before a scene is loaded or ranks are
    started. Binds as the server does: every address ``host`` resolves to, SO_REUSEADDR (so a
    closed connection's TIME_WAIT does not count), IPv6 sockets v6-only. Port 0 always binds;
    other bind failures (no such address) are left to the server to report."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror:
        return
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                s.bind(addr)
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    raise _port_in_use(host, port) from None
                return


def _host_name(host_header: str) -> str:
    """The host part of a ``Host`` header (``[::1]:8080`` -> ``::1``)."""
    h = host_header.strip()
    if h.startswith("["):
        return h[1:h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


class _Client:
    def __init__(self, ws, role: str):
        self.ws = ws
        self.role = role
        self.frame: bytes | None = None
        self.stats: str | None = None
        self.ready = asyncio.Event()


class ViewerServer:
    """``token``: required off loopback (a random one is made when None); ``url`` says where to go."""

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, token: str | None = None):
        self.state, self.host, self.port = state, host, port
        self.loopback = is_loopback(host)
        self.token = None if self.loopback and token is None else (token or secrets.token_urlsafe(24))
        self._clients: list[_Client] = []  # in connection order: the first is the pilot
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="massview-viewer", daemon=True)

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()
        self._started.wait(30)
        if isinstance(self._error, OSError) and self._error.errno == errno.EADDRINUSE:  # taken since check_port
            raise _port_in_use(self.host, self.port) from None
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # noqa: BLE001 - reported by start()
            self._error = e
            self._started.set()

    async def _main(self) -> None:
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(self._handler, self.host, self.port, process_request=self._http, max_size=MAX_MESSAGE,
                         ping_interval=20, ping_timeout=20) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._started.set()
            await self._stop.wait()

    def stop(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=5)

    @property
    def url(self) -> str:
        """The address to open (with the token when one is required)."""
        host = socket.gethostname() if self.host in ("0.0.0.0", "::", "") else self.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    # -- HTTP ---------------------------------------------------------------------------
    def _refusal(self, request) -> str | None:
        """Why this request is refused (403), or None to serve it (see the module docstring)."""
        host = request.headers.get("Host", "")
        if self.loopback and not is_loopback(_host_name(host)):
            return f"Host {host!r} is not this machine's loopback name"
        if self.token is not None:
            given = parse_qs(urlsplit(request.path).query).get("token", [""])[0]
            cookie = SimpleCookie()
            try:
                cookie.load(request.headers.get("Cookie", ""))
            except Exception:  # noqa: BLE001 - a malformed cookie is no token
                pass
            given = given or (cookie[COOKIE].value if COOKIE in cookie else "")
            if not hmac.compare_digest(given.encode(), self.token.encode()):
                return "missing or wrong token: open the URL the viewer printed (it ends with ?token=...)"
        if urlsplit(request.path).path == "/ws":
            origin = request.headers.get("Origin")
            if origin is not None and origin not in (f"http://{host}", f"https://{host}"):
                return f"WebSocket from origin {origin!r}, not this page's"
        return None

    def _http(self, connection, request):
        why = self._refusal(request)
        if why is not None:
            log.warning("refused %s from %s: %s", urlsplit(request.path).path, getattr(connection, "remote_address", "?"), why)
            return connection.respond(403, f"forbidden: {why}\n")
        path = urlsplit(request.path).path
        if path == "/ws":
            return None
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        asset = _ASSETS.get(path)
        if asset is None:
            return connection.respond(404, "not found\n")
        body = importlib.resources.files("massview.app.viewer").joinpath("static").joinpath(asset[0]).read_bytes()
        headers = Headers([("Content-Type", asset[1]), ("Content-Length", str(len(body))), ("Cache-Control", "no-store")])
        if self.token is not None and path == "/":  # the assets and the WebSocket then authenticate by cookie
            headers["Set-Cookie"] = f"{COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict"
        return Response(200, "OK", headers, body)

    # -- WebSocket ----------------------------------------------------------------------
    async def _handler(self, ws) -> None:
        client = _Client(ws, "watcher" if self._clients else "pilot")
        self._clients.append(client)
        sender = asyncio.create_task(self._send_loop(client))
        try:
            await ws.send(json.dumps({"type": "hello", "choices": self.state.choices, "settings": self.state.settings,
                                      "role": client.role}))
            async for raw in ws:
                if client.role != "pilot":
                    await ws.send(json.dumps({"type": "error", "message": "watching: another browser steers this viewer "
                                                                          "(the first one connected; it hands over when it closes)"}))
                    continue
                try:
                    self.state.apply(raw)
                except MessageError as e:
                    self.state.rejected += 1
                    log.warning("rejected a message from %s: %s", ws.remote_address, e)
                    await ws.send(json.dumps({"type": "error", "message": str(e)}))
        except Exception as e:  # noqa: BLE001 - one client's failure never stops the server
            log.warning("client %s closed: %s", getattr(ws, "remote_address", "?"), e)
        finally:
            sender.cancel()
            self._clients.remove(client)
            if client.role == "pilot" and self._clients:
                await self._promote(self._clients[0])

    async def _promote(self, client: _Client) -> None:
        client.role = "pilot"
        try:
            await client.ws.send(json.dumps({"type": "role", "role": "pilot"}))
        except Exception:  # noqa: BLE001 - that one is closing too; its handler promotes the next
            pass

    async def _send_loop(self, client: _Client) -> None:
        while True:
            await client.ready.wait()
            client.ready.clear()
            frame, stats = client.frame, client.stats
            try:
                if stats is not None:
                    await client.ws.send(stats)
                if frame is not None:
                    await client.ws.send(frame)
            except Exception:  # noqa: BLE001 - the handler notices the closed connection
                return

    def publish(self, jpeg: bytes, stats: dict) -> None:
        """Hand the newest frame to every client (thread-safe; never blocks the renderer)."""
        if self._loop is None:
            return
        text = json.dumps({"type": "stats", **stats})

        def post():
            for c in list(self._clients):
                c.frame, c.stats = jpeg, text
                c.ready.set()

        self._loop.call_soon_threadsafe(post)

    @property
    def clients(self) -> int:
        return len(self._clients)
