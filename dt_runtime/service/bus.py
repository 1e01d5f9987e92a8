"""Zenoh bus of the twin daemon: telemetry, corrections, state and durable maintenance requests.

Key expressions (payloads are UTF-8 JSON objects, encoding application/json)::

    dt/<cell>/<robot>/telemetry                  best effort, CongestionControl.DROP, DATA_LOW
    dt/<cell>/<robot>/correction                 RELIABLE, BLOCK, DATA_HIGH
    dt/<cell>/<robot>/state                      RELIABLE, BLOCK, INTERACTIVE_HIGH
    dt/<cell>/<robot>/maintenance/request        RELIABLE, BLOCK, INTERACTIVE_HIGH
    dt/<cell>/<robot>/maintenance/ack/<id>       RELIABLE, BLOCK, INTERACTIVE_HIGH (consumer ->)

Delivery of maintenance requests (at least once, end to end):
1. `request_maintenance(payload)` writes the request to the Store outbox and commits it
   (fsync) BEFORE anything is published; a failing store raises StoreError and nothing is sent.
2. A worker thread publishes every pending outbox entry at once and then every
   `republish_period_s` until an ack arrives; a new Bus on the same Store (daemon restart)
   republishes whatever is still pending.
3. The consumer acks every copy it receives by publishing on `.../maintenance/ack/<id>` with
   `{"id", "uid"}`; the Bus marks the outbox row acked only if the uid matches (ids restart if
   a store file is replaced; the uuid makes the pair unambiguous). Consumers de-duplicate on
   (cell, robot, uid).
Why a pub/sub ack and not a queryable/get: the request must survive the consumer being absent
for hours; with pub/sub the publisher never waits on a reply (no get timeouts in the loop), acks
and republishes are both idempotent, and a lost ack is repaired by the next republish.

Threads: zenoh callbacks only enqueue (never block, never touch SQLite). One worker thread
publishes reliable messages (so a BLOCK put never stalls the caller's control loop), handles
acks and republishes. Telemetry is put directly with DROP: it never blocks. The queue of
reliable messages is bounded (`send_queue`); when full, corrections/state are dropped and
counted in `dropped` (maintenance requests are never lost: they live in the outbox).
`close()` stops the worker and closes the session in a helper thread joined with a time-out.

Config (`BusConfig`, configs/bus.yaml) maps onto the zenoh JSON5 config as:
    mode                  -> mode ("peer" | "client")
    listen, connect       -> listen/endpoints, connect/endpoints
    multicast_scouting    -> scouting/multicast/enabled (default false: loopback tests stay local)
    gossip_scouting       -> scouting/gossip/enabled
    tls.root_ca_certificate, listen_certificate, listen_private_key, connect_certificate,
    connect_private_key, enable_mtls, verify_name_on_connect
                          -> transport/link/tls/<same name>   (endpoints must use tls/ or quic/)
    access_control.enabled, default_permission, rules[], subjects[], policies[]
                          -> access_control/<same name> (zenoh 1.x ACL schema: rules have id,
                             messages, flows, permission, key_exprs; subjects id plus
                             interfaces / cert_common_names / usernames / zids; policies
                             reference rule and subject ids, checked here)
    extra                 -> any further zenoh key path -> JSON value (escape hatch)
configs/bus_tls_acl_example.yaml shows TLS + ACL.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Literal, Mapping

import zenoh
from pydantic import Field, field_validator, model_validator

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import DriverError, StateError
from dt_runtime.service.store import Store, StoreError

log = logging.getLogger(__name__)

KINDS = ("telemetry", "correction", "state", "maintenance/request")
ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")


def _keyexpr_ok(k: str) -> str:
    try:
        zenoh.KeyExpr(k)
    except Exception as exc:  # zenoh raises ZError on invalid key expressions
        raise ValueError(f"invalid zenoh key expression {k!r}: {exc}") from exc
    return k


def _check_endpoint(e: str) -> str:
    proto, sep, rest = e.partition("/")
    if not sep or not rest or proto not in ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream"):
        raise ValueError(f"endpoint {e!r} must look like tcp/127.0.0.1:7447 "
                         "(protocols tcp, udp, tls, quic, ws, unixsock-stream)")
    return e


class TlsConfig(Frozen):
    root_ca_certificate: str
    listen_certificate: str | None = None
    listen_private_key: str | None = None
    connect_certificate: str | None = None
    connect_private_key: str | None = None
    enable_mtls: bool = False
    verify_name_on_connect: bool = True

    @model_validator(mode="after")
    def _pairs(self) -> "TlsConfig":
        for side in ("listen", "connect"):
            cert, key = getattr(self, f"{side}_certificate"), getattr(self, f"{side}_private_key")
            if (cert is None) != (key is None):
                raise ValueError(f"{side}_certificate and {side}_private_key go together")
        if self.enable_mtls and self.connect_certificate is None:
            raise ValueError("enable_mtls needs connect_certificate/connect_private_key")
        return self


class AclRule(Frozen):
    id: str
    messages: list[Literal[ACL_MESSAGES]]  # type: ignore[valid-type]
    flows: list[Literal["ingress", "egress"]] = ["ingress", "egress"]
    permission: Literal["allow", "deny"]
    key_exprs: list[str]

    @field_validator("key_exprs")
    @classmethod
    def _k(cls, v: list[str]) -> list[str]:
        return [_keyexpr_ok(k) for k in v]


class AclSubject(Frozen):
    id: str
    interfaces: list[str] | None = None
    cert_common_names: list[str] | None = None
    usernames: list[str] | None = None
    zids: list[str] | None = None


class AclPolicy(Frozen):
    id: str | None = None
    rules: list[str]
    subjects: list[str]


class AccessControlConfig(Frozen):
    enabled: bool = True
    default_permission: Literal["allow", "deny"] = "deny"
    rules: list[AclRule] = []
    subjects: list[AclSubject] = []
    policies: list[AclPolicy] = []

    @model_validator(mode="after")
    def _refs(self) -> "AccessControlConfig":
        rules, subjects = {r.id for r in self.rules}, {s.id for s in self.subjects}
        for p in self.policies:
            for r in p.rules:
                if r not in rules:
                    raise ValueError(f"policy refers to unknown rule {r!r}; rules: {sorted(rules)}")
            for s in p.subjects:
                if s not in subjects:
                    raise ValueError(f"policy refers to unknown subject {s!r}; "
                                     f"subjects: {sorted(subjects)}")
        return self


class BusConfig(Frozen):
    cell: str = "cell1"
    robot: str = "r1"
    mode: Literal["peer", "client"] = "peer"
    listen: list[str] = ["tcp/127.0.0.1:0"]
    connect: list[str] = []
    multicast_scouting: bool = False
    gossip_scouting: bool = True
    republish_period_s: float = Field(2.0, gt=0)
    close_timeout_s: float = Field(3.0, gt=0)
    send_queue: int = Field(1000, ge=1)
    tls: TlsConfig | None = None
    access_control: AccessControlConfig | None = None
    extra: dict[str, Any] = {}

    @field_validator("cell", "robot")
    @classmethod
    def _chunk(cls, v: str) -> str:
        if not v or any(c in v for c in "/*$?#"):
            raise ValueError(f"{v!r} must be one non-empty key chunk (no / * $ ? #)")
        return v

    @field_validator("listen", "connect")
    @classmethod
    def _eps(cls, v: list[str]) -> list[str]:
        return [_check_endpoint(e) for e in v]

    @model_validator(mode="after")
    def _tls_endpoints(self) -> "BusConfig":
        if self.tls is not None:
            eps = self.listen + self.connect
            if not any(e.startswith(("tls/", "quic/")) for e in eps):
                raise ValueError("tls is configured but no listen/connect endpoint uses tls/ "
                                 "or quic/")
        if self.mode == "client" and not self.connect:
            raise ValueError("mode 'client' needs at least one connect endpoint (a router)")
        return self

    def key(self, kind: str) -> str:
        return f"dt/{self.cell}/{self.robot}/{kind}"

    def zenoh_config(self) -> zenoh.Config:
        """The zenoh.Config this maps to (see the module docstring)."""
        c = zenoh.Config()
        try:
            c.insert_json5("mode", json.dumps(self.mode))
            c.insert_json5("listen/endpoints", json.dumps(self.listen if self.mode == "peer"
                                                          else []))
            c.insert_json5("connect/endpoints", json.dumps(self.connect))
            c.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
            c.insert_json5("scouting/gossip/enabled", json.dumps(self.gossip_scouting))
            if self.tls is not None:
                for k, v in self.tls.model_dump(exclude_none=True).items():
                    c.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
            if self.access_control is not None:
                c.insert_json5("access_control",
                               json.dumps(self.access_control.model_dump(exclude_none=True)))
            for k, v in self.extra.items():
                c.insert_json5(k, json.dumps(v))
        except Exception as exc:  # zenoh.ZError: a value zenoh itself rejects
            raise DriverError(f"zenoh rejected the bus config: {exc}") from exc
        return c


def load_bus_config(path: str | Path) -> BusConfig:
    return load_yaml(path, BusConfig)


def _open(cfg: BusConfig) -> zenoh.Session:
    try:
        return zenoh.open(cfg.zenoh_config())
    except DriverError:
        raise
    except Exception as exc:
        raise DriverError(f"cannot open zenoh session ({cfg.mode}, listen={cfg.listen}, "
                          f"connect={cfg.connect}): {exc}") from exc


def _close_session(session: zenoh.Session, timeout: float) -> bool:
    """Close in a helper thread so a wedged close cannot hang the daemon; True if it finished."""
    def run() -> None:
        try:
            session.close()
        except Exception as exc:  # noqa: BLE001 - closing is best effort
            log.warning("zenoh close failed: %s", exc)

    th = threading.Thread(target=run, name="zenoh-close", daemon=True)
    th.start()
    th.join(timeout)
    if th.is_alive():
        log.warning("zenoh session did not close within %.1f s; abandoned", timeout)
        return False
    return True


def _encode(payload: Mapping[str, Any]) -> bytes:
    return json.dumps(payload, separators=(",", ":"), allow_nan=False,
                      default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)
                      ).encode()


class Bus:
    """Daemon-side bus for one robot; see the module docstring."""

    def __init__(self, config: BusConfig, store: Store | None = None, *,
                 on_ack: Callable[[int, dict[str, Any]], None] | None = None):
        self.config = config
        self.store = store
        self.on_ack = on_ack
        self.dropped = 0
        self.published = 0
        self.acked = 0
        self._tasks: queue.Queue = queue.Queue()  # unbounded; sends are bounded by hand
        self._sends = 0
        self._count_lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._session = _open(config)
        s, Z = self._session, zenoh
        try:
            self._pub = {
                "telemetry": s.declare_publisher(
                    config.key("telemetry"), encoding=Z.Encoding.APPLICATION_JSON,
                    congestion_control=Z.CongestionControl.DROP, priority=Z.Priority.DATA_LOW,
                    reliability=Z.Reliability.BEST_EFFORT),
                "correction": s.declare_publisher(
                    config.key("correction"), encoding=Z.Encoding.APPLICATION_JSON,
                    congestion_control=Z.CongestionControl.BLOCK, priority=Z.Priority.DATA_HIGH,
                    reliability=Z.Reliability.RELIABLE),
                "state": s.declare_publisher(
                    config.key("state"), encoding=Z.Encoding.APPLICATION_JSON,
                    congestion_control=Z.CongestionControl.BLOCK,
                    priority=Z.Priority.INTERACTIVE_HIGH, reliability=Z.Reliability.RELIABLE),
                "maintenance/request": s.declare_publisher(
                    config.key("maintenance/request"), encoding=Z.Encoding.APPLICATION_JSON,
                    congestion_control=Z.CongestionControl.BLOCK,
                    priority=Z.Priority.INTERACTIVE_HIGH, reliability=Z.Reliability.RELIABLE),
            }
            self._ack_sub = s.declare_subscriber(
                config.key("maintenance/ack/*"),
                lambda sample: self._tasks.put(("ack", sample.payload.to_bytes())))
        except Exception as exc:
            _close_session(s, config.close_timeout_s)
            raise DriverError(f"cannot declare bus entities: {exc}") from exc
        self._worker = threading.Thread(target=self._run, name=f"bus-{config.robot}",
                                        daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ publishing
    def _check(self) -> None:
        if self._closed:
            raise StateError("bus is closed")

    def publish_telemetry(self, payload: Mapping[str, Any]) -> None:
        """Best effort, never blocks (DROP congestion control); may be lost."""
        self._check()
        try:
            self._pub["telemetry"].put(_encode(payload))
        except Exception as exc:  # noqa: BLE001 - telemetry is droppable by contract
            with self._count_lock:
                self.dropped += 1
            log.debug("telemetry dropped: %s", exc)

    def publish_correction(self, payload: Mapping[str, Any]) -> bool:
        return self._enqueue_send("correction", payload)

    def publish_state(self, payload: Mapping[str, Any]) -> bool:
        return self._enqueue_send("state", payload)

    def _enqueue_send(self, kind: str, payload: Mapping[str, Any]) -> bool:
        """Hand a reliable message to the worker; False (and counted) if the queue is full."""
        self._check()
        data = _encode(payload)
        with self._count_lock:
            if self._sends >= self.config.send_queue:
                self.dropped += 1
                return False
            self._sends += 1
        self._tasks.put(("send", kind, data))
        return True

    def request_maintenance(self, payload: Mapping[str, Any]) -> int:
        """Durably store, then publish until acked. Returns the outbox id.

        Raises StateError without a Store, StoreError if the request could not be committed
        (then nothing was published).
        """
        self._check()
        if self.store is None:
            raise StateError("request_maintenance needs a Store (the outbox makes it durable)")
        body = dict(payload)
        body.setdefault("uid", uuid.uuid4().hex)
        body.setdefault("cell", self.config.cell)
        body.setdefault("robot", self.config.robot)
        body.setdefault("created", time.time())
        oid = self.store.outbox_add(self.config.key("maintenance/request"), body)
        self._tasks.put(("wake",))
        return oid

    def pending(self) -> list:
        return [] if self.store is None else self.store.outbox_pending()

    # ------------------------------------------------------------------ worker
    def _run(self) -> None:
        next_republish = 0.0  # publish pending entries at once (restart case)
        while not self._stop.is_set():
            now = time.monotonic()
            if self.store is not None and now >= next_republish:
                self._republish()
                next_republish = time.monotonic() + self.config.republish_period_s
            try:
                task = self._tasks.get(timeout=max(0.0, next_republish - time.monotonic())
                                       if self.store is not None else 0.5)
            except queue.Empty:
                continue
            try:
                self._handle(task)
            except Exception:  # noqa: BLE001 - the worker must survive any single failure
                log.exception("bus worker task %s failed", task[0])
            if task[0] == "wake":
                next_republish = 0.0

    def _handle(self, task: tuple) -> None:
        kind = task[0]
        if kind == "send":
            with self._count_lock:
                self._sends -= 1
            self._pub[task[1]].put(task[2])
            self.published += 1
        elif kind == "ack":
            self._on_ack_bytes(task[1])
        elif kind == "stop":
            self._stop.set()

    def _on_ack_bytes(self, raw: bytes) -> None:
        try:
            msg = json.loads(raw)
            oid, uid = int(msg["id"]), str(msg["uid"])
        except (ValueError, KeyError, TypeError):
            log.warning("malformed maintenance ack ignored: %r", raw[:200])
            return
        if self.store is None:
            return
        item = self.store.outbox_get(oid)
        if item is None or item.payload.get("uid") != uid:
            log.warning("ack for unknown request id=%s uid=%s ignored", oid, uid)
            return
        if self.store.outbox_ack(oid):
            self.acked += 1
            if self.on_ack is not None:
                self.on_ack(oid, msg)

    def _republish(self) -> None:
        try:
            items = self.store.outbox_pending()
        except StoreError as exc:
            log.warning("cannot read outbox: %s", exc)
            return
        for item in items:
            if self._stop.is_set():
                return
            body = dict(item.payload) | {"id": item.id, "attempt": item.attempts + 1}
            try:
                if item.key == self.config.key("maintenance/request"):
                    self._pub["maintenance/request"].put(_encode(body))
                else:  # written under another cell/robot name: still deliver it there
                    self._session.put(item.key, _encode(body),
                                      encoding=zenoh.Encoding.APPLICATION_JSON,
                                      congestion_control=zenoh.CongestionControl.BLOCK,
                                      priority=zenoh.Priority.INTERACTIVE_HIGH)
                self.published += 1
                self.store.outbox_attempted(item.id)
            except StoreError as exc:
                log.warning("outbox attempt not recorded: %s", exc)
            except Exception as exc:  # noqa: BLE001 - zenoh error: retry next period
                log.warning("maintenance request %s not published: %s", item.id, exc)

    # ------------------------------------------------------------------ lifecycle
    def close(self, timeout: float | None = None) -> bool:
        """Stop the worker and close the session, bounded by `timeout` (config default)."""
        if self._closed:
            return True
        self._closed = True
        timeout = self.config.close_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        self._stop.set()
        self._tasks.put(("stop",))
        self._worker.join(max(0.0, deadline - time.monotonic()))
        return _close_session(self._session, max(0.1, deadline - time.monotonic())) \
            and not self._worker.is_alive()

    def __enter__(self) -> "Bus":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class MaintenanceConsumer:
    """Receives maintenance requests from every cell/robot, records and acks them.

    Requests are de-duplicated on (cell, robot, uid); every copy is acked (the first ack may
    have been lost). `on_request(request)` is called once per new request from the worker
    thread. Used by tests and by the `dt` CLI.
    """

    def __init__(self, config: BusConfig, *, key_expr: str = "dt/**/maintenance/request",
                 on_request: Callable[[dict[str, Any]], None] | None = None,
                 auto_ack: bool = True):
        self.config = config
        self.on_request = on_request
        self.auto_ack = auto_ack
        self.requests: list[dict[str, Any]] = []
        self.copies = 0
        self._seen: set[tuple[str, str, str]] = set()
        self._cond = threading.Condition()
        self._tasks: queue.Queue = queue.Queue()
        self._closed = False
        self._session = _open(config)
        try:
            self._sub = self._session.declare_subscriber(
                _keyexpr_ok(key_expr),
                lambda s: self._tasks.put((str(s.key_expr), s.payload.to_bytes())))
        except Exception as exc:
            _close_session(self._session, config.close_timeout_s)
            raise DriverError(f"cannot subscribe to {key_expr}: {exc}") from exc
        self._worker = threading.Thread(target=self._run, name="maintenance-consumer",
                                        daemon=True)
        self._worker.start()

    def _run(self) -> None:
        while True:
            task = self._tasks.get()
            if task is None:
                return
            try:
                self._handle(*task)
            except Exception:  # noqa: BLE001
                log.exception("maintenance consumer failed on %s", task[0])

    def _handle(self, key: str, raw: bytes) -> None:
        try:
            req = json.loads(raw)
            oid, uid = int(req["id"]), str(req["uid"])
        except (ValueError, KeyError, TypeError):
            log.warning("malformed maintenance request on %s ignored", key)
            return
        prefix = key[: -len("/maintenance/request")]  # dt/<cell>/<robot>
        with self._cond:
            self.copies += 1
            ident = (prefix, uid)
            new = ident not in self._seen
            if new:
                self._seen.add(ident)
                self.requests.append(req | {"key": key})
                self._cond.notify_all()
        if new and self.on_request is not None:
            self.on_request(req | {"key": key})
        if self.auto_ack:
            self.ack(prefix, oid, uid)

    def ack(self, prefix: str, oid: int, uid: str) -> None:
        """Publish the ack for request `oid` of `prefix` (= 'dt/<cell>/<robot>')."""
        if self._closed:
            return
        self._session.put(f"{prefix}/maintenance/ack/{oid}",
                          _encode({"id": oid, "uid": uid, "t": time.time()}),
                          encoding=zenoh.Encoding.APPLICATION_JSON,
                          congestion_control=zenoh.CongestionControl.BLOCK,
                          priority=zenoh.Priority.INTERACTIVE_HIGH)

    def wait_for(self, n: int, timeout: float) -> bool:
        """Wait until at least n distinct requests arrived; False on time-out."""
        with self._cond:
            return self._cond.wait_for(lambda: len(self.requests) >= n, timeout)

    def close(self, timeout: float | None = None) -> bool:
        if self._closed:
            return True
        self._closed = True
        timeout = self.config.close_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        self._tasks.put(None)
        self._worker.join(timeout)
        return _close_session(self._session, max(0.1, deadline - time.monotonic()))

    def __enter__(self) -> "MaintenanceConsumer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
