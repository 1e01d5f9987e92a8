"""`MaintenanceConsumer`: receives maintenance requests from every cell and robot on the bus,
records, de-duplicates and acknowledges them (tests, `dt consume` and the plant's inbox use it);
`publish_ack` and `publish_done` for the callers without one (`dt ack --bus`, the dashboard).
The protocol: docs/bus.md ("Maintenance request and acknowledgement")."""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from dt_kernel.errors import DataError
from dt_runtime.common.safe_json import loads
from dt_runtime.fabric.auth import Signer
from dt_runtime.fabric.config import MAX_MESSAGE_BYTES, BusConfig
from dt_runtime.fabric.session import (
    BusError,
    close_session,
    open_session,
    put_json,
    serve_tasks,
    shut_down,
    zenoh_errors,
)

log = logging.getLogger("dt_runtime.service.bus")  # the log channel keeps its name (filters name it)


def publish_ack(session: zenoh.Session, signer: Signer, prefix: str, oid: int, uid: str, group: str) -> str:
    """Acknowledge delivery of `group`'s copy `oid` (uid `uid`) of a request of `prefix`
    (= 'dt/<cell>/<robot>'), signed and time-stamped now; the key it was put on.

    Parameters
    ----------
    session : zenoh.Session
        An open session on the bus.
    signer : Signer
        Holds the service's key.
    prefix : str
        `dt/<cell>/<robot>` of the request.
    oid : int
        The request's `id` (its outbox row, one per group).
    uid : str
        The request's `uid`.
    group : str
        The consumer group whose copy this is.

    Returns
    -------
    str
        `<prefix>/maintenance/ack/<oid>`.

    Raises
    ------
    BusError
        The put failed.
    """
    key = f"{prefix}/maintenance/ack/{oid}"
    put_json(session, key, signer.sign(key, {"id": oid, "uid": uid, "group": group, "t": time.time()}))
    return key


def publish_done(session: zenoh.Session, signer: Signer, prefix: str, oid: int, uid: str, by: str, note: str) -> str:
    """Tell the twin of `prefix` that the maintenance asked for by request `oid` (uid `uid`) was
    done, by whom and why (stored with the transition back to nominal), signed and time-stamped
    now (it must reach the twin within bus.auth.max_age_s); the key it was put on.

    Parameters
    ----------
    session : zenoh.Session
        An open session on the bus.
    signer : Signer
        Holds the service's key.
    prefix : str
        `dt/<cell>/<robot>` of the request.
    oid : int
        The request's `id`.
    uid : str
        The request's `uid` (the twin applies the done only if it matches).
    by : str
        Who did the maintenance.
    note : str
        What was done, or why.

    Returns
    -------
    str
        `<prefix>/maintenance/done/<oid>`.

    Raises
    ------
    BusError
        The put failed.
    """
    key = f"{prefix}/maintenance/done/{oid}"
    put_json(session, key, signer.sign(key, {"id": oid, "uid": uid, "by": by, "note": note, "t": time.time()}))
    return key


class MaintenanceConsumer:
    """Receives maintenance requests from every cell/robot, records and acks them.

    Requests are de-duplicated on (dt/<cell>/<robot>, uid); every copy is acked (the first ack
    may have been lost). A consumer belongs to one consumer `group` and takes only its group's
    copy of each request (the twin sends one per configured group; a copy without a `group` is
    taken by every group). `done(...)` tells the twin that maintenance was done. Malformed
    messages (more than MAX_MESSAGE_BYTES, not JSON, no `id`/`uid`) are logged and ignored.

    Signed both ways (bus.auth): a request without the service's signature is not taken (a
    forged one: logged, counted in `refused`, `last_refused`, not acked); acks and dones leave
    signed with the same key (`config.auth.key_file`, created 0600 if missing).

    Threads: zenoh's callback only enqueues; one worker thread handles the requests, calls
    `on_request` and acks. `requests`, `copies`, `refused` and `last_refused` are updated under
    a lock; `wait_for` waits on it from any thread.

    Parameters
    ----------
    config : BusConfig
        The bus to join (and `auth`, the key).
    key_expr : str
        The requests subscribed to (default every cell's and robot's).
    on_request : callable or None
        Called once per new request (its payload plus `key`, the key it came on), in the
        worker thread. If it raises, the request is neither acked nor remembered, so the twin's
        next republication brings it again (a plant inbox acks only what its history committed).
    auto_ack : bool
        Ack every copy taken (default); False leaves acking to the caller (`ack`).
    group : str
        The consumer group.
    seen : iterable of (str, str)
        (dt/<cell>/<robot>, uid) pairs taken before (a restarted consumer's history): their
        copies are acked, not passed on again.

    Raises
    ------
    ConfigError
        The key cannot be created or read, or others may access it (`auth.Signer`).
    BusError
        The session cannot open or the subscription cannot be declared.
    """

    def __init__(self, config: BusConfig, *, key_expr: str = "dt/**/maintenance/request",
                 on_request: Callable[[dict[str, Any]], None] | None = None,
                 auto_ack: bool = True, group: str = "maintenance", seen: Iterable[tuple[str, str]] = ()):
        self.config = config
        self.group = group
        self.on_request = on_request
        self.auto_ack = auto_ack
        self.requests: list[dict[str, Any]] = []
        self.copies = 0
        self.refused = 0  # requests without the service's signature (forged, or another key)
        self.last_refused: str | None = None
        self.signer = Signer(config.auth, create=True)
        self._seen: set[tuple[str, str]] = set(seen)  # (dt/<cell>/<robot>, uid)
        self._cond = threading.Condition()
        self._tasks: queue.Queue = queue.Queue()
        self._closed = False
        self._session = open_session(config)
        try:
            with zenoh_errors(f"cannot subscribe to {key_expr}"):
                self._sub = self._session.declare_subscriber(
                    key_expr, lambda s: self._tasks.put((str(s.key_expr), s.payload.to_bytes())))
        except BusError:
            close_session(self._session, config.close_timeout_s)
            raise
        self._worker = threading.Thread(target=self._run, name="maintenance-consumer",
                                        daemon=True)
        self._worker.start()

    def _run(self) -> None:
        serve_tasks(self._tasks, lambda task: self._handle(*task),
                    lambda task: f"maintenance consumer failed on {task[0]}")

    def _handle(self, key: str, raw: bytes) -> None:
        try:
            req = loads(raw, "maintenance request", max_bytes=MAX_MESSAGE_BYTES)
            oid, uid = int(req["id"]), str(req["uid"])
        except (DataError, ValueError, KeyError, TypeError):
            log.warning("malformed maintenance request on %s ignored", key)
            return
        if req.get("group", self.group) != self.group:
            return  # another group's copy: its consumers ack it
        why = self.signer.check(key, req, fresh=False)
        if why:
            with self._cond:
                self.refused += 1
                self.last_refused = f"request on {key} refused: {why}"
            log.warning("maintenance request id=%s uid=%s on %s not taken: %s", oid, uid, key, why)
            return
        prefix = key[: -len("/maintenance/request")]  # dt/<cell>/<robot>
        with self._cond:
            self.copies += 1
            ident = (prefix, uid)
            new = ident not in self._seen
            if new:
                self._seen.add(ident)  # a concurrent copy is not taken twice while this one is recorded
        if new:
            if self.on_request is not None:
                try:
                    self.on_request(req | {"key": key})
                except BaseException:
                    with self._cond:  # not taken: the next copy is new again, and nothing is acked now
                        self._seen.discard(ident)
                    raise
            with self._cond:  # taken only once recorded: `requests` never shows one the record refused
                self.requests.append(req | {"key": key})
                self._cond.notify_all()
        if self.auto_ack:
            self.ack(prefix, oid, uid)

    def ack(self, prefix: str, oid: int, uid: str) -> None:
        """Publish the ack for request `oid` of `prefix` (= 'dt/<cell>/<robot>'); nothing once closed.

        Parameters
        ----------
        prefix : str
            `dt/<cell>/<robot>` of the request.
        oid : int
            The request's `id`.
        uid : str
            The request's `uid`.

        Raises
        ------
        BusError
            The put failed.
        """
        if self._closed:
            return
        publish_ack(self._session, self.signer, prefix, oid, uid, self.group)

    def done(self, prefix: str, oid: int, uid: str, by: str, note: str) -> None:
        """Tell the twin of `prefix` (= 'dt/<cell>/<robot>') that the maintenance asked for by
        request `oid` was done: who and why are stored with the transition back to nominal.

        Parameters
        ----------
        prefix : str
            `dt/<cell>/<robot>` of the request.
        oid : int
            The request's `id`.
        uid : str
            The request's `uid`.
        by : str
            Who did the maintenance.
        note : str
            What was done, or why.

        Raises
        ------
        BusError
            The consumer is closed, or the put failed.
        """
        if self._closed:
            raise BusError("consumer is closed")
        publish_done(self._session, self.signer, prefix, oid, uid, by, note)

    def wait_for(self, n: int, timeout: float) -> bool:
        """Wait until at least n distinct requests arrived; False on time-out.

        Parameters
        ----------
        n : int
            How many distinct requests (`len(requests)`).
        timeout : float
            s.

        Returns
        -------
        bool
            True once `n` have arrived, False if `timeout` passed first.
        """
        with self._cond:
            return self._cond.wait_for(lambda: len(self.requests) >= n, timeout)

    def close(self, timeout: float | None = None) -> bool:
        """Stop the worker and close the session; a second call does nothing.

        Parameters
        ----------
        timeout : float or None
            s for both; None: `config.close_timeout_s`.

        Returns
        -------
        bool
            True if the worker ended and the session closed in time (also when already closed).
        """
        if self._closed:
            return True
        self._closed = True
        return shut_down(self._session, self._worker, lambda: self._tasks.put(None),
                         self.config.close_timeout_s if timeout is None else timeout)

    def __enter__(self) -> MaintenanceConsumer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
