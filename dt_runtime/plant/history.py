"""The plant's maintenance history: every request the inbox received, once, in one table
(`maintenance_requests`, primary key cell, robot, uid, consumer group), on SQLite (a file path,
the default) or PostgreSQL (a `postgresql://` URL, the `plant` extra). Every row is committed
before `History.record` returns; database errors become StoreError. The table: docs/plant.md
("One maintenance inbox")."""
from __future__ import annotations

import json
import re
import sqlite3
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dt_kernel.errors import StoreError
from dt_runtime.plant.config import POSTGRES_SCHEMES

COLUMNS = ("cell", "robot", "uid", "grp", "request_id", "kind", "episode", "state", "reason", "created", "received",
           "attempt", "payload")
SCHEMA = """CREATE TABLE IF NOT EXISTS maintenance_requests (
    cell TEXT NOT NULL, robot TEXT NOT NULL, uid TEXT NOT NULL, grp TEXT NOT NULL,
    request_id BIGINT, kind TEXT, episode BIGINT, state TEXT, reason TEXT,
    created DOUBLE PRECISION, received DOUBLE PRECISION NOT NULL, attempt BIGINT, payload TEXT NOT NULL,
    PRIMARY KEY (cell, robot, uid, grp))"""
INSERT = (f"INSERT INTO maintenance_requests ({', '.join(COLUMNS)}) VALUES ({', '.join('?' * len(COLUMNS))}) "
          "ON CONFLICT DO NOTHING")


def _int(v: Any) -> int | None:
    return int(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _float(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


class History:
    """The history on one connection (its own lock: the inbox's worker writes, anyone reads).

    SQLite runs with WAL and synchronous=FULL (a committed row survives a power cut); the table is
    created when missing.

    Parameters
    ----------
    url : str
        A file path or ``sqlite:///PATH`` (SQLite), or a ``postgresql://`` URL.

    Raises
    ------
    StoreError
        When the database cannot be opened.
    ImportError
        For a PostgreSQL URL without psycopg installed (the ``plant`` extra).
    """

    def __init__(self, url: str):
        self.url = url
        self.postgres = url.startswith(POSTGRES_SCHEMES)
        self._lock = threading.Lock()
        with self._errors("open"):
            if self.postgres:
                import psycopg  # the `plant` extra: only a PostgreSQL history needs it

                self._db: Any = psycopg.connect(url, autocommit=True)
            else:
                path = Path(url.removeprefix("sqlite:///")) if url.startswith("sqlite:///") else Path(url)
                path.parent.mkdir(parents=True, exist_ok=True)
                self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute(SCHEMA)

    @property
    def where(self) -> str:
        """The database, for messages (a PostgreSQL URL without its password)."""
        return re.sub(r"://([^:/@]+):[^@]*@", r"://\1@", self.url)

    @contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except StoreError:
            raise
        except Exception as exc:  # noqa: BLE001 - sqlite3 and psycopg have no common root
            if type(exc).__module__.split(".")[0] not in ("sqlite3", "psycopg") and not isinstance(exc, OSError):
                raise
            raise StoreError(f"plant history {self.where}: {what} failed: {exc}") from exc

    def _sql(self, sql: str) -> str:
        return sql.replace("?", "%s") if self.postgres else sql

    def record(self, req: Mapping[str, Any], received: float) -> bool:
        """Commit one received request (``INSERT ... ON CONFLICT DO NOTHING``).

        Parameters
        ----------
        req : Mapping
            A request as the consumer passes it (with its ``key``, ``uid`` and ``group``).
        received : float
            s, Unix time of receipt.

        Returns
        -------
        bool
            True if it is new; False when this uid and group were already recorded.

        Raises
        ------
        StoreError
            When the insert fails (nothing is committed).
        KeyError
            When the request has no ``uid``.
        """
        key = str(req.get("key", ""))
        parts = key.split("/")
        cell, robot = (parts[1], parts[2]) if len(parts) >= 3 else (str(req.get("cell")), str(req.get("robot")))
        row = (cell, robot, str(req["uid"]), str(req.get("group", "")), _int(req.get("id")), req.get("kind"),
               _int(req.get("episode")), req.get("state"), req.get("reason"), _float(req.get("created")), received,
               _int(req.get("attempt")), json.dumps(dict(req), sort_keys=True, default=str))
        with self._lock, self._errors("insert"):
            cur = self._db.execute(self._sql(INSERT), row)
            return bool(cur.rowcount)

    def seen(self, group: str) -> set[tuple[str, str]]:
        """The requests of a consumer group already recorded: a restarted inbox acks their copies
        without recording them again.

        Parameters
        ----------
        group : str

        Returns
        -------
        set of (str, str)
            (``dt/<cell>/<robot>``, uid).

        Raises
        ------
        StoreError
        """
        with self._lock, self._errors("read"):
            rows = self._db.execute(self._sql("SELECT cell, robot, uid FROM maintenance_requests WHERE grp = ?"),
                                    (group,)).fetchall()
        return {(f"dt/{c}/{r}", u) for c, r, u in rows}

    def rows(self, limit: int = 1000) -> list[dict[str, Any]]:
        """The latest rows, newest first (payload parsed).

        Parameters
        ----------
        limit : int

        Returns
        -------
        list of dict
            Column name -> value.

        Raises
        ------
        StoreError
        """
        with self._lock, self._errors("read"):
            rows = self._db.execute(self._sql(f"SELECT {', '.join(COLUMNS)} FROM maintenance_requests "
                                              "ORDER BY received DESC LIMIT ?"), (int(limit),)).fetchall()
        return [dict(zip(COLUMNS, r)) | {"payload": json.loads(r[-1])} for r in rows]

    def count(self) -> int:
        """The number of rows.

        Returns
        -------
        int

        Raises
        ------
        StoreError
        """
        with self._lock, self._errors("read"):
            return int(self._db.execute("SELECT COUNT(*) FROM maintenance_requests").fetchone()[0])

    def close(self) -> None:
        """Close the connection (best effort)."""
        with self._lock:
            try:
                self._db.close()
            except Exception:  # noqa: BLE001 - closing is best effort
                pass

    def __enter__(self) -> History:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def open_history(url: str) -> History:
    """Open the history at ``url`` (see History).

    Parameters
    ----------
    url : str
        A file path or ``sqlite:///PATH``, or a ``postgresql://`` URL.

    Returns
    -------
    History

    Raises
    ------
    StoreError
        When the database cannot be opened.
    """
    return History(url)
