"""What a daemon answers on `dt/<cell>/<robot>/<kind>` (fabric.queries; docs/plant.md).

- `status`: the one line of a plant table: running / degraded / halted and why, the escalation
  state and episode, ticks and the last tick (epoch s), Eq. 17 failures, open requests (not
  acknowledged) and the oldest one's creation time, the twin (twin.json's SHA-256, short) and
  when it was calibrated, the process id and the time of the answer.
- `health`: what `.../health` carries (`Daemon.health()`).
- `requests`: the open requests (outbox entries not acknowledged: id, uid, group, kind, episode,
  created, attempts, reason) and the latest ones, acknowledged or not (`Store.requests`).
- `tests`: the latest Eq. 17 tests, newest first (t, t_value, dof, p_value, passed).
- `provenance`: the twin the daemon runs: its directory, twin.json's SHA-256, when it was
  calibrated (the provenance record's `created`), by which software, from which campaign files
  (paths and SHA-256), on which robot and with which instruments.

Answers run on the query worker's thread (never zenoh's): they may read the store.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dt_runtime.common.provenance import sha256_file


def answers(daemon: Any, twin_dir: Path) -> dict[str, Callable[[], dict[str, Any]]]:
    """The answers of `daemon` (a service.daemon.Daemon) whose twin lives in `twin_dir`."""
    twin = _twin_identity(daemon.twin, twin_dir)  # read once: the daemon runs one twin

    def status() -> dict[str, Any]:
        h = daemon.health()
        pending = daemon.store.outbox_pending()
        return {"status": h["status"], "reason": h["reason"], "escalation": h["escalation"],
                "episode": h["episode"], "ticks": h["ticks"], "last_tick": h["last_tick"],
                "t_test_failures": daemon.counters.failures, "open_requests": len(pending),
                "oldest_open_created": min((i.created for i in pending), default=None),
                "twin_sha256": twin["twin_sha256"][:12], "calibrated": twin["calibrated"],
                "pid": h["pid"], "t": time.time()}

    def requests() -> dict[str, Any]:
        return {"open": [{"id": i.id, "created": i.created, "attempts": i.attempts,
                          **{k: i.payload.get(k) for k in ("uid", "group", "kind", "episode", "reason")}}
                         for i in daemon.store.outbox_pending()],
                "latest": daemon.store.requests(limit=10), "escalation": daemon.escalator.state,
                "t": time.time()}

    return {"status": status, "health": daemon.health,
            "requests": requests,
            "tests": lambda: {"tests": daemon.store.last_t_tests(10), "t": time.time()},
            "provenance": lambda: dict(twin)}


def _twin_identity(twin: Any, twin_dir: Path) -> dict[str, Any]:
    meta = twin_dir / "twin.json"
    prov = twin.provenance
    rec = prov.to_dict() if prov is not None else None
    return {"twin": str(twin_dir), "twin_sha256": sha256_file(meta) if meta.is_file() else None,
            "calibrated": rec["created"] if rec else None,
            "software": rec["software"] if rec else None,
            "campaign": [{"path": f["path"], "sha256": f["sha256"]} for f in rec["inputs"]] if rec else [],
            "robot": rec["robot"] if rec else None,
            "instruments": [{k: i.get(k) for k in ("role", "kind", "model", "serial", "certificate")}
                            for i in rec["instruments"]] if rec else [],
            "instruments_drivers": dict(twin.instruments)}
