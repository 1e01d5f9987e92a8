"""The dashboard's live state: the latest of everything and bounded histories, shared between
the bus worker (writes) and the page streams (read), in bounded memory whatever the run's length.

Every update gets a sequence number. A page's stream (server.py) remembers the last number it
sent and, when woken, sends what is newer in one batch; a page that falls behind by more than a
ring holds loses the oldest telemetry (the stream counts it), never its memory. State
transitions, health and requests are few and kept as the latest plus a bounded history.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

TELEMETRY_RING = 2000  # 16 s at 125 Hz: what a page that reconnects gets back, and the plot's window
EVENT_RING = 500  # state transitions, health changes and requests waiting for the pages
TIMELINE = 200  # escalation transitions kept for the timeline
REQUESTS = 50  # maintenance requests kept (the newest; one entry per uid)


class Hub:
    def __init__(self, telemetry_ring: int = TELEMETRY_RING):
        self._cond = threading.Condition()
        self.seq = 0
        self.telemetry: deque[tuple[int, int, dict[str, Any]]] = deque(maxlen=telemetry_ring)  # (seq, n, msg)
        self.events: deque[tuple[int, str, dict[str, Any]]] = deque(maxlen=EVENT_RING)
        self.health: dict[str, Any] | None = None
        self.timeline: deque[dict[str, Any]] = deque(maxlen=TIMELINE)
        self.requests: dict[str, dict[str, Any]] = {}  # uid -> the request (its copies' ids by group)
        self.received = {"telemetry": 0, "health": 0, "state": 0, "request": 0}
        self.bus_refused = 0  # messages that claim to be the daemon's but do not carry its signature
        self.closed = False

    def _bump(self) -> int:
        self.seq += 1
        return self.seq

    def add_telemetry(self, msg: dict[str, Any]) -> None:
        with self._cond:
            self.received["telemetry"] += 1
            self.telemetry.append((self._bump(), self.received["telemetry"], msg))
            self._cond.notify_all()

    def add_health(self, msg: dict[str, Any]) -> None:
        with self._cond:
            self.received["health"] += 1
            self.health = msg
            self.events.append((self._bump(), "health", msg))
            self._cond.notify_all()

    def add_state(self, msg: dict[str, Any]) -> None:
        with self._cond:
            self.received["state"] += 1
            self.timeline.append(msg)
            self.events.append((self._bump(), "state", msg))
            self._cond.notify_all()

    def add_request(self, msg: dict[str, Any]) -> None:
        """A request copy (one per consumer group, republished until acknowledged): one entry per
        uid, with every group's copy id; the newest REQUESTS uids are kept."""
        with self._cond:
            self.received["request"] += 1
            uid = str(msg.get("uid"))
            entry = self.requests.pop(uid, None) or {k: v for k, v in msg.items() if k not in ("id", "group", "attempt",
                                                                                              "sig")}
            entry.setdefault("copies", {})[str(msg.get("group"))] = msg.get("id")
            entry["attempt"] = msg.get("attempt")
            entry["last_seen"] = time.time()
            self.requests[uid] = entry  # re-inserted: newest last
            while len(self.requests) > REQUESTS:
                self.requests.pop(next(iter(self.requests)))
            self.events.append((self._bump(), "request", entry))
            self._cond.notify_all()

    def mark_request(self, uid: str, **fields: Any) -> None:
        """What the dashboard's operators did with a request (acknowledged, done: by whom)."""
        with self._cond:
            entry = self.requests.get(uid)
            if entry is None:
                return
            entry.update(fields)
            self.events.append((self._bump(), "request", entry))
            self._cond.notify_all()

    def refused(self) -> None:
        with self._cond:
            self.bus_refused += 1

    def request(self, uid: str) -> dict[str, Any] | None:
        with self._cond:
            entry = self.requests.get(uid)
            return None if entry is None else dict(entry)

    def snapshot(self) -> dict[str, Any]:
        """Everything a page needs when it (re)connects, and the sequence number it covers."""
        with self._cond:
            return {"seq": self.seq, "health": self.health, "timeline": list(self.timeline),
                    "requests": list(self.requests.values()),
                    "telemetry": [m for _, _, m in self.telemetry][-500:],
                    "telemetry_n": self.received["telemetry"],
                    "received": dict(self.received), "bus_refused": self.bus_refused}

    def since(self, seq: int, timeout: float) -> tuple[int, list[tuple[int, dict[str, Any]]],
                                                      list[tuple[str, dict[str, Any]]]]:
        """Wait up to `timeout` s for anything newer than `seq`: (the newest seq, the telemetry
        newer than `seq` as (its number, message), the other events newer than `seq`). A caller
        that compares the first number with the last it got sees what the ring dropped."""
        with self._cond:
            self._cond.wait_for(lambda: self.seq > seq or self.closed, timeout)
            tel = [(n, m) for s, n, m in self.telemetry if s > seq]
            ev = [(k, m) for s, k, m in self.events if s > seq]
            return self.seq, tel, ev

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()
