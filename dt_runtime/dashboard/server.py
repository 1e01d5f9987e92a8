"""The dashboard's web server: one page, its static files, a live feed and the operators' actions.

The standard library's `http.server` (a thread per connection) and server-sent events: the
page opens one `EventSource` on /api/events and gets a snapshot, then batches of what is new
(hub.Hub), at most `max_rate_hz` batches a second whatever the daemon's rate (125 Hz telemetry
arrives as a few messages a batch). No framework, no dependency, nothing fetched at run time.

Routes:
    GET  /                      the page (static/index.html)
    GET  /static/<file>         its script and style sheet (a fixed list)
    GET  /api/scene             the twin: robot, calibrated volume, Eq. 17 thresholds, provenance, error map
    GET  /metrology             the metrologist's page (static/metrology.html; with --results)
    GET  /api/results           the results under --results: [{name, kind}]
    GET  /api/result?name=N     one of them, as results.load reads it (N: a name of /api/results)
    GET  /plant                 the plant page (static/plant.html; with --plant): every cell on the fabric
    GET  /api/plant             its rows (plant.PlantWatch.snapshot)
    GET  /api/snapshot          the live state now (JSON)
    GET  /api/events            server-sent events: `snapshot`, then batches (`message`)
    GET  /api/whoami            the operator a token names (401/403 as for an action)
    POST /api/requests/ack      {"uid"}: acknowledge delivery of a request (this dashboard's group's copy)
    POST /api/requests/done     {"uid", "note"}: maintenance done, by the token's operator

Who may do what: viewing needs nothing beyond reaching the page (what the bus shows any
reader). The two actions need `Authorization: Bearer <token>` of an operator of the token file
(operators.py): without one 401, with a wrong one (or on a dashboard started without a token
file) 403, and nothing is published. Requests whose Host is not the address served (DNS
rebinding) and cross-origin posts are refused (403) too. Bodies are at most 4096 bytes of JSON.
"""
from __future__ import annotations

import ipaddress
import logging
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

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
MAX_STREAMS = 16  # pages open at once (each holds a thread)
KEEPALIVE_S = 15.0


def _static(name: str) -> bytes:
    return resources.files("dt_runtime.dashboard").joinpath("static", name).read_bytes()


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class DashboardServer(ThreadingHTTPServer):
    daemon_threads = True  # a page's stream never holds the process up at exit
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], hub: Hub, scene: Scene | None, feed: BusFeed | None,
                 operators: Operators | None, max_rate_hz: float = 50.0, results: Path | None = None,
                 plant: PlantWatch | None = None):
        super().__init__(address, Handler)
        self.plant = plant  # the plant page's source (None: no /plant)
        self.hub, self.scene, self.feed, self.operators = hub, scene, feed, operators
        self.results = results  # the metrologist's directory (None: no /metrology)
        self.min_interval_s = 1.0 / max_rate_hz
        # None: no live cell (the metrologist's page only)
        self.scene_json = dumps(scene.to_dict() | {"metrology": results is not None}).encode() if scene else None
        self.streams = 0
        self.actions: list[dict[str, Any]] = []  # what the operators did (also logged)
        self._lock = threading.Lock()
        self.stopping = threading.Event()
        self.scheme = "http"

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    @property
    def url(self) -> str:
        host = str(self.server_address[0])
        shown = f"[{host}]" if ":" in host else host
        return f"{self.scheme}://{shown}:{self.port}/"

    def allowed_host(self, header: str | None) -> bool:
        """DNS rebinding: on loopback only a loopback name or address reaches the page."""
        if not is_loopback(str(self.server_address[0])):
            return True
        if not header:
            return False
        host = header.rsplit(":", 1)[0] if not header.endswith("]") else header
        return is_loopback(host)

    def stop(self) -> None:
        self.stopping.set()
        self.hub.close()
        self.shutdown()
        self.server_close()


class Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    protocol_version = "HTTP/1.1"
    server_version = "cobot-dt-dashboard"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        log.debug("%s " + format, self.address_string(), *args)

    # --- replies -----------------------------------------------------------------------------
    def _send(self, status: int, body: bytes, ctype: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", "default-src 'self'; style-src 'self'; img-src 'self' data:")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, obj: Any, extra: dict[str, str] | None = None) -> None:
        self._send(status, dumps(obj).encode(), "application/json", extra)

    def _error(self, status: int, why: str, extra: dict[str, str] | None = None) -> None:
        self._json(status, {"error": why}, extra)

    # --- GET ---------------------------------------------------------------------------------
    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        if not self.server.allowed_host(self.headers.get("Host")):
            return self._error(HTTPStatus.FORBIDDEN, "Host not served here")
        path, _, query = self.path.partition("?")
        live = self.server.scene_json is not None
        if path in ("/", "/index.html") and not live:
            home = "/plant" if self.server.plant is not None else "/metrology"
            return self._send(HTTPStatus.FOUND, b"", "text/plain", {"Location": home})
        if path == "/plant" and self.server.plant is not None:
            return self._send(HTTPStatus.OK, _static("plant.html"), STATIC["plant.html"])
        if path == "/api/plant" and self.server.plant is not None:
            return self._json(HTTPStatus.OK, self.server.plant.snapshot())
        if path in ("/", "/index.html"):
            return self._send(HTTPStatus.OK, _static("index.html"), STATIC["index.html"])
        if path == "/metrology" and self.server.results is not None:
            return self._send(HTTPStatus.OK, _static("metrology.html"), STATIC["metrology.html"])
        if path == "/api/results" and self.server.results is not None:
            try:
                found = find_results(self.server.results)
            except ConfigError as exc:  # the directory went away while served
                return self._error(HTTPStatus.NOT_FOUND, str(exc))
            return self._json(HTTPStatus.OK, {"root": str(self.server.results), "live": live,
                                              "results": [{"name": r.name, "kind": r.kind} for r in found]})
        if path == "/api/result" and self.server.results is not None:
            return self._result(parse_qs(query).get("name", [""])[0])
        if path.startswith("/static/") and path[len("/static/"):] in STATIC:
            name = path[len("/static/"):]
            return self._send(HTTPStatus.OK, _static(name), STATIC[name])
        if path == "/favicon.ico":
            return self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
        if path == "/api/scene" and self.server.scene_json is not None:
            return self._send(HTTPStatus.OK, self.server.scene_json, "application/json")
        if path == "/api/snapshot":
            return self._json(HTTPStatus.OK, self._snapshot())
        if path == "/api/events":
            return self._events()
        if path == "/api/whoami":
            who = self._operator()
            if who is not None:
                self._json(HTTPStatus.OK, {"operator": who})
            return None
        return self._error(HTTPStatus.NOT_FOUND, f"no such page: {path}")

    def _result(self, name: str) -> None:
        """One result of the metrologist's directory, named as /api/results lists it (nothing else
        under or beside the directory is read)."""
        assert self.server.results is not None
        try:
            found = {r.name: r for r in find_results(self.server.results)}
        except ConfigError:  # the directory went away while served
            found = {}
        if name not in found:
            return self._error(HTTPStatus.NOT_FOUND, f"no result {name[:200]!r} under {self.server.results}")
        try:
            body = load_result(found[name])
        except (DataError, ModelError, OSError) as exc:
            log.warning("dashboard: result %s not readable: %s", name, exc)
            return self._error(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
        return self._json(HTTPStatus.OK, body)

    def _snapshot(self) -> dict[str, Any]:
        feed = self.server.feed
        return self.server.hub.snapshot() | {
            "read_only": self.server.operators is None,
            "bus": None if feed is None else {"prefix": feed.prefix, "group": feed.group, "dropped": feed.dropped,
                                              "verified": feed.signer is not None},
            "server_t": time.time()}

    def _events(self) -> None:
        srv = self.server
        with srv._lock:
            if srv.streams >= MAX_STREAMS:
                return self._error(HTTPStatus.SERVICE_UNAVAILABLE, f"{MAX_STREAMS} pages are open already")
            srv.streams += 1
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            snap = self._snapshot()
            self._write(b"event: snapshot\ndata: " + dumps(snap).encode() + b"\n\n")
            seq, last_n = snap["seq"], snap["telemetry_n"]
            while not srv.stopping.is_set():
                new_seq, tel, ev = srv.hub.since(seq, KEEPALIVE_S)
                if srv.stopping.is_set():
                    break
                if new_seq == seq:
                    self._write(b": keep-alive\n\n")
                    continue
                skipped = (tel[0][0] - last_n - 1) if tel else 0
                batch = {"seq": new_seq, "telemetry": [m for _, m in tel], "skipped": max(0, skipped),
                         "events": [{"kind": k, "msg": m} for k, m in ev], "server_t": time.time()}
                self._write(b"data: " + dumps(batch).encode() + b"\n\n")
                seq = new_seq
                if tel:
                    last_n = tel[-1][0]
                srv.stopping.wait(srv.min_interval_s)  # at most max_rate_hz batches: the rest waits in the ring
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass  # the page went away
        finally:
            with srv._lock:
                srv.streams -= 1
            self.close_connection = True

    def _write(self, data: bytes) -> None:
        self.wfile.write(data)
        self.wfile.flush()

    # --- who ---------------------------------------------------------------------------------
    def _operator(self) -> str | None:
        """The operator of the request's bearer token; else replies 401/403 and returns None."""
        ops = self.server.operators
        if ops is None:
            self._error(HTTPStatus.FORBIDDEN, "this dashboard is read-only: it was started without --token-file")
            return None
        auth = self.headers.get("Authorization") or ""
        scheme, _, token = auth.partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            self._error(HTTPStatus.UNAUTHORIZED, "an operator's token is needed (Authorization: Bearer <token>)",
                        {"WWW-Authenticate": 'Bearer realm="cobot-dt dashboard"'})
            return None
        who = ops.who(token.strip())
        if who is None:
            log.warning("dashboard: an action with an unknown token from %s refused", self.address_string())
            self._error(HTTPStatus.FORBIDDEN, "this token is no operator's")
            return None
        return who

    # --- POST --------------------------------------------------------------------------------
    def do_POST(self) -> None:  # noqa: N802 - http.server's name
        if not self.server.allowed_host(self.headers.get("Host")):
            return self._error(HTTPStatus.FORBIDDEN, "Host not served here")
        origin = self.headers.get("Origin")
        if origin and origin.split("://", 1)[-1] != self.headers.get("Host"):
            return self._error(HTTPStatus.FORBIDDEN, "cross-origin requests are refused")
        path = self.path.split("?", 1)[0]
        if path not in ("/api/requests/ack", "/api/requests/done"):
            return self._error(HTTPStatus.NOT_FOUND, f"no such action: {path}")
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_BODY:
            self.close_connection = True
            return self._error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if length > MAX_BODY else HTTPStatus.BAD_REQUEST,
                               f"a JSON body of at most {MAX_BODY} bytes")
        raw = self.rfile.read(length)
        who = self._operator()
        if who is None:
            return None
        try:
            body = loads(raw, "request body", max_bytes=MAX_BODY, max_depth=2)
            if not isinstance(body, dict) or not isinstance(body.get("uid"), str):
                raise DataError("request body: an object with the request's 'uid' (text)")
        except DataError as exc:
            return self._error(HTTPStatus.BAD_REQUEST, str(exc))
        action = path.rsplit("/", 1)[1]
        note = body.get("note")
        if action == "done" and (not isinstance(note, str) or not note.strip() or len(note) > MAX_NOTE):
            return self._error(HTTPStatus.BAD_REQUEST, f"a 'note' saying what was done (1 to {MAX_NOTE} characters): "
                                                       "the record says who confirmed what")
        self._act(action, body["uid"], who, note.strip() if isinstance(note, str) else None)

    def _act(self, action: str, uid: str, who: str, note: str | None) -> None:
        srv = self.server
        req = srv.hub.request(uid)
        if req is None or srv.feed is None or srv.feed.signer is None:
            return self._error(HTTPStatus.NOT_FOUND, f"no request with uid {uid[:64]!r} on this dashboard")
        copies: dict[str, Any] = req.get("copies") or {}
        oid = copies.get(srv.feed.group)
        if action == "ack" and oid is None:
            return self._error(HTTPStatus.CONFLICT, f"no copy of this request for group {srv.feed.group!r} "
                                                    f"(copies: {sorted(copies)}): start the dashboard with --group")
        if oid is None:
            oid = next(iter(copies.values()))  # a 'done' names the request by any copy's id and its uid
        try:
            if action == "ack":
                key = srv.feed.ack(int(oid), uid)
                srv.hub.mark_request(uid, acked_by=who, acked_at=time.time())
            else:
                assert note is not None
                key = srv.feed.done(int(oid), uid, who, note)
                srv.hub.mark_request(uid, done_by=who, done_note=note, done_at=time.time())
        except Exception as exc:  # noqa: BLE001 - a bus failure is the page's 502, not a dead thread
            log.error("dashboard: %s of request %s by %s not published: %s", action, uid, who, exc)
            return self._error(HTTPStatus.BAD_GATEWAY, f"not published on the bus: {exc}")
        record = {"action": action, "uid": uid, "id": int(oid), "by": who, "note": note, "key": key, "t": time.time()}
        with srv._lock:
            srv.actions.append(record)
            del srv.actions[:-100]
        log.info("dashboard: operator %s: %s of request %s (%s)%s", who, action, uid, key,
                 f": {note}" if note else "")
        self._json(HTTPStatus.OK, {"published": key, "by": who, "action": action})
