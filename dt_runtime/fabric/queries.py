"""`dt/<cell>/<robot>/<kind>`: a cell answers questions about itself (queryables; the bus keys'
contract, docs/bus.md: one query on `dt/*/*/status` through a router collects a whole plant).

One queryable per kind on `dt/<cell>/<robot>/<kind>` (status, health, requests, tests, provenance:
`health` is also the key the daemon publishes on; a queryable and a publisher share a key without
meeting); a query names the kind it wants by its key expression (`dt/*/*/status` through a router
asks every cell for its status, `dt/c1/r1/health` one cell's health) and gets one reply per kind
it intersects, on `dt/<cell>/<robot>/<kind>`,
signed like the daemon's other messages (bus.auth: readers may ignore `sig`). The kinds and what
they answer are the caller's (`answers`: kind -> a function returning a JSON object); the daemon's
are `service.answers` (status, health, requests, tests, provenance).

Zenoh callbacks only enqueue (they never block and never touch SQLite: an answer may read the
store); one worker thread answers and then drops the query, so the asker sees the end of the
replies at once. A query left waiting longer than `max_queued` deep is answered with an error
reply (the asker's timeout would otherwise be the only answer).
"""
from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from dt_kernel.errors import TwinError, cut
from dt_runtime.fabric.config import BusConfig
from dt_runtime.fabric.session import BusError, encode, serve_tasks, zenoh_errors

log = logging.getLogger("dt_runtime.service.bus")  # the log channel keeps its name (filters name it)

KINDS = ("status", "health", "requests", "tests", "provenance")


class QueryServer:
    """Answers `dt/<cell>/<robot>/<kind>` queries with `answers[kind]()` on `session` (the
    daemon's bus session: one listen endpoint per process).

    Each reply is `{"cell", "robot", "kind", **answers[kind]()}`; an answer that raises a
    TwinError gives `{..., "error", "type"}` instead, any other exception the same with
    "internal error" (logged); both are counted in `failed`. `served` counts replies sent,
    `overflow` the queries refused because `max_queued` were waiting. The answers run in the
    server's worker thread, one query at a time.

    Parameters
    ----------
    config : BusConfig
        The cell's bus config (`cell`, `robot`, `close_timeout_s`).
    session : zenoh.Session
        The open session the queryables are declared on; not closed by `close`.
    answers : mapping of str to callable
        Kind -> a function of no argument returning a JSON object (a dict).
    sign : callable or None
        `sign(key, payload) -> bytes` encodes a reply (the Bus's signer); None: plain JSON.
    max_queued : int
        Queries waiting for the worker beyond which a query gets an error reply (`Busy`).

    Raises
    ------
    BusError
        A queryable cannot be declared.
    """

    def __init__(self, config: BusConfig, session: zenoh.Session, answers: Mapping[str, Callable[[], Any]],
                 sign: Callable[[str, Mapping[str, Any]], bytes] | None = None, max_queued: int = 64):
        self.config, self.answers = config, dict(answers)
        self._sign = sign
        self._kinds = {k: zenoh.KeyExpr(config.key(k)) for k in self.answers}
        self._tasks: queue.Queue = queue.Queue(maxsize=max_queued)
        self.served = self.failed = self.overflow = 0
        self._queryables = []
        for key in self._kinds.values():  # one per kind: a wildcard would also take `.../correct`'s queries
            with zenoh_errors(f"declare queryable {key}"):
                self._queryables.append(session.declare_queryable(key, self._on_query))
        self._worker = threading.Thread(target=self._run, name=f"queries-{config.robot}", daemon=True)
        self._worker.start()

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._tasks.put_nowait(query)
        except queue.Full:
            self.overflow += 1
            try:
                with zenoh_errors("query overflow reply"):
                    query.reply_err(encode({"error": "too many queries waiting", "type": "Busy"}))
            except BusError as exc:
                log.debug("%s", exc)
            finally:
                query.drop()

    def _run(self) -> None:
        serve_tasks(self._tasks, self._answer_then_drop, lambda query: f"query {query.key_expr} not answered")

    def _answer_then_drop(self, query: zenoh.Query) -> None:
        try:
            self._answer(query)
        finally:
            query.drop()  # the asker sees the end of the replies now

    def _answer(self, query: zenoh.Query) -> None:
        asked = query.key_expr
        for kind, key in self._kinds.items():
            if not asked.intersects(key):
                continue
            try:
                body = {"cell": self.config.cell, "robot": self.config.robot, "kind": kind, **self.answers[kind]()}
            except TwinError as exc:
                body = {"cell": self.config.cell, "robot": self.config.robot, "kind": kind, "error": str(exc),
                        "type": type(exc).__name__}
                self.failed += 1
            except Exception as exc:  # noqa: BLE001 - a defect: logged, and still a reply
                log.exception("answer %s failed", kind)
                body = {"cell": self.config.cell, "robot": self.config.robot, "kind": kind,
                        "error": cut(f"internal error: {exc}"), "type": type(exc).__name__}
                self.failed += 1
            data = self._sign(str(key), body) if self._sign is not None else encode(body)
            with zenoh_errors(f"reply on {key}"):
                query.reply(key, data, encoding=zenoh.Encoding.APPLICATION_JSON)
            self.served += 1

    def close(self, timeout: float | None = None) -> None:
        """Undeclare the queryables (failures logged) and stop the worker; the session stays open.

        Parameters
        ----------
        timeout : float or None
            s to wait for the worker (it first answers the queries already waiting); None:
            `config.close_timeout_s`.
        """
        for q in self._queryables:
            try:
                with zenoh_errors(f"undeclare {q.key_expr}"):
                    q.undeclare()
            except BusError as exc:
                log.warning("%s", exc)
        try:
            self._tasks.put(None, timeout=0.5)
        except queue.Full:
            pass
        self._worker.join(self.config.close_timeout_s if timeout is None else timeout)
