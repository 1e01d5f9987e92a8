"""`Bus`: the daemon's side of the Zenoh bus for one robot (the keys, their QoS, the delivery of
maintenance requests and the threads: docs/bus.md). Requests and reliable messages leave
signed; an ack or 'done' without a valid signature of the service's key is refused, logged and
counted (`refused`, `last_refused`), and nothing is recorded (bus.auth).

A client whose router is not up yet starts all the same (`state` is `connecting`,
fabric.session.SessionOpener): telemetry is dropped meanwhile (counted), reliable messages wait in
the send queue (bounded; of health only the latest is kept), maintenance requests in the outbox;
once connected, the services given to `serve` are declared and the outbox drains."""
from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from dt_kernel.errors import DataError, StateError
from dt_runtime.common.safe_json import loads
from dt_runtime.fabric.auth import Signer
from dt_runtime.fabric.config import MAX_MESSAGE_BYTES, BusConfig
from dt_runtime.fabric.session import (
    BusError,
    SessionOpener,
    encode,
    put_json,
    zenoh_errors,
)
from dt_runtime.service.events import RequestsQueued, Transition
from dt_runtime.service.store import Store, StoreError

log = logging.getLogger("dt_runtime.service.bus")  # the log channel keeps its name (filters name it)

_CC, _P, _R = zenoh.CongestionControl, zenoh.Priority, zenoh.Reliability
# kind -> (congestion control, priority, reliability)
_QOS = {
    "telemetry": (_CC.DROP, _P.DATA_LOW, _R.BEST_EFFORT),
    "correction": (_CC.BLOCK, _P.DATA_HIGH, _R.RELIABLE),
    "state": (_CC.BLOCK, _P.INTERACTIVE_HIGH, _R.RELIABLE),
    "health": (_CC.BLOCK, _P.INTERACTIVE_HIGH, _R.RELIABLE),
    "maintenance/request": (_CC.BLOCK, _P.INTERACTIVE_HIGH, _R.RELIABLE),
}


def new_requests(config: BusConfig, body: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The outbox entries (key, payload) of one maintenance request: one per consumer group, all
    with the same `uid` (consumers of a group de-duplicate on it) and each with its `group`.

    Parameters
    ----------
    config : BusConfig
        The key, the cell and robot names, the consumer groups.
    body : Mapping
        The request; `uid`, `cell`, `robot` and `created` (epoch s) are added unless given.

    Returns
    -------
    list of (str, dict)
        One (key, payload) per consumer group.
    """
    base = dict(body)
    base.setdefault("uid", uuid.uuid4().hex)
    base.setdefault("cell", config.cell)
    base.setdefault("robot", config.robot)
    base.setdefault("created", time.time())
    return [(config.key("maintenance/request"), base | {"group": g}) for g in config.consumer_groups]


class Bus:
    """Daemon-side bus for one robot (module docstring).

    One worker thread (`bus-<robot>`) sends the reliable messages, republishes the outbox's
    pending entries every `republish_period_s` (and at once on `wake`) and handles acks and
    'done's; zenoh's callbacks only queue work for it. Telemetry is put on the caller's thread.

    Parameters
    ----------
    config : BusConfig
        Endpoints, names, QoS bounds, the signing key (`auth.key_file`, created on first start).
    store : Store, optional
        The outbox (maintenance requests, acks and operator actions); None: no requests.
    on_ack : callable, optional
        `on_ack(outbox id, ack)` after a signed delivery acknowledgement was recorded.
    on_done : callable, optional
        `on_done(action id)` after a signed 'done' was stored as an operator action.

    Raises
    ------
    BusError
        A peer's session cannot open (a client whose router is not up starts all the same).
    ConfigError
        The signing key is missing and cannot be created, cannot be read, is too short or open
        to others.
    """

    def __init__(self, config: BusConfig, store: Store | None = None, *,
                 on_ack: Callable[[int, dict[str, Any]], None] | None = None,
                 on_done: Callable[[int], None] | None = None):
        self.config = config
        self.store = store
        self.on_ack = on_ack
        self.on_done = on_done  # an operator's 'done' arrived and was stored as an action (its id)
        self.dropped = 0
        self.published = 0
        self.acked = 0
        self.refused = 0  # acks and dones without a valid signature (bus.auth)
        self.last_refused: str | None = None
        self.signer = Signer(config.auth, create=True)  # the service makes its key on first start
        self._tasks: queue.Queue = queue.Queue()  # unbounded; sends are bounded by hand
        self._sends = 0
        self._count_lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._session: zenoh.Session | None = None
        self._ready = threading.Event()  # the session is open and declared
        self._serve_lock = threading.Lock()
        self._factories: list[Callable[[zenoh.Session], Any]] = []  # `serve`: run once connected
        self._served: list[Any] = []  # what they made, closed with the bus
        self._held_health: bytes | None = None  # the latest health while connecting
        self._opener = SessionOpener(config, on_connected=self._connected)  # raises for a peer that cannot open
        self._worker = threading.Thread(target=self._run, name=f"bus-{config.robot}",
                                        daemon=True)
        self._worker.start()

    def _connected(self, s: zenoh.Session) -> None:
        """The session is open (now, or in the opener's thread): declare, serve, drain."""
        config = self.config
        with zenoh_errors("cannot declare bus entities"):
            self._pub = self._declare(s, config)
            self._ack_sub = s.declare_subscriber(
                config.key("maintenance/ack/*"),
                lambda sample: self._tasks.put(("ack", str(sample.key_expr), sample.payload.to_bytes())))
            self._done_sub = s.declare_subscriber(
                config.key("maintenance/done/*"),
                lambda sample: self._tasks.put(("done", str(sample.key_expr), sample.payload.to_bytes())))
        with self._serve_lock:
            self._session = s
            for factory in self._factories:
                try:
                    self._keep(factory(s))
                except Exception:  # noqa: BLE001 - one service that cannot start must not keep the bus down
                    log.exception("bus: a service could not start on the new session")
            self._factories.clear()
            held, self._held_health = self._held_health, None
            self._ready.set()
        if held is not None:
            with self._count_lock:
                self._sends += 1
            self._tasks.put(("send", "health", held))
        self.wake()

    @property
    def state(self) -> str:
        """`connecting` (a client without its router: not yet, or again), `connected`, `closed`."""
        return "closed" if self._closed else self._opener.state

    def serve(self, factory: Callable[[zenoh.Session], Any]) -> None:
        """Run `factory(session)` (a service on the bus's session: queryables) now if the bus is
        connected, else when it connects; what it returns is closed (`close()`) with the bus.

        Parameters
        ----------
        factory : callable
            Takes the open zenoh session, returns an object with a `close()` method (or None:
            a hook that only needs to know the bus is connected).
        """
        with self._serve_lock:
            if self._closed:
                return
            if self._session is None:
                self._factories.append(factory)
                return
            self._keep(factory(self._session))

    def _keep(self, obj: Any) -> None:
        if obj is not None:
            self._served.append(obj)

    @staticmethod
    def _declare(session: zenoh.Session, config: BusConfig) -> dict[str, zenoh.Publisher]:
        """One publisher per kind, with the QoS of the package docstring."""
        return {kind: session.declare_publisher(config.key(kind), encoding=zenoh.Encoding.APPLICATION_JSON,
                                                congestion_control=cc, priority=prio, reliability=rel)
                for kind, (cc, prio, rel) in _QOS.items()}

    # ------------------------------------------------------------------ publishing
    def _check(self) -> None:
        if self._closed:
            raise StateError("bus is closed")

    def publish_telemetry(self, payload: Mapping[str, Any]) -> None:
        """Publish telemetry: best effort, never blocks (DROP congestion control); may be lost
        (counted in `dropped`, as it is while connecting).

        Parameters
        ----------
        payload : Mapping
            JSON-ready (docs/bus.md).

        Raises
        ------
        StateError
            The bus is closed.
        """
        self._check()
        if not self._ready.is_set():  # connecting: nowhere to send it
            with self._count_lock:
                self.dropped += 1
            return
        data = encode(payload)
        try:
            with zenoh_errors("telemetry put"):
                self._pub["telemetry"].put(data)
        except BusError as exc:  # telemetry is droppable by contract
            with self._count_lock:
                self.dropped += 1
            log.debug("telemetry dropped: %s", exc)

    def publish_correction(self, payload: Mapping[str, Any]) -> bool:
        """Queue a signed `.../correction` for the worker (reliable).

        Parameters
        ----------
        payload : Mapping
            JSON-ready.

        Returns
        -------
        bool
            False (and counted in `dropped`) if the send queue is full.

        Raises
        ------
        StateError
            The bus is closed.
        """
        return self._enqueue_send("correction", payload)

    def publish_state(self, payload: Mapping[str, Any]) -> bool:
        """Queue a signed `.../state` for the worker (reliable).

        Parameters
        ----------
        payload : Mapping
            A transition (`Transition.payload`).

        Returns
        -------
        bool
            False (and counted in `dropped`) if the send queue is full.

        Raises
        ------
        StateError
            The bus is closed.
        """
        return self._enqueue_send("state", payload)

    def publish_health(self, payload: Mapping[str, Any]) -> bool:
        """Queue a signed `.../health` for the worker (reliable); while connecting only the latest
        is held.

        Parameters
        ----------
        payload : Mapping
            The health (`HealthReporter.health`).

        Returns
        -------
        bool
            False (and counted in `dropped`) if the send queue is full.

        Raises
        ------
        StateError
            The bus is closed.
        """
        return self._enqueue_send("health", payload)

    def wake(self) -> None:
        """Publish the pending outbox entries now (a transition just committed some)."""
        if not self._closed:
            self._tasks.put(("wake",))

    def on_transition(self, event: Transition) -> None:
        """A recorded transition (`service.events`): `.../state`, and the requests it opened
        delivered now.

        Parameters
        ----------
        event : Transition
            The transition, once recorded.
        """
        self.publish_state(event.payload())
        if event.requests:
            self.wake()

    def on_requests(self, event: RequestsQueued) -> None:
        """Requests put in the outbox outside a transition (re-created at start-up): deliver them.

        Parameters
        ----------
        event : RequestsQueued
            Their outbox ids (all pending entries are delivered).
        """
        self.wake()

    def _enqueue_send(self, kind: str, payload: Mapping[str, Any]) -> bool:
        """Hand a reliable message to the worker, signed; False (and counted) if the queue is full."""
        self._check()
        data = self.signer.sign(self.config.key(kind), payload)
        if kind == "health" and not self._ready.is_set():
            with self._serve_lock:  # connecting: only the latest health is worth sending
                if not self._ready.is_set():
                    self._held_health = data
                    return True
        with self._count_lock:
            if self._sends >= self.config.send_queue:
                self.dropped += 1
                return False
            self._sends += 1
        self._tasks.put(("send", kind, data))
        return True

    def request_maintenance(self, payload: Mapping[str, Any]) -> int:
        """Durably store a maintenance request (one entry per consumer group), then publish it
        until each is acknowledged.

        Parameters
        ----------
        payload : Mapping
            The request (`new_requests` adds `uid`, `cell`, `robot`, `created`, `group`).

        Returns
        -------
        int
            The first group's outbox id.

        Raises
        ------
        StateError
            The bus is closed or has no Store.
        StoreError
            The request could not be committed (then nothing was published).
        """
        self._check()
        if self.store is None:
            raise StateError("request_maintenance needs a Store (the outbox makes it durable)")
        ids = [self.store.outbox_add(key, body) for key, body in new_requests(self.config, payload)]
        self.wake()
        return ids[0]

    def pending(self) -> list:
        """The outbox's un-acknowledged entries, oldest first (none without a Store)."""
        return [] if self.store is None else self.store.outbox_pending()

    # ------------------------------------------------------------------ worker
    def _run(self) -> None:
        next_republish = 0.0  # publish pending entries at once (restart case)
        while not self._stop.is_set():
            if not self._ready.is_set():  # connecting: what is queued and the outbox wait
                self._ready.wait(0.2)
                continue
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
            with zenoh_errors(f"{task[1]} put"):
                self._pub[task[1]].put(task[2])
            self.published += 1
        elif kind == "ack":
            self._on_ack_bytes(task[1], task[2])
        elif kind == "done":
            self._on_done_bytes(task[1], task[2])
        elif kind == "stop":
            self._stop.set()

    def _refuse(self, what: str, key: str, reason: str, msg: Mapping[str, Any]) -> None:
        """An ack or 'done' that does not carry the service's signature: nothing is recorded."""
        with self._count_lock:
            self.refused += 1
            self.last_refused = f"{what} on {key} refused: {reason}"
            n = self.refused
        if n <= 10 or n % 100 == 0:  # a flood of forgeries must not flood the log: the count is on .../health
            by = f" (by {str(msg.get('by'))[:80]!r})" if "by" in msg else ""
            log.warning("maintenance %s on %s%s refused, nothing recorded: %s (%d refused so far)", what, key, by,
                        reason, n)

    def _on_ack_bytes(self, key: str, raw: bytes) -> None:
        try:
            msg = loads(raw, "maintenance message", max_bytes=MAX_MESSAGE_BYTES)
            oid, uid = int(msg["id"]), str(msg["uid"])
        except (DataError, ValueError, KeyError, TypeError):
            log.warning("malformed maintenance ack ignored: %r", raw[:200])
            return
        why = self.signer.check(key, msg, fresh=True)
        if why:
            self._refuse("ack", key, why, msg)
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

    def _on_done_bytes(self, key: str, raw: bytes) -> None:
        """Maintenance done, from a maintenance system: stored as an operator action (who, why)
        for the daemon to apply; only signed with the service's key and for a request this store
        sent (id and uid match)."""
        try:
            msg = loads(raw, "maintenance message", max_bytes=MAX_MESSAGE_BYTES)
            oid, uid = int(msg["id"]), str(msg["uid"])
            by, note = str(msg["by"]), str(msg["note"])
        except (DataError, ValueError, KeyError, TypeError):
            log.warning("malformed maintenance done ignored (needs id, uid, by, note): %r", raw[:200])
            return
        why = self.signer.check(key, msg, fresh=True)
        if why:
            self._refuse("done", key, why, msg)
            return
        item = None if self.store is None else self.store.outbox_get(oid)
        if item is None or item.payload.get("uid") != uid:
            log.warning("done for unknown request id=%s uid=%s ignored", oid, uid)
            return
        assert self.store is not None
        aid = self.store.add_action("done", by, note, request_id=oid, source="bus")
        if self.on_done is not None:
            self.on_done(aid)

    def _republish(self) -> None:
        store = self.store
        if store is None:  # no outbox: nothing is ever pending
            return
        try:
            items = store.outbox_pending()
        except StoreError as exc:
            log.warning("cannot read outbox: %s", exc)
            return
        for item in items:
            if self._stop.is_set():
                return
            body = dict(item.payload) | {"id": item.id, "attempt": item.attempts + 1}
            data = self.signer.sign(item.key, body)
            try:
                if item.key == self.config.key("maintenance/request"):
                    with zenoh_errors("maintenance request put"):
                        self._pub["maintenance/request"].put(data)
                else:  # written under another cell/robot name: still deliver it there
                    put_json(self.session, item.key, data)
                self.published += 1
                store.outbox_attempted(item.id)
            except StoreError as exc:
                log.warning("outbox attempt not recorded: %s", exc)
            except BusError as exc:  # retried next period
                log.warning("maintenance request %s not published: %s", item.id, exc)

    @property
    def session(self) -> zenoh.Session:
        """The bus's Zenoh session, for services of the same process (one listen endpoint);
        StateError while connecting (`serve` runs a service once it is open)."""
        session = self._session
        if session is None:
            raise StateError(f"the bus is {self.state}: no session yet")
        return session

    # ------------------------------------------------------------------ lifecycle
    def close(self, timeout: float | None = None) -> bool:
        """Close the services given to `serve`, stop the worker and close the session.

        Parameters
        ----------
        timeout : float, optional
            Bound of the whole close, s (the config's `close_timeout_s` if None).

        Returns
        -------
        bool
            True if everything closed in time (also when already closed).
        """
        if self._closed:
            return True
        timeout = self.config.close_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        with self._serve_lock:
            self._closed = True
        self._stop.set()
        done = self._opener.cancel(timeout)  # no session opens after this
        with self._serve_lock:
            served, self._served = self._served, []
        for obj in reversed(served):
            try:
                obj.close()
            except Exception as exc:  # noqa: BLE001 - closing is best effort, keep closing the rest
                log.warning("bus: closing %s: %s", type(obj).__name__, exc)
        self._tasks.put(("stop",))
        self._worker.join(max(0.0, deadline - time.monotonic()))
        done = self._opener.close(max(0.1, deadline - time.monotonic())) and done
        return done and not self._worker.is_alive()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
