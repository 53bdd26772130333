"""The live page's web server: a Starlette app on uvicorn, in one thread with its own event loop.

Routes: ``/`` (the page), ``/static/...`` (its script, style and the vendored three.js / uPlot
bundle), ``/api/state``, ``/api/geometry`` and ``/api/events`` (Server-Sent Events). The access
policies are the middleware of :mod:`softphantom.viz.live.security`.

Every browser gets the same frames: :class:`FrameHub` builds one frame per view tick (the
estimates since the last tick, the surface when it changed, the status), encodes it once and
queues it to each open event stream. A browser that falls behind by more than its queue
(``CLIENT_QUEUE`` frames) loses the oldest (their estimates counted in ``view_dropped``); one that
accepts nothing for ``client_timeout_s`` is dropped, freeing its slot. Nothing here waits on the
estimate pump: it reads :class:`~softphantom.viz.live.state.LiveState` under its short lock. When
the server stops, each stream gets a last frame (the final status) and an ``end`` event, after
which the page stops reconnecting and shows the session ended.

This module serves any :class:`PageSession` (the live session,
:class:`~softphantom.viz.live.server.LiveSession`, is one); it does not import the session's module.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import threading
from pathlib import Path
from typing import Any, Protocol

import h11
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.responses import JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from uvicorn import Config, Server
from uvicorn.protocols.http.h11_impl import H11Protocol

from softphantom.errors import UserError
from softphantom.viz.live.security import (
    HostCheck, LoopbackOnly, MaxClients, PageHeaders, TokenCheck, host_names, is_loopback,
)
from softphantom.viz.live.state import LiveConfig, LiveState

STATIC_DIR = Path(__file__).with_name("static")

CLIENT_QUEUE = 64
"""Frames queued per browser (about 2 s at the default view rate)."""
STATUS_PERIOD_S = 1.0
"""A frame at least this often, new estimates or not: the page's status (stalled, ended) stays fresh."""


END_EVENT = b"event: end\ndata: {}\n\n"
"""The last event of a stream: the session has ended (the page stops reconnecting)."""


class PageSession(Protocol):
    """What the page's server reads from a session."""

    state: LiveState
    config: LiveConfig
    geometry_json: dict[str, Any] | None

    def state_json(self) -> dict[str, Any]: ...


def _sse(frame_json: bytes) -> bytes:
    return b"event: frame\ndata: " + frame_json + b"\n\n"


class FrameHub:
    """One frame per view tick for every open event stream (see the module docstring)."""

    def __init__(self, session: PageSession):
        self.state, self.period_s = session.state, 1.0 / session.config.view_rate_Hz
        self.clients: dict[asyncio.Queue, None] = {}
        self.seq, self.sv = -1, 0
        self.closed = False

    def subscribe(self) -> asyncio.Queue:
        """A queue for a new browser, holding its first frame: the history and the surface."""
        frame, _, seq, sv = self.state.frame_json_since(-1, 0)
        if not self.clients:  # the broadcast resumes where this client's history ends
            self.seq, self.sv = seq, sv
        q: asyncio.Queue = asyncio.Queue(CLIENT_QUEUE)
        q.put_nowait((_sse(frame), 0))
        self.clients[q] = None
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self.clients.pop(q, None)

    def close(self) -> None:
        """End every event stream (the session stops): a last frame with the final status (ended),
        the ``end`` event, then the end of the response."""
        self.closed = True
        if not self.clients:
            return
        frame, n, self.seq, self.sv = self.state.frame_json_since(self.seq, self.sv)
        last = _sse(frame) + END_EVENT
        for q in self.clients:
            while q.qsize() > CLIENT_QUEUE - 2:  # room for the last frame and the end
                _, lost = q.get_nowait()
                self.state.add_view_dropped(lost)
            q.put_nowait((last, n))
            q.put_nowait(None)

    def tick(self) -> None:
        """Build this tick's frame once and queue it to every client."""
        st = self.state
        frame, n, self.seq, self.sv = st.frame_json_since(self.seq, self.sv)
        data = _sse(frame)
        for q in self.clients:
            if q.full():  # this browser is behind: it loses its oldest frame
                _, lost = q.get_nowait()
                st.add_view_dropped(lost)
            q.put_nowait((data, n))

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = last_sent = loop.time()
        while not self.closed:
            next_t += self.period_s
            now = loop.time()
            if next_t < now - self.period_s:  # the loop was held up: do not burst to catch up
                next_t = now
            await asyncio.sleep(max(0.0, next_t - now))
            if not self.clients or self.closed:
                continue
            if not self.state.changed_since(self.seq, self.sv) and loop.time() - last_sent < STATUS_PERIOD_S:
                continue
            self.tick()
            last_sent = loop.time()


class EventStream:
    """``/api/events``: a browser's Server-Sent Events stream from the hub."""

    def __init__(self, hub: FrameHub, timeout_s: float):
        self.hub, self.timeout_s = hub, timeout_s

    async def __call__(self, scope, receive, send) -> None:
        q = self.hub.subscribe()

        async def disconnect() -> None:
            while (await receive())["type"] != "http.disconnect":
                pass

        gone = asyncio.ensure_future(disconnect())
        try:
            await send({"type": "http.response.start", "status": 200,
                        "headers": [(b"content-type", b"text/event-stream"), (b"cache-control", b"no-store")]})
            while True:
                get = asyncio.ensure_future(q.get())
                await asyncio.wait({get, gone}, return_when=asyncio.FIRST_COMPLETED)
                if not get.done():  # the browser went away
                    get.cancel()
                    return
                item = get.result()
                if item is None:
                    await send({"type": "http.response.body", "body": b"", "more_body": False})
                    return
                # a browser that accepts nothing for timeout_s (stalled, not closed) is dropped
                await asyncio.wait_for(send({"type": "http.response.body", "body": item[0], "more_body": True}),
                                       self.timeout_s)
        except (asyncio.TimeoutError, OSError):
            return
        finally:
            gone.cancel()
            self.hub.unsubscribe(q)


def build_app(session: PageSession, hub: FrameHub) -> Starlette:
    """The page's ASGI app with the session's access policies."""

    cfg = session.config
    geometry = None if session.geometry_json is None else json.dumps(session.geometry_json).encode()

    async def page(request) -> Response:
        return Response((STATIC_DIR / "index.html").read_bytes(), media_type="text/html; charset=utf-8",
                        headers={"cache-control": "no-store"})

    async def state(request) -> Response:
        return JSONResponse(session.state_json(), headers={"cache-control": "no-store"})

    async def geometry_route(request) -> Response:
        if geometry is None:
            return Response(b"this source has no geometry\n", 404, media_type="text/plain")
        return Response(geometry, media_type="application/json")

    async def not_found(request, exc) -> None:
        return Response(b"not found\n", 404, media_type="text/plain; charset=utf-8")

    loopback = is_loopback(cfg.listen_host)
    middleware = [Middleware(PageHeaders), Middleware(MaxClients, limit=cfg.max_clients)]
    if loopback:
        middleware.append(Middleware(LoopbackOnly))
    middleware.append(Middleware(HostCheck, names=host_names(cfg.listen_host, cfg.allowed_hosts), loopback_only=loopback))
    if cfg.token:
        middleware.append(Middleware(TokenCheck, token=cfg.token))
    routes = [Route("/", page), Route("/api/state", state), Route("/api/geometry", geometry_route),
              Route("/api/events", EventStream(hub, cfg.client_timeout_s)),
              Mount("/static", StaticFiles(directory=STATIC_DIR), name="static")]
    return Starlette(routes=routes, middleware=middleware, exception_handlers={404: not_found})


def _protocol(timeout_s: float) -> type[H11Protocol]:
    class Protocol(H11Protocol):
        """uvicorn's HTTP/1.1, plus: a connection that has not sent a whole request within
        ``timeout_s`` of opening is closed (uvicorn times out only idle keep-alive connections)."""

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self.loop.call_later(timeout_s, self._drop_if_idle)

        def _drop_if_idle(self) -> None:
            if self.conn.their_state is h11.IDLE and self.conn.our_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

    return Protocol


class _Quiet(logging.Filter):
    """Dropping a stalled browser leaves its response unfinished on purpose (and, at the stop, its
    task is cancelled after the grace period)."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        return "without completing response" not in msg and "timeout graceful shutdown" not in msg


class WebServer:
    """The app served by uvicorn in a thread; :meth:`stop` ends the event streams and the server."""

    def __init__(self, session: PageSession):
        cfg = session.config
        family = socket.AF_INET6 if ":" in cfg.listen_host else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((cfg.listen_host, cfg.http_port))
            self._sock.listen(128)
        except OSError as exc:
            self._sock.close()
            raise UserError(f"cannot serve the live page on {cfg.listen_host}:{cfg.http_port}: {exc.strerror}") from None
        self.address = self._sock.getsockname()[:2]
        self.hub = FrameHub(session)
        logging.getLogger("uvicorn.error").addFilter(_Quiet())
        self.app = build_app(session, self.hub)
        config = Config(self.app, http=_protocol(cfg.client_timeout_s), ws="none",
                        lifespan="off", loop="asyncio", server_header=False, log_config=None, log_level="error", access_log=False,
                        timeout_keep_alive=max(1, int(cfg.client_timeout_s)), timeout_graceful_shutdown=2)
        self._server = Server(config)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-http", daemon=True)
        self._thread.start()
        if not self._ready.wait(30.0):
            raise UserError("the live page's server did not start within 30 s")

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            hub = asyncio.ensure_future(self.hub.run())
            self._ready.set()
            try:
                await self._server.serve(sockets=[self._sock])
            finally:
                hub.cancel()

        try:
            asyncio.run(main())
        finally:
            self._ready.set()

    def stop(self) -> None:
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self.hub.close)
        self._server.should_exit = True
        self._thread.join(10.0)
        self._sock.close()
