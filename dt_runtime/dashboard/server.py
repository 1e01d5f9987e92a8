"""The dashboard's web server: one page, its static files, a live feed and the operators' actions.

Starlette (a route table, one guard: Host, Origin, the operator's token, body size) served by
uvicorn on asyncio, on a socket bound here, in one thread of its own. The page opens one
`EventSource` on /api/events and gets a snapshot, then batches of what is new (hub.Hub), at most
`max_rate_hz` batches a second. The routes, who may do what, and the limits with what a client
beyond them sees: docs/dashboard.md ("Who may do what", "The web server and its limits")."""
from __future__ import annotations

import asyncio
import functools
import ipaddress
import logging
import resource
import socket
import ssl
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any

import anyio
import uvicorn
from starlette.applications import Starlette
from starlette.datastructures import Headers, MutableHeaders
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import RedirectResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from dt_kernel.errors import ConfigError, DataError, ModelError
from dt_runtime.common.jsonsafe import dumps
from dt_runtime.common.safe_json import loads
from dt_runtime.dashboard.feed import BusFeed
from dt_runtime.dashboard.hub import Hub
from dt_runtime.dashboard.operators import Operators
from dt_runtime.dashboard.plant import PlantWatch
from dt_runtime.dashboard.results import find_results
from dt_runtime.dashboard.results import load as load_result
from dt_runtime.dashboard.scene import Scene

log = logging.getLogger("dt.dashboard")
STATIC = {"index.html": "text/html; charset=utf-8", "app.js": "text/javascript; charset=utf-8",
          "view3d.js": "text/javascript; charset=utf-8", "style.css": "text/css; charset=utf-8",
          "metrology.html": "text/html; charset=utf-8", "metrology.js": "text/javascript; charset=utf-8",
          "plant.html": "text/html; charset=utf-8", "plant.js": "text/javascript; charset=utf-8"}
MAX_BODY = 4096
MAX_NOTE = 500
MAX_STREAMS = 64  # event streams (open pages) at once; one more gets 503 + Retry-After
RETRY_AFTER_S = 10
KEEPALIVE_S = 15.0  # an SSE comment on a quiet stream, so proxies and the page see it alive
LIMIT_CONCURRENCY = 2048  # connections (open or half-open) at once: uvicorn answers 503 beyond
HEAD_TIMEOUT_S = 10.0  # a connection must send a whole request head within this (slow or silent clients)
KEEP_ALIVE_S = 5  # an idle keep-alive connection is closed after this
MAX_HEAD = 8192  # bytes of a request line and headers (h11)
WORKERS = 4  # threads for blocking work (results read from disk, a bus put); asyncio does the rest
TOKEN_ROUTES = {("GET", "/api/whoami"), ("POST", "/api/requests/ack"), ("POST", "/api/requests/done")}
SECURITY_HEADERS = {"cache-control": "no-store", "x-content-type-options": "nosniff",
                    "content-security-policy": "default-src 'self'; style-src 'self'; img-src 'self' data:"}


@functools.cache
def _static(name: str) -> bytes:
    return resources.files("dt_runtime.dashboard").joinpath("static", name).read_bytes()


def is_loopback(host: str) -> bool:
    """True for ``localhost`` or a loopback address (brackets around an IPv6 one allowed).

    Parameters
    ----------
    host : str

    Returns
    -------
    bool
    """
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _json(status: int, obj: Any, headers: dict[str, str] | None = None) -> Response:
    return Response(dumps(obj).encode(), status, headers, media_type="application/json")


def _error(status: int, why: str, headers: dict[str, str] | None = None) -> Response:
    return _json(status, {"error": why}, headers)


class HeadTimeoutProtocol(H11Protocol):
    """uvicorn's h11 protocol, and a deadline for each request head: a connection that sends
    nothing, or half a request line, is closed after HEAD_TIMEOUT_S (uvicorn's own keep-alive
    timer starts only after a first response) instead of holding a slot for ever."""

    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        """Start the head deadline of the connection's first request.

        Parameters
        ----------
        transport : asyncio.Transport
        """
        super().connection_made(transport)
        self._arm_head()

    def on_response_complete(self) -> None:
        """Start the head deadline of the next request."""
        super().on_response_complete()
        self._arm_head()

    def connection_lost(self, exc: Exception | None) -> None:
        """Cancel the head deadline.

        Parameters
        ----------
        exc : Exception or None
        """
        if self._head_timer is not None:
            self._head_timer.cancel()
        super().connection_lost(exc)

    def _arm_head(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        self._head_timer = self.loop.call_later(HEAD_TIMEOUT_S, self._head_late, self.cycle)

    def _head_late(self, cycle: object) -> None:
        # no new request head since the timer was armed (a pipelined one may already be in progress: kept)
        idle = cycle is None or getattr(cycle, "response_complete", True)
        if self.cycle is cycle and idle and not self.transport.is_closing():
            log.debug("dashboard: %s sent no request head within %.0f s: closed", self.client, HEAD_TIMEOUT_S)
            self.transport.close()


#: A client that went away while its reply was written or its body read: Starlette's own
#: (StreamingResponse turns the OSError of a closed connection into it, Request.json on a
#: disconnect) and the socket's. Quietly ended, never uvicorn's "Exception in ASGI application"
#: traceback, of which a page reloaded by many browsers made hundreds.
GONE = (ClientDisconnect, anyio.BrokenResourceError, anyio.ClosedResourceError, OSError)


class Guard:
    """The one gate of every request: Host (DNS rebinding), Origin (cross-origin posts), the body's
    size (read here, at most MAX_BODY bytes, then handed on), the operator's token on the routes
    that act (TOKEN_ROUTES; the operator's name in request.state.operator), and the security
    headers on every reply."""

    def __init__(self, app: ASGIApp, server: DashboardServer):
        self.app, self.server = app, server

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def secured(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for k, v in SECURITY_HEADERS.items():
                    if k not in headers:
                        headers[k] = v
            await send(message)

        refused = await self._refusal(scope, Headers(scope=scope))
        if refused is not None:
            return await refused(scope, receive, secured)
        if scope["method"] == "POST":
            body = await self._body(receive)
            if body is None:
                return await _error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a JSON body of at most {MAX_BODY} bytes")(
                    scope, receive, secured)
            receive = _replay(body, receive)
        try:
            await self.app(scope, receive, secured)
        except GONE as exc:
            log.debug("dashboard: %s %s: the client went away (%s)", scope["method"], scope["path"],
                      type(exc).__name__)

    async def _refusal(self, scope: Scope, headers: Headers) -> Response | None:
        srv = self.server
        if not srv.allowed_host(headers.get("host")):
            return _error(HTTPStatus.FORBIDDEN, "Host not served here")
        method, path = scope["method"], scope["path"]
        if method == "POST":
            origin = headers.get("origin")
            if origin and origin.split("://", 1)[-1] != headers.get("host"):
                return _error(HTTPStatus.FORBIDDEN, "cross-origin requests are refused")
            try:
                length = int(headers.get("content-length") or 0)
            except ValueError:
                length = -1
            if not 0 <= length <= MAX_BODY:
                return _error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if length > MAX_BODY else HTTPStatus.BAD_REQUEST,
                              f"a JSON body of at most {MAX_BODY} bytes", {"connection": "close"})
        if (method, path) in TOKEN_ROUTES:
            who = srv.operator(headers.get("authorization") or "", scope.get("client"))
            if isinstance(who, Response):
                return who
            scope.setdefault("state", {})["operator"] = who
        return None

    @staticmethod
    async def _body(receive: Receive) -> bytes | None:
        """The whole body (however sent: a Content-Length or chunks), None beyond MAX_BODY."""
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > MAX_BODY:
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    sent = False

    async def again() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()
    return again


@dataclass(frozen=True)
class _Frame:
    """One batch as sent to every page whose stream stood at `prev`."""
    prev: int
    seq: int
    last_n: int
    data: bytes


class _EventStream(StreamingResponse):
    """A page's stream; its slot is given back however it ends (the page gone, the server stopping)."""

    def __init__(self, content: AsyncIterator[bytes], release: Callable[[], None]):
        super().__init__(content, media_type="text/event-stream", headers={"cache-control": "no-store"})
        self._release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        except GONE:  # the page went away while written to
            log.debug("dashboard: a page's stream closed by its client")
        finally:
            self._release()


class DashboardServer:
    """The pages and the live feed over Starlette + uvicorn, on `address` (bound at once: a port
    in use fails here). `start()` serves from a thread of its own; `stop()` ends the streams and
    the server. `tls`: (certificate chain, key) PEM files, or (None, None) for plain HTTP."""

    def __init__(self, address: tuple[str, int], hub: Hub, scene: Scene | None, feed: BusFeed | None,
                 operators: Operators | None, max_rate_hz: float = 50.0, results: Path | None = None,
                 plant: PlantWatch | None = None, *, tls: tuple[str | None, str | None] = (None, None),
                 max_streams: int = MAX_STREAMS):
        self.plant = plant  # the plant page's source (None: no /plant)
        self.hub, self.scene, self.feed, self.operators = hub, scene, feed, operators
        self.results = results  # the metrologist's directory (None: no /metrology)
        self.min_interval_s = 1.0 / max_rate_hz
        self.max_streams = max_streams
        # None: no live cell (the metrologist's page only)
        self.scene_json = dumps(scene.to_dict() | {"metrology": results is not None}).encode() if scene else None
        self.streams = 0  # touched by the event loop's thread only
        self.refused_streams = 0
        self.actions: list[dict[str, Any]] = []  # what the operators did (also logged)
        self._lock = threading.Lock()
        self.stopping = threading.Event()
        self._frame = _Frame(-1, -1, 0, b"")
        self._ticked: asyncio.Event | None = None
        self._ticker: asyncio.Task[None] | None = None
        self._limiter: anyio.CapacityLimiter | None = None
        self.app = Starlette(routes=self._routes(), middleware=[Middleware(Guard, server=self)],
                             exception_handlers={404: self._not_found, 405: self._not_found})
        self.address = address
        self.socket = _bind(address)
        cert, key = tls
        try:
            self.config = uvicorn.Config(
                self.app, http=HeadTimeoutProtocol, loop="asyncio", lifespan="off", log_config=None,
                log_level="warning", access_log=False, server_header=False, proxy_headers=False,
                limit_concurrency=LIMIT_CONCURRENCY, timeout_keep_alive=KEEP_ALIVE_S, timeout_graceful_shutdown=3,
                h11_max_incomplete_event_size=MAX_HEAD, ssl_certfile=cert, ssl_keyfile=key)
            try:
                self.config.load()  # the certificate and key read now: a bad one is the command line's error
            except (OSError, ssl.SSLError) as exc:
                raise ConfigError(str(cert), "--tls-cert/--tls-key", str(exc), "a PEM certificate chain and "
                                  "its private key") from exc
            if self.config.ssl is not None:
                self.config.ssl.minimum_version = ssl.TLSVersion.TLSv1_2
        except BaseException:
            self.socket.close()
            raise
        self.scheme = "https" if cert is not None else "http"
        self._uvicorn = uvicorn.Server(self.config)
        self._thread: threading.Thread | None = None

    # --- life --------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The port bound."""
        return int(self.socket.getsockname()[1])

    @property
    def url(self) -> str:
        """The page's URL (``http://`` or ``https://``)."""
        host = str(self.address[0])
        shown = f"[{host}]" if ":" in host else host
        return f"{self.scheme}://{shown}:{self.port}/"

    def start(self) -> None:
        """Serve on the bound socket in a thread (raising the open-files limit first when allowed)."""
        _enough_files(LIMIT_CONCURRENCY + 256)
        self._thread = threading.Thread(target=self._uvicorn.run, kwargs={"sockets": [self.socket]},
                                        name="dashboard-http", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the streams at their next tick, stop uvicorn and close the socket."""
        self.stopping.set()  # the streams end at their next tick, then uvicorn's shutdown finds them done
        self.hub.close()
        self._uvicorn.should_exit = True
        if self._thread is not None:
            self._thread.join(10.0)
        self.socket.close()

    def allowed_host(self, header: str | None) -> bool:
        """DNS rebinding: on loopback only a loopback name or address reaches the page.

        Parameters
        ----------
        header : str or None
            The request's Host header.

        Returns
        -------
        bool
        """
        if not is_loopback(str(self.address[0])):
            return True
        if not header:
            return False
        host = header.rsplit(":", 1)[0] if not header.endswith("]") else header
        return is_loopback(host)

    # --- routes ------------------------------------------------------------------------------
    def _routes(self) -> list[Route]:
        routes = [Route("/", self._home), Route("/index.html", self._home),
                  Route("/static/{name}", self._static_file), Route("/favicon.ico", self._favicon),
                  Route("/api/snapshot", self._snapshot_route), Route("/api/events", self._events),
                  Route("/api/whoami", self._whoami),
                  Route("/api/requests/ack", self._action, methods=["POST"]),
                  Route("/api/requests/done", self._action, methods=["POST"])]
        if self.plant is not None:
            routes += [Route("/plant", self._page("plant.html")), Route("/api/plant", self._plant)]
        if self.results is not None:
            routes += [Route("/metrology", self._page("metrology.html")), Route("/api/results", self._results),
                       Route("/api/result", self._result)]
        if self.scene_json is not None:
            routes.append(Route("/api/scene", self._scene))
        return routes

    async def _not_found(self, request: Request, exc: Exception) -> Response:
        what = "action" if request.method == "POST" else "page"
        return _error(HTTPStatus.NOT_FOUND, f"no such {what}: {request.url.path}")

    def _page(self, name: str) -> Callable[[Request], Awaitable[Response]]:
        async def page(request: Request) -> Response:
            return Response(_static(name), media_type=STATIC[name])
        return page

    async def _home(self, request: Request) -> Response:
        if self.scene_json is None:
            return RedirectResponse("/plant" if self.plant is not None else "/metrology", HTTPStatus.FOUND)
        return Response(_static("index.html"), media_type=STATIC["index.html"])

    async def _static_file(self, request: Request) -> Response:
        name = request.path_params["name"]
        if name not in STATIC:
            raise HTTPException(HTTPStatus.NOT_FOUND)
        return Response(_static(name), media_type=STATIC[name])

    async def _favicon(self, request: Request) -> Response:
        return Response(b"", HTTPStatus.NO_CONTENT, media_type="image/x-icon")

    async def _scene(self, request: Request) -> Response:
        assert self.scene_json is not None
        return Response(self.scene_json, media_type="application/json")

    async def _plant(self, request: Request) -> Response:
        assert self.plant is not None
        return _json(HTTPStatus.OK, self.plant.snapshot())

    async def _results(self, request: Request) -> Response:
        root = self.results
        assert root is not None
        try:
            found = await self._blocking(find_results, root)
        except ConfigError as exc:  # the directory went away while served
            return _error(HTTPStatus.NOT_FOUND, str(exc))
        return _json(HTTPStatus.OK, {"root": str(root), "live": self.scene_json is not None,
                                     "results": [{"name": r.name, "kind": r.kind} for r in found]})

    async def _result(self, request: Request) -> Response:
        """One result of the metrologist's directory, named as /api/results lists it (nothing else
        under or beside the directory is read)."""
        root = self.results
        assert root is not None
        name = request.query_params.get("name", "")
        try:
            found = {r.name: r for r in await self._blocking(find_results, root)}
        except ConfigError:  # the directory went away while served
            found = {}
        if name not in found:
            return _error(HTTPStatus.NOT_FOUND, f"no result {name[:200]!r} under {root}")
        try:
            body = await self._blocking(load_result, found[name])
        except (DataError, ModelError, OSError) as exc:
            log.warning("dashboard: result %s not readable: %s", name, exc)
            return _error(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
        return _json(HTTPStatus.OK, body)

    def _snapshot(self) -> dict[str, Any]:
        feed = self.feed
        return self.hub.snapshot() | {
            "read_only": self.operators is None,
            "bus": None if feed is None else {"prefix": feed.prefix, "group": feed.group, "dropped": feed.dropped,
                                              "verified": feed.signer is not None},
            "server_t": time.time()}

    async def _snapshot_route(self, request: Request) -> Response:
        return _json(HTTPStatus.OK, self._snapshot())

    async def _whoami(self, request: Request) -> Response:
        return _json(HTTPStatus.OK, {"operator": request.state.operator})

    async def _blocking(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Blocking work (disk, the bus) in a few threads of its own, never more than WORKERS."""
        if self._limiter is None:
            self._limiter = anyio.CapacityLimiter(WORKERS)
        return await anyio.to_thread.run_sync(fn, *args, limiter=self._limiter)

    # --- the live feed -----------------------------------------------------------------------
    async def _events(self, request: Request) -> Response:
        if self.streams >= self.max_streams or self.stopping.is_set():
            self.refused_streams += 1
            return _error(HTTPStatus.SERVICE_UNAVAILABLE, f"{self.max_streams} pages are open already",
                          {"retry-after": str(RETRY_AFTER_S)})
        self.streams += 1
        if self._ticker is None:
            self._ticked = asyncio.Event()
            self._ticker = asyncio.get_running_loop().create_task(self._tick(), name="dashboard-ticker")
        snap = self._snapshot()

        def release() -> None:
            self.streams -= 1
        return _EventStream(self._stream(snap), release)

    async def _stream(self, snap: dict[str, Any]) -> AsyncIterator[bytes]:
        yield b"event: snapshot\ndata: " + dumps(snap).encode() + b"\n\n"
        seq, last_n = snap["seq"], snap["telemetry_n"]
        quiet_since = time.monotonic()
        while not self.stopping.is_set():
            frame = self._frame
            if frame.seq > seq:
                if frame.prev == seq:  # in step with the ticker: its batch, encoded once for every page
                    data, seq, last_n = frame.data, frame.seq, frame.last_n
                else:  # behind (a slow page) or new: its own batch from the ring
                    new_seq, tel, ev = self.hub.since(seq, 0.0)
                    data, last_n = self._batch(new_seq, tel, ev, last_n)
                    seq = new_seq
                yield data
                quiet_since = time.monotonic()
            elif time.monotonic() - quiet_since >= KEEPALIVE_S:
                yield b": keep-alive\n\n"
                quiet_since = time.monotonic()
            ticked = self._ticked
            assert ticked is not None
            try:
                await asyncio.wait_for(ticked.wait(), KEEPALIVE_S)
            except TimeoutError:
                pass

    async def _tick(self) -> None:
        """Polls the thread-fed hub at the pages' rate; what is new becomes one encoded batch."""
        snap = self.hub.snapshot()
        seq, last_n = snap["seq"], snap["telemetry_n"]
        self._frame = _Frame(seq, seq, last_n, b"")
        while not self.stopping.is_set():
            await asyncio.sleep(self.min_interval_s)
            if self.hub.seq == seq and not self.stopping.is_set():
                continue
            if self.streams:
                new_seq, tel, ev = self.hub.since(seq, 0.0)
                data, n = self._batch(new_seq, tel, ev, last_n)
                self._frame = _Frame(seq, new_seq, n, data)
                seq, last_n = new_seq, n
            ticked, self._ticked = self._ticked, asyncio.Event()
            assert ticked is not None
            ticked.set()

    @staticmethod
    def _batch(seq: int, tel: list[tuple[int, dict[str, Any]]], ev: list[tuple[str, dict[str, Any]]],
               last_n: int) -> tuple[bytes, int]:
        skipped = (tel[0][0] - last_n - 1) if tel else 0
        batch = {"seq": seq, "telemetry": [m for _, m in tel], "skipped": max(0, skipped),
                 "events": [{"kind": k, "msg": m} for k, m in ev], "server_t": time.time()}
        return b"data: " + dumps(batch).encode() + b"\n\n", tel[-1][0] if tel else last_n

    # --- who ---------------------------------------------------------------------------------
    def operator(self, authorization: str, client: tuple[str, int] | None = None) -> str | Response:
        """The operator of a bearer token; else the 401/403 reply.

        Parameters
        ----------
        authorization : str
            The Authorization header.
        client : tuple or None
            (address, port) of the client, for the log.

        Returns
        -------
        str or Response
            The operator's name, or 403 (read-only dashboard, unknown token) or 401 (no bearer token).
        """
        ops = self.operators
        if ops is None:
            return _error(HTTPStatus.FORBIDDEN, "this dashboard is read-only: it was started without --token-file")
        scheme, _, token = authorization.partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            return _error(HTTPStatus.UNAUTHORIZED, "an operator's token is needed (Authorization: Bearer <token>)",
                          {"www-authenticate": 'Bearer realm="cobot-dt dashboard"'})
        who = ops.who(token.strip())
        if who is None:
            log.warning("dashboard: an action with an unknown token from %s refused", client[0] if client else "?")
            return _error(HTTPStatus.FORBIDDEN, "this token is no operator's")
        return who

    # --- actions -----------------------------------------------------------------------------
    async def _action(self, request: Request) -> Response:
        who: str = request.state.operator
        try:
            body = loads(await request.body(), "request body", max_bytes=MAX_BODY, max_depth=2)
            if not isinstance(body, dict) or not isinstance(body.get("uid"), str):
                raise DataError("request body: an object with the request's 'uid' (text)")
        except DataError as exc:
            return _error(HTTPStatus.BAD_REQUEST, str(exc))
        action = request.url.path.rsplit("/", 1)[1]
        note = body.get("note")
        if action == "done" and (not isinstance(note, str) or not note.strip() or len(note) > MAX_NOTE):
            return _error(HTTPStatus.BAD_REQUEST, f"a 'note' saying what was done (1 to {MAX_NOTE} characters): "
                                                  "the record says who confirmed what")
        return await self._act(action, body["uid"], who, note.strip() if isinstance(note, str) else None)

    async def _act(self, action: str, uid: str, who: str, note: str | None) -> Response:
        req = self.hub.request(uid)
        feed = self.feed
        if req is None or feed is None or feed.signer is None:
            return _error(HTTPStatus.NOT_FOUND, f"no request with uid {uid[:64]!r} on this dashboard")
        copies: dict[str, Any] = req.get("copies") or {}
        oid = copies.get(feed.group)
        if action == "ack" and oid is None:
            return _error(HTTPStatus.CONFLICT, f"no copy of this request for group {feed.group!r} "
                                               f"(copies: {sorted(copies)}): start the dashboard with --group")
        if oid is None:
            oid = next(iter(copies.values()))  # a 'done' names the request by any copy's id and its uid

        def publish() -> str:
            if action == "ack":
                key = feed.ack(int(oid), uid)
                self.hub.mark_request(uid, acked_by=who, acked_at=time.time())
            else:
                assert note is not None
                key = feed.done(int(oid), uid, who, note)
                self.hub.mark_request(uid, done_by=who, done_note=note, done_at=time.time())
            return key
        try:
            key = await self._blocking(publish)
        except Exception as exc:  # noqa: BLE001 - a bus failure is the page's 502, not a dead server
            log.error("dashboard: %s of request %s by %s not published: %s", action, uid, who, exc)
            return _error(HTTPStatus.BAD_GATEWAY, f"not published on the bus: {exc}")
        record = {"action": action, "uid": uid, "id": int(oid), "by": who, "note": note, "key": key, "t": time.time()}
        with self._lock:
            self.actions.append(record)
            del self.actions[:-100]
        log.info("dashboard: operator %s: %s of request %s (%s)%s", who, action, uid, key,
                 f": {note}" if note else "")
        return _json(HTTPStatus.OK, {"published": key, "by": who, "action": action})


def _bind(address: tuple[str, int]) -> socket.socket:
    """The listening socket, bound now (port 0: any free one, read back by `port`)."""
    host, port = address
    family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host.strip("[]"), port))
        sock.listen(1024)
        sock.set_inheritable(True)
    except BaseException:
        sock.close()
        raise
    return sock


def _enough_files(n: int) -> None:
    """Raise the soft limit of open files to `n` (within the hard one): each connection is one."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = n if hard == resource.RLIM_INFINITY else min(n, hard)
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
