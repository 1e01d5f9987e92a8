"""Durable store of the twin daemon (`Store`): one SQLite file in WAL mode, `synchronous=FULL`.

Tables: `commands`, `corrections`, `measurements`, `t_stats` (the high-rate rows,
`service.rows`), `transitions`, `outbox` (maintenance requests that must reach a consumer),
`state` (the one resume row) and `operator_actions`. A transition, the state it leads to and the
requests it opens are one transaction (`Store.record_transition`). Its guarantees (crash, full
disk, one daemon per store, 0600 files, retention): docs/service.md. Times: `t` is the caller's
time stamp in s; `created` columns are wall-clock epoch s.
"""
from __future__ import annotations

import collections
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from dt_kernel.errors import StoreError
from dt_runtime.common import private_files
from dt_runtime.common.jsonsafe import compact
from dt_runtime.service.rows import ROW_TYPES, Row

log = logging.getLogger("dt.store")

SCHEMA_VERSION = 2  # 2 added operator_actions (a version-1 file gains it on open)

# Table name -> (columns written by the high-rate path, in order): the typed rows' fields.
_HIGH_RATE: dict[str, tuple[str, ...]] = {table: cls.columns() for table, cls in ROW_TYPES.items()}

_SQL_TYPE = {"float": "REAL", "bool": "INTEGER"}  # a row field's annotation -> its column's type; else TEXT


def _high_rate_table(table: str, cls: type[Row]) -> str:
    """CREATE TABLE of a high-rate table from its row type: the fields are the columns, in order."""
    cols = []
    for f in fields(cls):  # type: ignore[arg-type]
        base = str(f.type).split("|")[0].strip()
        sql = _SQL_TYPE.get(base, "TEXT")
        cols.append(f"{f.name} {sql}" + (" NOT NULL" if f.name == "t" else ""))
    return f"CREATE TABLE IF NOT EXISTS {table} (\n    id INTEGER PRIMARY KEY, {', '.join(cols)});"


_SCHEMA = "\n".join(_high_rate_table(t, c) for t, c in ROW_TYPES.items()) + """
CREATE TABLE IF NOT EXISTS transitions (
    id INTEGER PRIMARY KEY, t REAL NOT NULL, src TEXT NOT NULL, dst TEXT NOT NULL,
    evidence TEXT NOT NULL, created REAL NOT NULL);
CREATE TABLE IF NOT EXISTS outbox (
    id INTEGER PRIMARY KEY AUTOINCREMENT, created REAL NOT NULL, key TEXT NOT NULL,
    payload TEXT NOT NULL, acked INTEGER NOT NULL DEFAULT 0, acked_at REAL,
    attempts INTEGER NOT NULL DEFAULT 0, last_attempt REAL);
CREATE INDEX IF NOT EXISTS outbox_pending ON outbox(acked, id);
CREATE TABLE IF NOT EXISTS state (
    id INTEGER PRIMARY KEY CHECK (id = 1), name TEXT NOT NULL, data TEXT NOT NULL,
    updated REAL NOT NULL);
CREATE TABLE IF NOT EXISTS operator_actions (
    id INTEGER PRIMARY KEY AUTOINCREMENT, created REAL NOT NULL, kind TEXT NOT NULL,
    request_id INTEGER, by_whom TEXT NOT NULL, note TEXT NOT NULL, source TEXT NOT NULL,
    applied_at REAL, result TEXT);
CREATE INDEX IF NOT EXISTS operator_pending ON operator_actions(applied_at, id);
"""

#: Operator actions: 'delivered' (the request reached maintenance: stop republishing it),
#: 'done' (maintenance was done: leave maintenance_requested / halted) and 'rereference' (apply
#: the offered re-referencing of the camera frame: leave rereference_offered).
ACTION_KINDS = ("delivered", "done", "rereference")


@contextmanager
def _sqlite_errors(what: str) -> Iterator[None]:
    """The store's one boundary: sqlite3 (and file system) errors become StoreError."""
    try:
        yield
    except (sqlite3.Error, OSError) as exc:
        raise StoreError(f"{what}: {exc}") from exc


@dataclass(frozen=True)
class OperatorAction:
    """One row of `operator_actions`: `kind` (`ACTION_KINDS`) `by` whom and why (`note`),
    for which outbox entry (`request_id`, None: the open episode), from where (`source`: `cli`
    for `dt ack --store`, `bus`, `api` for `Daemon.acknowledge_maintenance`), when it was
    `created` and `applied_at` (epoch s, None until the daemon applied it) with its `result`."""

    id: int
    created: float
    kind: str
    request_id: int | None
    by: str
    note: str
    source: str
    applied_at: float | None = None
    result: str | None = None


@dataclass(frozen=True)
class OutboxItem:
    """One outbox entry: its id, creation time (epoch s), Zenoh key, payload and the number of
    publication attempts so far."""

    id: int
    created: float
    key: str
    payload: dict[str, Any]
    attempts: int


class Store:
    """The SQLite store; use it as a context manager or call `close()`.

    High-rate rows (`put`) leave the caller through one lock-free queue (a deque append, no lock,
    no I/O) and are committed in one transaction, by a writer thread every `batch_ms`
    (`background=True`: the daemon's loop never waits on a lock or an fsync), or else on the
    caller's thread once `batch_rows` rows wait or `batch_ms` elapsed (checked at each `put`;
    call `flush()` when idle). Every other write commits at once, with the queued rows and the
    staged resume row (`stage_state`) in the same transaction. With `synchronous=FULL` a
    committed row survives power loss, not only a crash: a maintenance request seen on the bus is
    never missing from the store. The connection is shared by threads (the loop, the store's
    writer, the bus worker, housekeeping) behind one lock.

    Any sqlite3 or file-system error becomes a StoreError naming the file; the failing
    transaction is rolled back (committed rows stay). Rows of a failed commit are kept for the
    next one, at most `max_pending_rows` (the oldest dropped and counted in `dropped_rows`);
    `write_errors_in_row` counts failed commits since the last good one.

    Parameters
    ----------
    path : str or Path
        The database file (created 0600 with its directory; an existing one readable by others
        is made 0600 with a warning).
    batch_rows : int
        Queued rows that trigger a commit without the writer thread.
    batch_ms : float
        Commit period of the queued rows, ms.
    background : bool
        Run the writer thread.
    max_pending_rows : int
        Bound of the rows kept for a retry after a failed commit.
    synchronous : str
        SQLite's `synchronous`: FULL (default), NORMAL or EXTRA.
    timeout_s : float
        How long a write waits for another connection's lock, s.
    exclusive : bool
        Take the advisory one-daemon-per-store lock (`flock` on `<path>.lock`, released by the
        kernel when the process dies); readers (`dt status`, `dt ack`) do not.
    clock : callable
        The batch timer's clock, s.

    Raises
    ------
    StoreError
        The file cannot be opened or switched to WAL, its schema is newer than this software's,
        `synchronous` is not allowed, or (`exclusive`) another process holds the store.
    """

    def __init__(self, path: str | Path, *, batch_rows: int = 200, batch_ms: float = 500.0,
                 background: bool = False, max_pending_rows: int = 100_000,
                 synchronous: str = "FULL", timeout_s: float = 5.0, exclusive: bool = False,
                 clock: Callable[[], float] = time.monotonic):
        self.path = Path(path)
        self._clock = clock  # the batch timer's clock (seconds; a test may drive it by hand)
        self._lock_file = self._take_lock() if exclusive else None
        self.batch_rows = int(batch_rows)
        self.batch_s = float(batch_ms) / 1000.0
        self.max_pending_rows = int(max_pending_rows)
        self.dropped_rows = 0
        self.write_errors = 0  # failed flushes of the writer thread (rows kept for a retry)
        self.write_errors_in_row = 0  # failed commits since the last good one (the daemon's health)
        self._lock = threading.RLock()
        # The one queue of high-rate rows: deque.append is atomic, so put() needs no lock.
        self._queue: collections.deque[Row] = collections.deque()
        self._pending: list[Row] = []  # taken from the queue, not yet committed
        self._closed = False
        self._staged_state: tuple[str, dict[str, Any]] | None = None
        if synchronous.upper() not in ("FULL", "NORMAL", "EXTRA"):
            self._release_lock()
            raise StoreError(f"synchronous={synchronous!r}: allowed FULL, NORMAL, EXTRA")
        try:
            self._open(synchronous, timeout_s)
        except BaseException:
            self._release_lock()
            raise
        self._last_flush = self._clock()  # once open: opening (fsyncs) is not batch time
        self._stop = threading.Event()
        self._writer: threading.Thread | None = None
        if background:
            self._writer = threading.Thread(target=self._write_periodically, name="dt-store-writer",
                                            daemon=True)
            self._writer.start()

    def _take_lock(self):
        """The advisory one-daemon-per-store lock (module docstring); StoreError naming the holder."""
        import fcntl
        import os

        lock_path = self.path.with_name(self.path.name + ".lock")
        with _sqlite_errors(f"{lock_path}: cannot create the store's lock file"):
            lock_path.parent.mkdir(parents=True, exist_ok=True)
            # held open for the Store's lifetime
            f = os.fdopen(private_files.open_private(lock_path, "store lock"), "r+")
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            f.seek(0)
            holder = f.read().strip() or "another process"
            f.close()
            raise StoreError(f"{self.path} is in use by {holder}: one daemon per store (stop it, or give this "
                             "daemon its own `store:`)") from exc
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}")
        f.flush()
        return f

    def _release_lock(self) -> None:
        if self._lock_file is not None:
            self._lock_file.close()  # closing the descriptor releases the flock
            self._lock_file = None

    def _open(self, synchronous: str, timeout_s: float) -> None:
        with _sqlite_errors(f"{self.path}: cannot open store"):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            private_files.create_private(self.path)  # SQLite would create it 0644; an empty file is a new database
            for f in (self.path, *(self.path.with_name(self.path.name + x) for x in ("-wal", "-shm"))):
                private_files.tighten(f, "store file")
            # isolation_level=None: we issue BEGIN/COMMIT ourselves (one transaction per batch).
            self._db = sqlite3.connect(str(self.path), timeout=timeout_s,
                                       isolation_level=None, check_same_thread=False)
            mode = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreError(f"{self.path}: cannot switch to WAL journal (got {mode!r})")
            self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
            self._db.execute(f"PRAGMA busy_timeout={int(timeout_s * 1000)}")
            found = int(self._db.execute("PRAGMA user_version").fetchone()[0])
            if found > SCHEMA_VERSION:
                self._db.close()
                raise StoreError(f"{self.path}: store schema version {found} is newer than this software's "
                                 f"({SCHEMA_VERSION}): use the dt that wrote it, or another `store:` file")
            self._db.executescript(_SCHEMA)  # creates what a new file lacks; version 1 gains operator_actions
            self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Stop the writer thread, flush the queued rows (best effort) and close the file."""
        self._stop.set()
        if self._writer is not None:
            self._writer.join(timeout=5)  # outside the lock: the writer takes it to flush
        with self._lock:
            if self._closed:
                return
            try:
                self.flush()
            except StoreError:
                pass  # rows of a failed final flush are lost; committed rows are safe
            finally:
                self._closed = True
                self._db.close()
                self._release_lock()

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(f"{self.path}: store is closed")

    # ------------------------------------------------------------------ high-rate path
    def put(self, row: Row) -> None:
        """Queue one typed row. With the writer thread this is a deque append and nothing else;
        without it, the batch triggers are checked here (and may commit).

        Parameters
        ----------
        row : Row
            A `service.rows` row.

        Raises
        ------
        StoreError
            The store is closed, or (without the writer thread) the commit it triggered failed
            (the rows are kept for the next one).
        """
        self._check_open()
        self._queue.append(row)
        if self._writer is None and (
                len(self._queue) + len(self._pending) >= self.batch_rows
                or self._clock() - self._last_flush >= self.batch_s):
            self.flush()

    def flush(self) -> int:
        """Commit the queued rows in one transaction; returns how many were committed."""
        with self._lock:
            self._check_open()
            if not self._queue and not self._pending:
                self._last_flush = self._clock()
                return 0
            return self._tx(lambda: None)

    def _write_periodically(self) -> None:
        while not self._stop.wait(self.batch_s):
            try:
                self.flush()
            except StoreError as exc:  # disk full: rows are kept (bounded) for the next try
                self.write_errors += 1
                log.error("store write failed, will retry: %s", exc)

    def _write_pending(self) -> int:
        by_table: dict[str, list[tuple]] = {}
        for row in self._pending:
            by_table.setdefault(row.TABLE, []).append(row.values())
        for table, values in by_table.items():
            cols = _HIGH_RATE[table]
            self._db.executemany(f"INSERT INTO {table} ({','.join(cols)}) "
                                 f"VALUES ({','.join('?' * len(cols))})", values)
        return len(self._pending)

    def _tx(self, body: Callable[[], Any]) -> Any:
        """Run body() in one transaction together with the queued rows; StoreError on failure.

        Returns the number of queued rows committed if body returns None, else body's value.
        """
        with self._lock:
            self._check_open()
            queue = self._queue
            while queue:  # popleft is atomic too: rows put meanwhile stay for the next batch
                self._pending.append(queue.popleft())
            staged, self._staged_state = self._staged_state, None
            try:
                with _sqlite_errors(f"{self.path}: write failed"):
                    self._db.execute("BEGIN IMMEDIATE")
                    try:
                        n = self._write_pending()
                        if staged is not None:
                            self._write_state(*staged)
                        result = body()
                        self._db.execute("COMMIT")
                    except BaseException:
                        if self._db.in_transaction:
                            self._db.execute("ROLLBACK")
                        raise
            except StoreError:
                self.write_errors_in_row += 1
                if self._staged_state is None:  # nothing newer was staged meanwhile: retry this one
                    self._staged_state = staged
                # Keep the rows for a retry, bounded so a full disk cannot exhaust RAM.
                excess = len(self._pending) - self.max_pending_rows
                if excess > 0:
                    del self._pending[:excess]
                    self.dropped_rows += excess
                raise
            self._pending.clear()
            self.write_errors_in_row = 0
            self._last_flush = self._clock()
            return n if result is None else result

    # ------------------------------------------------------------------ immediate writes
    def outbox_add(self, key: str, payload: Mapping[str, Any]) -> int:
        """Durably record a message that must be delivered (committed before this returns).

        Parameters
        ----------
        key : str
            The Zenoh key it is published on.
        payload : Mapping
            Its JSON-ready payload.

        Returns
        -------
        int
            The outbox id.

        Raises
        ------
        StoreError
            It could not be committed (nothing was written).
        """
        text = compact(dict(payload))
        return self._tx(lambda: self._db.execute(
            "INSERT INTO outbox (created, key, payload) VALUES (?,?,?)",
            (time.time(), str(key), text)).lastrowid)

    def outbox_add_many(self, items: Iterable[tuple[str, Mapping[str, Any]]]) -> list[int]:
        """Several messages in one transaction (all or none).

        Parameters
        ----------
        items : iterable of (str, Mapping)
            (key, payload) of each message.

        Returns
        -------
        list of int
            Their outbox ids, in order.

        Raises
        ------
        StoreError
            They could not be committed (none was written).
        """
        rows = [(str(k), compact(dict(p))) for k, p in items]
        return self._tx(lambda: [self._insert_outbox(k, text) for k, text in rows])

    def _insert_outbox(self, key: str, text: str) -> int:
        rowid = self._db.execute("INSERT INTO outbox (created, key, payload) VALUES (?,?,?)",
                                 (time.time(), key, text)).lastrowid
        assert rowid is not None  # an INSERT always sets it
        return rowid

    def outbox_pending(self) -> list[OutboxItem]:
        """Un-acknowledged outbox entries, oldest first."""
        rows = self._query("SELECT id, created, key, payload, attempts FROM outbox "
                           "WHERE acked = 0 ORDER BY id")
        return [OutboxItem(r[0], r[1], r[2], json.loads(r[3]), r[4]) for r in rows]

    def outbox_get(self, id: int) -> OutboxItem | None:
        """One outbox entry, acknowledged or not.

        Parameters
        ----------
        id : int
            The outbox id.

        Returns
        -------
        OutboxItem or None
            None if there is no such entry.
        """
        rows = self._query("SELECT id, created, key, payload, attempts FROM outbox WHERE id=?",
                           (int(id),))
        return OutboxItem(rows[0][0], rows[0][1], rows[0][2], json.loads(rows[0][3]),
                          rows[0][4]) if rows else None

    def outbox_attempted(self, id: int) -> None:
        """Count one (re)publication attempt, with its time.

        Parameters
        ----------
        id : int
            The outbox id.
        """
        self._tx(lambda: self._db.execute(
            "UPDATE outbox SET attempts = attempts + 1, last_attempt = ? WHERE id = ?",
            (time.time(), int(id))) and None)

    def outbox_ack(self, id: int) -> bool:
        """Mark an entry acknowledged (idempotent).

        Parameters
        ----------
        id : int
            The outbox id.

        Returns
        -------
        bool
            True if it was pending.
        """
        return self._tx(lambda: self._db.execute(
            "UPDATE outbox SET acked = 1, acked_at = ? WHERE id = ? AND acked = 0",
            (time.time(), int(id))).rowcount == 1)

    def _write_state(self, name: str, data: Mapping[str, Any]) -> None:
        self._db.execute(
            "INSERT INTO state (id, name, data, updated) VALUES (1,?,?,?) ON CONFLICT(id) "
            "DO UPDATE SET name=excluded.name, data=excluded.data, updated=excluded.updated",
            (str(name), compact(dict(data)), time.time()))

    def save_state(self, name: str, data: Mapping[str, Any]) -> None:
        """Replace the single resume row (the escalation snapshot); committed at once. What was
        staged goes into the same transaction first and is overwritten by this newer one; a failed
        save leaves it staged for the next commit.

        Parameters
        ----------
        name : str
            What the row holds (the daemon's is "escalation").
        data : Mapping
            The JSON-ready state.

        Raises
        ------
        StoreError
            It could not be committed.
        """
        self._tx(lambda: self._write_state(name, data))

    def stage_state(self, name: str, data: Mapping[str, Any]) -> None:
        """Hand the latest resume row to the next commit (the batch of high-rate rows, or any
        immediate write), so the statistics on disk match the committed t-tests: no I/O here. A
        later stage or save replaces it.

        Parameters
        ----------
        name : str
            What the row holds.
        data : Mapping
            The JSON-ready state (copied).
        """
        self._staged_state = (str(name), dict(data))

    def record_transition(self, src: str, dst: str, evidence: Mapping[str, Any], t: float, *,
                          state: tuple[str, Mapping[str, Any]] | None = None,
                          requests: Iterable[tuple[str, Mapping[str, Any]]] = (),
                          applied: tuple[int, str] | None = None) -> tuple[int, list[int]]:
        """One transition as one transaction: the transition row, the resume row, the requests
        it opens and the operator action it carries out, with the queued rows, all or none.

        Parameters
        ----------
        src, dst : str
            The states it moved from and to.
        evidence : Mapping
            Why (JSON-ready).
        t : float
            The caller's time stamp, s.
        state : (str, Mapping), optional
            The resume row (name, snapshot); the daemon always gives it.
        requests : iterable of (str, Mapping)
            The outbox entries (key, payload) it opens.
        applied : (int, str), optional
            The operator action (id, result) it carries out.

        Returns
        -------
        (int, list of int)
            The transition's id and the outbox ids.

        Raises
        ------
        StoreError
            It could not be committed: nothing was written.
        """
        reqs = [(str(k), compact(dict(p))) for k, p in requests]
        # The staged resume row is taken by _tx under the lock and overwritten by `state` below;
        # it is not cleared here, outside the lock: a concurrent batch would then commit rows
        # without any state, and a failed transaction (a full disk) would lose it.

        def body() -> tuple[int, list[int]]:
            now = time.time()
            tid = self._db.execute(
                "INSERT INTO transitions (t, src, dst, evidence, created) VALUES (?,?,?,?,?)",
                (float(t), str(src), str(dst), compact(dict(evidence)), now)).lastrowid
            if state is not None:
                self._write_state(*state)
            ids = [self._insert_outbox(k, text) for k, text in reqs]
            if applied is not None:
                self._db.execute("UPDATE operator_actions SET applied_at = ?, result = ? WHERE id = ?",
                                 (now, str(applied[1]), int(applied[0])))
            assert tid is not None  # an INSERT always sets it
            return tid, ids
        return self._tx(body)

    # ------------------------------------------------------------------ episodes and operators
    def outbox_of_episode(self, episode: int) -> list[OutboxItem]:
        """Outbox entries (pending or delivered) of one paging episode of the escalation.

        Parameters
        ----------
        episode : int
            The escalation's episode (the payload's `episode`).

        Returns
        -------
        list of OutboxItem
            Oldest first.
        """
        rows = self._query("SELECT id, created, key, payload, attempts FROM outbox "
                           "WHERE json_extract(payload, '$.episode') = ? ORDER BY id", (int(episode),))
        return [OutboxItem(r[0], r[1], r[2], json.loads(r[3]), r[4]) for r in rows]

    def outbox_ack_episode(self, episode: int) -> int:
        """Mark every pending entry of an episode acknowledged (maintenance done implies
        delivered).

        Parameters
        ----------
        episode : int
            The escalation's episode.

        Returns
        -------
        int
            How many were pending.
        """
        return self._tx(lambda: self._db.execute(
            "UPDATE outbox SET acked = 1, acked_at = ? WHERE acked = 0 AND "
            "json_extract(payload, '$.episode') = ?", (time.time(), int(episode))).rowcount)

    def add_action(self, kind: str, by: str, note: str, *, request_id: int | None = None,
                   source: str = "store", applied: str | None = None) -> int:
        """Record an operator action (committed).

        Parameters
        ----------
        kind : str
            'delivered', 'done' or 'rereference' (`ACTION_KINDS`).
        by : str
            Who (not blank).
        note : str
            Why (not blank).
        request_id : int, optional
            The outbox entry it answers; None: the open episode.
        source : str
            Where it came from (`cli`, `bus`, `api`).
        applied : str, optional
            Its result, if it needs no daemon (a delivery confirmation); else the daemon applies
            it and fills in the result.

        Returns
        -------
        int
            The action's id.

        Raises
        ------
        StoreError
            An unknown kind, a blank `by` or `note`, or the commit failed.
        """
        if kind not in ACTION_KINDS:
            raise StoreError(f"operator action {kind!r}: allowed {', '.join(ACTION_KINDS)}")
        if not str(by).strip() or not str(note).strip():
            raise StoreError("an operator action needs who (by) and why (note)")
        now = time.time()
        return self._tx(lambda: self._db.execute(
            "INSERT INTO operator_actions (created, kind, request_id, by_whom, note, source, applied_at, result) "
            "VALUES (?,?,?,?,?,?,?,?)",
            (now, kind, request_id, str(by), str(note), str(source), now if applied else None, applied)).lastrowid)

    def apply_action(self, id: int, result: str) -> None:
        """Mark an operator action applied with its result (an action that changed no state).

        Parameters
        ----------
        id : int
            The action's id.
        result : str
            What came of it, in words.
        """
        self._tx(lambda: self._db.execute("UPDATE operator_actions SET applied_at = ?, result = ? WHERE id = ?",
                                          (time.time(), str(result), int(id))) and None)

    def actions(self, pending_only: bool = False, limit: int = 100) -> list[OperatorAction]:
        """The latest operator actions, oldest first.

        Parameters
        ----------
        pending_only : bool
            Only those not yet applied.
        limit : int
            At most this many (the newest).

        Returns
        -------
        list of OperatorAction
        """
        where = "WHERE applied_at IS NULL" if pending_only else ""
        rows = self._query("SELECT id, created, kind, request_id, by_whom, note, source, applied_at, result "
                           f"FROM operator_actions {where} ORDER BY id DESC LIMIT ?", (int(limit),))
        return [OperatorAction(*r) for r in reversed(rows)]

    def requests(self, limit: int = 20) -> list[dict[str, Any]]:
        """The latest outbox entries (maintenance requests), newest first, for `dt status`/`dt ack`.

        Parameters
        ----------
        limit : int
            At most this many.

        Returns
        -------
        list of dict
            `id`, `created`, `acked`, `acked_at`, `attempts` and the payload's `uid`, `episode`,
            `group`, `kind`, `reason`, `state`, `t`.
        """
        rows = self._query("SELECT id, created, payload, acked, acked_at, attempts FROM outbox "
                           "ORDER BY id DESC LIMIT ?", (int(limit),))
        return [{"id": r[0], "created": r[1], "acked": bool(r[3]), "acked_at": r[4], "attempts": r[5],
                 **{k: v for k, v in json.loads(r[2]).items()
                    if k in ("uid", "episode", "group", "kind", "reason", "state", "t")}} for r in rows]

    def last_t_tests(self, limit: int = 10) -> list[dict[str, Any]]:
        """The latest Eq. 17 tests, newest first (a cell's `tests` answer: service.answers).

        Parameters
        ----------
        limit : int
            At most this many.

        Returns
        -------
        list of dict
            `t`, `t_value`, `dof`, `p_value`, `passed`.
        """
        rows = self._query("SELECT t, t_value, dof, p_value, passed FROM t_stats ORDER BY id DESC LIMIT ?",
                           (int(limit),))
        return [{"t": r[0], "t_value": r[1], "dof": r[2], "p_value": r[3], "passed": bool(r[4])} for r in rows]

    # ------------------------------------------------------------------ retention
    def prune(self, *, before_t: float | None = None, keep_rows: int | None = None,
              chunk: int = 5_000) -> int:
        """Delete high-rate rows by age and/or count, in short transactions (the writer never
        waits long). Transitions, the outbox, the state and operator actions are never pruned.

        Parameters
        ----------
        before_t : float, optional
            Delete rows whose `t` (the callers' time, s) is older; None: no age bound.
        keep_rows : int, optional
            Keep the newest this many of each table; None: no count bound.
        chunk : int
            Rows per transaction and table.

        Returns
        -------
        int
            How many rows were deleted.

        Raises
        ------
        StoreError
            A delete could not be committed (those before it stay deleted).
        """
        total = 0
        for table in _HIGH_RATE:
            conds, params = [], []
            if before_t is not None:
                conds.append("t < ?")
                params.append(float(before_t))
            if keep_rows is not None:
                conds.append(f"id <= (SELECT COALESCE(MAX(id), 0) FROM {table}) - ?")
                params.append(int(keep_rows))
            if not conds:
                continue
            sql = (f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} WHERE "
                   f"{' OR '.join(conds)} ORDER BY id LIMIT {int(chunk)})")
            args = tuple(params)
            while True:
                n = self._delete(sql, args)
                total += n
                if n < chunk:
                    break
        return total

    def _delete(self, sql: str, args: tuple) -> int:
        return int(self._tx(lambda: self._db.execute(sql, args).rowcount))

    def size_bytes(self) -> int:
        """Bytes on disk: the database, its WAL and shared-memory files."""
        return sum(p.stat().st_size for p in (self.path, self.path.with_name(self.path.name + "-wal"),
                                              self.path.with_name(self.path.name + "-shm")) if p.exists())

    def load_state(self) -> dict[str, Any] | None:
        """{'name', 'data', 'updated'} of the resume row, or None on a fresh store."""
        rows = self._query("SELECT name, data, updated FROM state WHERE id = 1")
        if not rows:
            return None
        return {"name": rows[0][0], "data": json.loads(rows[0][1]), "updated": rows[0][2]}

    # ------------------------------------------------------------------ reading
    def _query(self, sql: str, params: tuple = ()) -> list[tuple]:
        with self._lock:
            self._check_open()
            with _sqlite_errors(f"{self.path}: read failed"):
                return self._db.execute(sql, params).fetchall()

    def count(self, table: str) -> int:
        """The number of rows of a table.

        Parameters
        ----------
        table : str
            One of the store's tables.

        Returns
        -------
        int

        Raises
        ------
        StoreError
            An unknown table, or the read failed.
        """
        if table not in (*_HIGH_RATE, "transitions", "outbox", "state", "operator_actions"):
            raise StoreError(f"unknown table {table!r}")
        return int(self._query(f"SELECT COUNT(*) FROM {table}")[0][0])

    def transitions(self, limit: int = 100) -> list[dict[str, Any]]:
        """The latest transitions, oldest first.

        Parameters
        ----------
        limit : int
            At most this many (the newest).

        Returns
        -------
        list of dict
            `id`, `t`, `src`, `dst`, `evidence`.
        """
        rows = self._query("SELECT id, t, src, dst, evidence FROM transitions "
                           "ORDER BY id DESC LIMIT ?", (int(limit),))
        return [{"id": r[0], "t": r[1], "src": r[2], "dst": r[3],
                 "evidence": json.loads(r[4])} for r in reversed(rows)]

    def integrity_ok(self) -> bool:
        """SQLite's `PRAGMA integrity_check` found nothing wrong."""
        return self._query("PRAGMA integrity_check")[0][0] == "ok"

    def last_figures(self) -> dict[str, Any]:
        """Small JSON-ready summary for `dt status`: counts, latest rows, state, outbox."""
        def last(table: str, cols: str) -> dict[str, Any] | None:
            rows = self._query(f"SELECT {cols} FROM {table} ORDER BY id DESC LIMIT 1")
            if not rows:
                return None
            out = dict(zip([c.strip() for c in cols.split(",")], rows[0]))
            for k in ("data", "evidence"):
                if out.get(k):
                    out[k] = json.loads(out[k])
            return out

        tstats = self._query("SELECT COUNT(*), SUM(passed = 0) FROM t_stats")[0]
        pending = self._query("SELECT COUNT(*), MIN(created) FROM outbox WHERE acked = 0")[0]
        return {
            "path": str(self.path),
            "counts": {t: self.count(t) for t in (*_HIGH_RATE, "transitions", "outbox")},
            "buffered_rows": len(self._queue) + len(self._pending),
            "dropped_rows": self.dropped_rows,
            "last_command": last("commands", "t, x, y, z, speed"),
            "last_correction": last("corrections", "t, dx, dy, dz, ux, uy, uz"),
            "last_measurement": last("measurements", "t, x, y, z, ex, ey, ez"),
            "last_tstat": last("t_stats", "t, t_value, dof, p_value, passed"),
            "t_tests": {"n": int(tstats[0] or 0), "failed": int(tstats[1] or 0)},
            "last_transition": last("transitions", "t, src, dst, evidence"),
            "state": self.load_state(),
            "outbox_pending": int(pending[0] or 0),
            "oldest_pending_created": pending[1],
            "requests": self.requests(limit=5),
            "operator_actions": [a.__dict__ for a in self.actions(limit=5)],
        }
