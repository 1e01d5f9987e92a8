"""`.../health` of one daemon, and the read-only status view the plant's queries read.

`HealthReporter` builds the payload (status and why from the supervisor, the escalation, the
counters, the outbox, each driver's own counters, the bus's refusals, a path's stream state),
marks it due on a change (`changed`, no I/O: the loop calls it every tick; a recorded
`Transition` forces it) by emitting `HealthDue`, and sends it (`send`, from the housekeeping
thread). `CellStatus` is what `service.answers` reads: health, requests, tests, nothing else.
`StatusLine` is the operator's one line (`dt run --status-every`), written by the housekeeping
thread.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dt_runtime.service.counters import Counters
from dt_runtime.service.escalation import Escalator
from dt_runtime.service.events import Events, HealthDue, Transition
from dt_runtime.service.path_run import PathStreamer
from dt_runtime.service.publisher import Bus
from dt_runtime.service.rows import shown_time
from dt_runtime.service.store import OutboxItem, Store, StoreError
from dt_runtime.twin.bounds import Corrected


class HealthReporter:
    """The `.../health` payload and its publication.

    Parameters
    ----------
    status : callable
        (running | degraded | halted, why), no I/O (`Supervisor.status`).
    escalator, counters, store :
        The daemon's machine, counters and store (read only).
    now : callable
        The daemon's clock (s).
    inst : Instruments
        The drivers (their own `counters()`, where they keep them).
    bus : Bus or None
        Where health is sent (None: not published).
    events : Events
        `HealthDue` is emitted on it; a `Transition` on it forces health.
    stream : callable
        The path's stream state (a dict), or None for a point program.
    stated_u : callable
        The stated U's adaptive scale (`AdaptiveCoverage.health`), or None.
    """

    def __init__(self, status: Callable[[], tuple[str, str | None]], escalator: Escalator, counters: Counters,
                 store: Store, now: Callable[[], float], inst: Any, bus: Bus | None, events: Events,
                 stream: Callable[[], dict[str, Any] | None],
                 stated_u: Callable[[], dict[str, Any] | None] = lambda: None):
        self.status, self.escalator, self.counters, self.store = status, escalator, counters, store
        self.stated_u = stated_u
        self.now, self.inst, self.bus, self.events, self.stream = now, inst, bus, events, stream
        self._key: tuple | None = None
        events.subscribe(Transition, lambda _event: self.changed(force=True))

    def health(self) -> dict[str, Any]:
        """What `.../health` carries: running / degraded / halted and why, the escalation state,
        the last tick, and the counters an operator looks at first."""
        status, reason = self.status()
        esc, stream, stated_u = self.escalator, self.stream(), self.stated_u()
        return {"status": status, "reason": reason, "escalation": esc.state, "episode": esc.episode,
                # an open re-referencing offer: its evidence (shift in mm and mrad, p-values, n)
                **({"rereference_offer": esc.offer} if esc.offer is not None else {}),
                **self.counters.health(self.now()),
                "outbox_pending": self._pending_count(), "drivers": self._driver_counters(),
                # acks and 'done's on the bus without the service's signature: refused, not recorded
                "bus_refused": self.bus.refused if self.bus else 0,
                "bus_last_refused": self.bus.last_refused if self.bus else None,
                "bus": self.bus.state if self.bus else "off",  # connecting (no router yet), connected
                "pid": os.getpid(), "t": time.time(),
                **({"stream": stream} if stream is not None else {}),
                **({"stated_u": stated_u} if stated_u is not None else {})}

    def changed(self, force: bool = False) -> None:
        """Emit `HealthDue` on a change of status, reason or escalation state (checked without
        I/O: the loop calls it every tick) or when `force`d.

        Parameters
        ----------
        force : bool
            Emit even if nothing changed.
        """
        key = (*self.status(), self.escalator.state)
        if not force and key == self._key:
            return
        self._key = key
        self.events.emit(HealthDue())

    def send(self) -> None:
        """Publish the health now (from the housekeeping thread); nothing without a bus.

        Raises
        ------
        StateError
            The bus is closed.
        """
        if self.bus:
            self.bus.publish_health(self.health())

    def _driver_counters(self) -> dict[str, dict]:
        """Each driver's own counters, for those that keep them (`counters()`, no I/O: an RTDE
        link's drops and reconnections, NatNet frames lost and late): a fault the driver
        recovered from by itself still shows on `.../health`."""
        out: dict[str, dict] = {}
        for kind in ("robot", "tracker", "camera"):
            counters = getattr(getattr(self.inst, kind, None), "counters", None)
            if callable(counters):
                try:
                    out[kind] = counters()
                except Exception as exc:  # noqa: BLE001 - a report must not fail on a driver's defect
                    out[kind] = {"error": str(exc)}
        return out

    def _pending_count(self) -> int | None:
        try:
            return len(self.store.outbox_pending())
        except StoreError:
            return None


@dataclass(frozen=True)
class CellStatus:
    """The read-only view of one daemon that its query answers read (`service.answers.StatusView`)."""

    reporter: HealthReporter
    store: Store
    counters: Counters
    escalator: Escalator

    def health(self) -> dict[str, Any]:
        """What `.../health` carries now."""
        return self.reporter.health()

    def open_requests(self) -> list[OutboxItem]:
        """Outbox entries no consumer acknowledged."""
        return self.store.outbox_pending()

    def latest_requests(self, limit: int) -> list[dict[str, Any]]:
        """The latest maintenance requests, acknowledged or not, newest first.

        Parameters
        ----------
        limit : int
            At most this many.

        Returns
        -------
        list of dict
            As `Store.requests` gives them.
        """
        return self.store.requests(limit=limit)

    def latest_tests(self, limit: int) -> list[dict[str, Any]]:
        """The latest Eq. 17 tests, newest first.

        Parameters
        ----------
        limit : int
            At most this many.

        Returns
        -------
        list of dict
            As `Store.last_t_tests` gives them.
        """
        return self.store.last_t_tests(limit)

    def t_test_failures(self) -> int:
        """Eq. 17 tests failed since the start."""
        return self.counters.failures

    def escalation(self) -> str:
        """The escalation's state."""
        return self.escalator.state


class StatusLine:
    """The operator's one line: ticks and their rate since the last line, status and escalation
    state, then where a path's stream is, or the time of the last command (`last`, set by the
    loop) and the expanded uncertainty (95 %) of the position it reached.

    Parameters
    ----------
    status : callable
        (running | degraded | halted, why), no I/O (`Supervisor.status`).
    counters : Counters
        The daemon's counters.
    escalator : Escalator
        The machine (its state).
    path : PathStreamer or None
        A path program's streamer (its state), None for a point program.
    bus : Bus or None
        The daemon's bus (its connection state), None when it publishes nothing.
    """

    def __init__(self, status: Callable[[], tuple[str, str | None]], counters: Counters, escalator: Escalator,
                 path: PathStreamer | None, bus: Bus | None):
        self.status, self.counters, self.escalator, self.path, self.bus = status, counters, escalator, path, bus
        self.last: tuple[float, Corrected] | None = None  # (t, the last command sent)
        self._mark = (time.monotonic(), 0)  # (when, ticks) of the last line: its rate

    def __call__(self) -> tuple[str, dict[str, Any]]:
        """The line now, and the same as fields (the log's JSON)."""
        now, ticks = time.monotonic(), self.counters.ticks
        then, before = self._mark
        self._mark = (now, ticks)
        rate = (ticks - before) / (now - then) if now > then else 0.0
        status, reason = self.status()
        failures, state = self.counters.failures, self.escalator.state
        bus = self.bus.state if self.bus else "off"
        f: dict[str, Any] = {"ticks": ticks, "rate_hz": round(rate, 2), "status": status, "reason": reason,
                             "escalation": state, "t_test_failures": failures, "bus": bus}
        text = f"{ticks} ticks ({rate:.1f}/s), {status}" + (f" ({reason})" if reason else "") + \
            f", escalation {state}, Eq. 17 failed {failures}" + (f", bus {bus}" if bus == "connecting" else "")
        offer = self.escalator.offer
        if offer is not None:  # the operator's cue: what was fitted and how to apply it
            f["rereference_offer"] = offer
            text += (f", session shift {'/'.join(f'{v:+.3f}' for v in offer['translation_mm'])} mm "
                     f"{'/'.join(f'{v:+.3f}' for v in offer['rotation_mrad'])} mrad: "
                     "re-reference (dt ack --rereference)")
        if self.path is not None:  # a path: where the stream is, not a last command
            st = self.path.state
            f |= {"stream": st.state, "pass": st.pass_started, "next": st.next, "n": st.n}
            return text + f", path {st.state}, pass {st.pass_started}, at {self.path.plan.where(st.next)}", f
        if self.last is None:
            return text + ", no command yet", f
        t, corr = self.last
        U = [round(float(u) * 1e3, 4) for u in corr.U_tcp] if np.all(np.isfinite(corr.U_tcp)) else None
        f |= {"last_t": t, "U95_mm": U, "inside": corr.inside}
        return (text + f", last command {shown_time(t)}, U95 "
                + ("x/y/z " + "/".join(f"{u:.3f}" for u in U) + " mm" if U else "none (sent uncorrected)")
                + ("" if corr.inside else " (outside the calibrated volume)")), f
