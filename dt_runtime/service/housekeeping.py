"""The daemon's housekeeping thread (never the loop): operator actions picked up from the store,
`.../health` every `bus.health_period_s` and whenever the loop saw a change (`health_due`, on
`service.events.HealthDue`), an operator's action stored (`ActionQueued`: picked up at once),
store retention every `retention.every_s`, the operator's status line every `status_every_s`,
and the systemd watchdog (`service.sdnotify`: WATCHDOG=1 only while the loop ticks, so a wedged
loop gets restarted; never after STOPPING=1).
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from dt_kernel.errors import TwinError
from dt_runtime.service import sdnotify
from dt_runtime.service.events import ActionQueued, Events, HealthDue

log = logging.getLogger("dt.run")
status_log = logging.getLogger("dt.run.status")  # the operator's periodic one-line status


class Housekeeper:
    """One thread running the jobs below until `stop` is set; `poll_now` wakes it early, and so
    do `HealthDue` and `ActionQueued` on `events`. It polls at least every 0.5 s; a TwinError of
    a job (the store or bus down) is logged as a warning and retried, any other exception logged
    with its traceback: neither ends the thread.

    Parameters
    ----------
    stop : threading.Event
        The daemon's stop flag.
    events : Events
        The daemon's events (it subscribes to `HealthDue` and `ActionQueued`).
    take_actions : callable
        Queue the operator actions stored (`Paging.take_actions`), every poll.
    send_health : callable
        Publish `.../health` (`HealthReporter.send`).
    prune : callable
        Apply the store's retention (`Daemon.prune`).
    status_line : callable
        The operator's line and its fields (`StatusLine`), logged on `dt.run.status`.
    last_tick_mono : callable
        The loop's last tick on the monotonic clock, s: the watchdog is fed only while it is recent.
    health_period_s : float
        Period of `.../health`, s.
    prune_every_s : float
        Period of the retention, s.
    status_every_s : float or None
        Period of the status line, s; None: none.
    """

    def __init__(self, stop: threading.Event, events: Events, *, take_actions: Callable[[], None],
                 send_health: Callable[[], None], prune: Callable[[], Any], status_line: Callable[[], tuple[str, dict]],
                 last_tick_mono: Callable[[], float], health_period_s: float, prune_every_s: float,
                 status_every_s: float | None):
        self._stop = stop
        self._take_actions, self._send_health, self._prune = take_actions, send_health, prune
        self._status_line, self._last_tick_mono = status_line, last_tick_mono
        self._health_period, self._prune_every, self._status_every = health_period_s, prune_every_s, status_every_s
        self.poll_now = threading.Event()  # an operator action or a change arrived: poll at once
        self._health_due = threading.Event()  # the loop saw a change: publish it
        self._notify_lock = threading.Lock()  # STOPPING=1 is the last message systemd gets
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="dt-daemon-housekeeping", daemon=True)
        events.subscribe(HealthDue, lambda _event: self.health_due())
        events.subscribe(ActionQueued, lambda _event: self.poll_now.set())

    def start(self) -> None:
        """Start the thread (`dt-daemon-housekeeping`, a daemon thread)."""
        self._thread.start()

    def health_due(self) -> None:
        """The loop saw a change of health: publish it now (from this thread)."""
        self._health_due.set()
        self.poll_now.set()

    def stopping(self) -> None:
        """Tell systemd the service is stopping; no watchdog message after this one."""
        with self._notify_lock:
            self._stopping = True
            sdnotify.notify("STOPPING=1")

    def stop(self) -> None:
        """Set the stop flag, wake the thread and wait for it, at most 2 s."""
        self._stop.set()
        self.poll_now.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        period = self._health_period
        next_health = next_prune = time.monotonic()
        next_status = next_health + (self._status_every or 0.0)
        watchdog = sdnotify.watchdog_period()
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                self._take_actions()
                if now >= next_health or self._health_due.is_set():
                    self._health_due.clear()
                    next_health = now + period
                    self._send_health()
                if now >= next_prune:
                    next_prune = now + self._prune_every
                    self._prune()
                if self._status_every and now >= next_status:
                    next_status = now + self._status_every
                    text, fields = self._status_line()
                    status_log.info("%s", text, extra={"fields": fields})
            except TwinError as exc:  # the store or bus is down: keep trying
                log.warning("housekeeping: %s", exc)
            except Exception:  # noqa: BLE001 - a defect here must not end paging or the watchdog
                log.exception("housekeeping failed")
            # The watchdog is fed only while the loop ticks: a wedged loop gets restarted. Never
            # after STOPPING=1 (`stopping` takes the same lock to send it).
            with self._notify_lock:
                if watchdog and not self._stopping and time.monotonic() - self._last_tick_mono() < watchdog:
                    sdnotify.notify("WATCHDOG=1")
            self.poll_now.wait(min(0.5, period, watchdog / 2 if watchdog else 0.5, self._status_every or 0.5))
            self.poll_now.clear()
