"""The dashboard's plant page: every cell on the fabric, from a plant config (`dt dashboard --plant`).

`PlantWatch` joins the plant's bus as `dt status --bus` does (the plant config's `bus` section,
plant.config) and asks the plant every `period_s` with ONE query (plant.status.collect, kind
status): each cell's status, escalation and open requests, and the expected cells (`cells:`)
that did not answer. Between the queries it follows `dt/*/*/health` and `dt/*/*/state` so that a
cell's change shows at once. Every answer or message is a contact: the page shows its age.

A click on a cell opens its live view: the URL of that cell's own `dt dashboard`, when the plant
config lists one (`dashboards: {cell/robot: URL}`). The plant page does not draw cells itself (it
has no twin of theirs; the cell's dashboard reads its twin beside its daemon).

Health and state on the bus are shown as read (not checked against the service's signature: the
plant's tools do not hold the cells' keys); the periodic query corrects them within `period_s`.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any
from urllib.parse import urlsplit

from dt_kernel.errors import ConfigError
from dt_runtime.fabric.config import MAX_MESSAGE_BYTES
from dt_runtime.fabric.session import BusError, close_session, open_session, zenoh_errors
from dt_runtime.plant.config import PlantConfig
from dt_runtime.plant.status import collect

log = logging.getLogger("dt.dashboard")
PERIOD_S = 3.0  # between two plant queries
MAX_CELLS = 10_000  # cells kept (one row each): a bound whatever appears on the fabric
_FIELDS = ("status", "reason", "escalation", "open_requests", "episode", "ticks")


_LOOPBACK = {"127.0.0.1", "localhost", "::1"}


def check_links(cfg: PlantConfig, source: str, host: str, port: int) -> None:
    """Refuse a plant config whose `dashboards:` sends a cell's row back to this plant page itself
    (a cell's `dt dashboard` needs a port of its own, e.g. `--port 8766`).

    Parameters
    ----------
    cfg : PlantConfig
        The plant config.
    source : str
        Its file, for the error message.
    host, port : str, int
        Where this plant page serves (`dt dashboard --host`, `--port`; port 0: a free one, never
        a listed one).

    Raises
    ------
    ConfigError
        Naming the cell's `dashboards` key and its URL.
    """
    hosts = {host} | (_LOOPBACK if host in _LOOPBACK else set())
    for cell, url in cfg.dashboards.items():
        u = urlsplit(url)
        if port and u.port == port and u.hostname in hosts:
            raise ConfigError(source, f"dashboards.{cell}", url,
                              f"the plant page itself serves on {host}:{port}: give the cell's dt dashboard a "
                              "port of its own (dt dashboard --config CELL.yaml --port 8766) and list that")


class PlantWatch:
    """The plant's cells as last heard; `snapshot()` is what /api/plant serves."""

    def __init__(self, cfg: PlantConfig, period_s: float = PERIOD_S, timeout_s: float = 2.0):
        self.cfg, self.period_s, self.timeout_s = cfg, period_s, timeout_s
        self._lock = threading.Lock()
        self.cells: dict[str, dict[str, Any]] = {}  # cell/robot -> its row
        self.queries = 0  # plant queries answered (by any number of cells)
        self.last_query: float | None = None
        self.errors: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._session = open_session(cfg.bus)
        try:
            self._subs = []
            for kind in ("health", "state"):
                with zenoh_errors(f"cannot subscribe to dt/*/*/{kind}"):
                    self._subs.append(self._session.declare_subscriber(f"dt/*/*/{kind}", self._on_sample(kind)))
        except BusError:
            close_session(self._session, cfg.bus.close_timeout_s)
            raise
        self._thread = threading.Thread(target=self._run, name="dashboard-plant", daemon=True)
        self._thread.start()

    def _row(self, name: str) -> dict[str, Any] | None:
        row = self.cells.get(name)
        if row is None and len(self.cells) < MAX_CELLS:
            cell, _, robot = name.partition("/")
            row = self.cells[name] = {"cell": cell, "robot": robot}
        return row

    def _on_sample(self, kind: str):
        def on_sample(sample: Any) -> None:
            parts = str(sample.key_expr).split("/")  # dt/<cell>/<robot>/<kind>
            raw = sample.payload.to_bytes()
            if len(parts) != 4 or len(raw) > MAX_MESSAGE_BYTES:
                return
            try:
                msg = json.loads(raw)
            except ValueError:
                return
            if not isinstance(msg, dict):
                return
            with self._lock:
                row = self._row(f"{parts[1]}/{parts[2]}")
                if row is None:
                    return
                if kind == "health":
                    row.update({k: msg[k] for k in _FIELDS if k in msg})
                    if isinstance(msg.get("outbox_pending"), int):
                        row["open_requests"] = msg["outbox_pending"]  # the same count as status's
                elif isinstance(msg.get("dst"), str):
                    row["escalation"] = msg["dst"]
                row["last_contact"] = time.time()
        return on_sample

    def poll(self) -> dict[str, Any]:
        """One plant query now; its answers filed. Returns collect's result."""
        result = collect(self._session, "dt/*/*", "status", expected=self.cfg.cells, timeout_s=self.timeout_s)
        now = time.time()
        with self._lock:
            for c in result["cells"]:
                row = self._row(f"{c.get('cell')}/{c.get('robot')}")
                if row is not None:
                    row.update({k: c[k] for k in _FIELDS if k in c})
                    row["last_contact"] = now
                    row["latency_ms"] = c.get("latency_ms")
            self.queries += 1
            self.last_query = now
            self.errors = result["errors"][-20:]
        return result

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll()
            except Exception as exc:  # noqa: BLE001 - a failed query is shown as silence, the next one may pass
                log.warning("dashboard: plant query failed: %s", exc)
            self._stop.wait(self.period_s)

    def snapshot(self) -> dict[str, Any]:
        """Every cell heard of or expected: its last state, the age of its last contact (s), and
        `silent` for an expected cell not heard within two query periods (or never)."""
        now = time.time()
        stale = 2 * self.period_s + self.timeout_s
        with self._lock:
            names = list(self.cfg.cells) + sorted(n for n in self.cells if n not in self.cfg.cells)
            rows = []
            for name in names:
                cell, _, robot = name.partition("/")
                row = dict(self.cells.get(name) or {"cell": cell, "robot": robot})
                last = row.get("last_contact")
                row["age_s"] = None if last is None else round(now - last, 1)
                row["expected"] = name in self.cfg.cells
                row["silent"] = last is None or now - last > stale
                row["dashboard"] = self.cfg.dashboards.get(name)
                rows.append(row)
            return {"cells": rows, "queries": self.queries, "period_s": self.period_s, "server_t": now,
                    "last_query_age_s": None if self.last_query is None else round(now - self.last_query, 1),
                    "errors": list(self.errors)}

    def close(self) -> None:
        """Stop polling, undeclare the subscriptions and close the session."""
        self._stop.set()
        self._thread.join(self.timeout_s + 5)
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - closing is best effort
                pass
        close_session(self._session, self.cfg.bus.close_timeout_s)
