"""What a daemon answers on `dt/<cell>/<robot>/<kind>` (fabric.queries; docs/plant.md).

- `status`: the one line of a plant table: running / degraded / halted and why, the escalation
  state and episode, ticks and the last tick (epoch s), Eq. 17 failures, open requests (not
  acknowledged) and the oldest one's creation time, the twin (twin.json's SHA-256, short) and
  when it was calibrated, the process id and the time of the answer.
- `health`: what `.../health` carries (`service.health`).
- `requests`: the open requests (outbox entries not acknowledged: id, uid, group, kind, episode,
  created, attempts, reason) and the latest ones, acknowledged or not (`Store.requests`).
- `tests`: the latest Eq. 17 tests, newest first (t, t_value, dof, p_value, passed).
- `provenance`: the twin the daemon runs: its directory, twin.json's SHA-256, when it was
  calibrated (the provenance record's `created`), by which software, from which campaign files
  (paths and SHA-256), on which robot and with which instruments.

Answers read a `StatusView` (the daemon gives `service.health.CellStatus`), never the daemon;
they run on the query worker's thread (never zenoh's) and may read the store.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from dt_runtime.common.provenance import sha256_file
from dt_runtime.service.store import OutboxItem


class StatusView(Protocol):
    """What the answers read of a running daemon, and nothing more."""

    def health(self) -> dict[str, Any]:
        """What `.../health` carries now."""
        ...

    def open_requests(self) -> list[OutboxItem]:
        """Outbox entries no consumer acknowledged, oldest first."""
        ...

    def latest_requests(self, limit: int) -> list[dict[str, Any]]:
        """The latest maintenance requests, acknowledged or not, newest first.

        Parameters
        ----------
        limit : int
            At most this many.
        """
        ...

    def latest_tests(self, limit: int) -> list[dict[str, Any]]:
        """The latest Eq. 17 tests, newest first.

        Parameters
        ----------
        limit : int
            At most this many.
        """
        ...

    def t_test_failures(self) -> int:
        """Eq. 17 tests failed since the daemon started."""
        ...

    def escalation(self) -> str:
        """The escalation's state."""
        ...


def answers(view: StatusView, twin: dict[str, Any]) -> dict[str, Callable[[], dict[str, Any]]]:
    """The answers of one daemon.

    Parameters
    ----------
    view : StatusView
        The daemon's status (health, requests, tests).
    twin : dict
        The twin it runs (`twin_identity`: read once, the daemon runs one twin).

    Returns
    -------
    dict
        The answer of each query kind: a function of nothing that returns a JSON-able dict.
    """

    def status() -> dict[str, Any]:
        h = view.health()
        pending = view.open_requests()
        return {"status": h["status"], "reason": h["reason"], "escalation": h["escalation"],
                "episode": h["episode"], "ticks": h["ticks"], "last_tick": h["last_tick"],
                "t_test_failures": view.t_test_failures(), "open_requests": len(pending),
                "oldest_open_created": min((i.created for i in pending), default=None),
                "twin_sha256": twin["twin_sha256"][:12], "calibrated": twin["calibrated"],
                "pid": h["pid"], "t": time.time()}

    def requests() -> dict[str, Any]:
        return {"open": [{"id": i.id, "created": i.created, "attempts": i.attempts,
                          **{k: i.payload.get(k) for k in ("uid", "group", "kind", "episode", "reason")}}
                         for i in view.open_requests()],
                "latest": view.latest_requests(10), "escalation": view.escalation(),
                "t": time.time()}

    return {"status": status, "health": view.health,
            "requests": requests,
            "tests": lambda: {"tests": view.latest_tests(10), "t": time.time()},
            "provenance": lambda: dict(twin)}


def twin_identity(twin: Any, twin_dir: Path) -> dict[str, Any]:
    """The twin in `twin_dir` as the `provenance` answer gives it (twin.json hashed once).

    Parameters
    ----------
    twin : Twin
        The loaded twin.
    twin_dir : Path
        Its directory.

    Returns
    -------
    dict
        Directory, twin.json's SHA-256, calibration time, software, campaign files, robot,
        instruments, and the drivers it was calibrated with.
    """
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
