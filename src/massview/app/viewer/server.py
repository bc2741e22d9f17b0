"""HTTP + WebSocket server of the viewer (runs on the destination rank, in its own thread).

``GET /`` serves the page, ``/viewer.js`` and ``/viewer.css`` its assets (shipped in the
package, no build step), ``/ws`` upgrades to a WebSocket that carries:

* server → browser: a ``hello`` JSON (choices and current settings), then per frame a JPEG
  (binary) and a ``stats`` JSON; each client gets the latest frame only, so a slow client
  drops frames instead of slowing the ranks;
* browser → server: ``input`` and ``settings`` messages (:mod:`state`); anything malformed is
  rejected, logged and answered with an ``error`` message, and the stream goes on. Messages
  over 64 KiB close that client's connection (the page reconnects); the job keeps running.
"""

from __future__ import annotations

import asyncio
import importlib.resources
import json
import logging
import threading

from .state import MAX_MESSAGE, MessageError, ViewerState

__all__ = ["ViewerServer"]

log = logging.getLogger("massview.viewer")

_ASSETS = {"/": ("index.html", "text/html; charset=utf-8"), "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
           "/viewer.css": ("viewer.css", "text/css; charset=utf-8")}


class _Client:
    def __init__(self, ws):
        self.ws = ws
        self.frame: bytes | None = None
        self.stats: str | None = None
        self.ready = asyncio.Event()


class ViewerServer:
    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080):
        self.state, self.host, self.port = state, host, port
        self._clients: set[_Client] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="massview-viewer", daemon=True)

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()
        self._started.wait(30)
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

    # -- HTTP ---------------------------------------------------------------------------
    def _http(self, connection, request):
        path = request.path.split("?")[0]
        if path == "/ws":
            return None
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        asset = _ASSETS.get(path)
        if asset is None:
            return connection.respond(404, "not found\n")
        body = importlib.resources.files("massview.app.viewer").joinpath("static").joinpath(asset[0]).read_bytes()
        headers = Headers([("Content-Type", asset[1]), ("Content-Length", str(len(body))), ("Cache-Control", "no-store")])
        return Response(200, "OK", headers, body)

    # -- WebSocket ----------------------------------------------------------------------
    async def _handler(self, ws) -> None:
        client = _Client(ws)
        self._clients.add(client)
        sender = asyncio.create_task(self._send_loop(client))
        try:
            await ws.send(json.dumps({"type": "hello", "choices": self.state.choices, "settings": self.state.settings}))
            async for raw in ws:
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
            self._clients.discard(client)

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
            for c in self._clients:
                c.frame, c.stats = jpeg, text
                c.ready.set()

        self._loop.call_soon_threadsafe(post)

    @property
    def clients(self) -> int:
        return len(self._clients)
