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
    """The dashboard's live state: telemetry in a ring, the latest health, the escalation timeline, the
    newest maintenance requests, and a sequence number per update; thread-safe.

    Parameters
    ----------
    telemetry_ring : int
        Telemetry messages kept.
    """
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
        """File one telemetry message (as the page draws it).

        Parameters
        ----------
        msg : dict
        """
        with self._cond:
            self.received["telemetry"] += 1
            self.telemetry.append((self._bump(), self.received["telemetry"], msg))
            self._cond.notify_all()

    def add_health(self, msg: dict[str, Any]) -> None:
        """File one health message (the latest is kept).

        Parameters
        ----------
        msg : dict
        """
        with self._cond:
            self.received["health"] += 1
            self.health = msg
            self.events.append((self._bump(), "health", msg))
            self._cond.notify_all()

    def add_state(self, msg: dict[str, Any]) -> None:
        """File one state transition (kept in the timeline). A return to nominal that an operator's
        'done' made (evidence ``acknowledged``, ``by``, ``note``: `dt ack --store`, a maintenance
        system's 'done' on the bus, this page's) closes every request made before it: the page
        shows them done, not waiting.

        Parameters
        ----------
        msg : dict
        """
        with self._cond:
            self.received["state"] += 1
            self.timeline.append(msg)
            self.events.append((self._bump(), "state", msg))
            evidence = msg.get("evidence")
            ev: dict[str, Any] = evidence if isinstance(evidence, dict) else {}
            t = msg.get("t")
            if msg.get("dst") == "nominal" and ev.get("acknowledged") and isinstance(t, (int, float)):
                for entry in self.requests.values():
                    made = entry.get("t")
                    if not entry.get("done_by") and isinstance(made, (int, float)) and made <= t:
                        entry.update(done_by=str(ev.get("by") or "operator"), done_note=str(ev.get("note") or ""),
                                     done_at=msg.get("rx"))
                        self.events.append((self._bump(), "request", entry))
            self._cond.notify_all()

    def add_request(self, msg: dict[str, Any]) -> None:
        """File a request copy (one per consumer group, republished until acknowledged).

        One entry per uid, with every group's copy id; the newest REQUESTS uids are kept.

        Parameters
        ----------
        msg : dict
            The request as published (``uid``, ``group``, ``id``, ``attempt``, ...).
        """
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
        """Record what the dashboard's operators did with a request; an unknown uid is ignored.

        Parameters
        ----------
        uid : str
        **fields
            E.g. ``acked_by``, ``done_by``: merged into the entry.
        """
        with self._cond:
            entry = self.requests.get(uid)
            if entry is None:
                return
            entry.update(fields)
            self.events.append((self._bump(), "request", entry))
            self._cond.notify_all()

    def refused(self) -> None:
        """Count one message refused for want of the service's signature."""
        with self._cond:
            self.bus_refused += 1

    def request(self, uid: str) -> dict[str, Any] | None:
        """A copy of the entry of a request.

        Parameters
        ----------
        uid : str

        Returns
        -------
        dict or None
            None when the hub holds no such request.
        """
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
        """Wait for anything newer than ``seq``.

        A caller that compares the telemetry numbers with the last it got sees what the ring dropped.

        Parameters
        ----------
        seq : int
            The last sequence number the caller has.
        timeout : float
            s.

        Returns
        -------
        seq : int
            The newest sequence number.
        telemetry : list of (int, dict)
            The telemetry newer than ``seq``, as (its number, message).
        events : list of (str, dict)
            The other events newer than ``seq``, as (kind, message).
        """
        with self._cond:
            self._cond.wait_for(lambda: self.seq > seq or self.closed, timeout)
            tel = [(n, m) for s, n, m in self.telemetry if s > seq]
            ev = [(k, m) for s, k, m in self.events if s > seq]
            return self.seq, tel, ev

    def close(self) -> None:
        """Wake every waiting stream for good."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()
