"""`dt router`: the plant's Zenoh router, a session of the zenoh library in router mode.

The cells' daemons (`bus.mode: client`, `connect:` the router) and the plant's tools connect to
it; it routes puts, subscriptions and queries between them and applies its access control
(`router.access_control`: which cell may publish under which key). A router per hall connects to
the plant's router (`router.connect`). It keeps no state of its own: killed and restarted, the
clients reconnect and declare their subscriptions and queryables again, and what was in flight
is repaired by the cells' outboxes (maintenance requests are republished until acknowledged).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh

from dt_runtime.fabric.session import BusError, close_session, zenoh_errors
from dt_runtime.plant.config import RouterConfig

log = logging.getLogger("dt.router")


class Router:
    """A Zenoh router open on `config.listen` until `close()`."""

    def __init__(self, config: RouterConfig, close_timeout_s: float = 3.0):
        self.config = config
        self.close_timeout_s = close_timeout_s
        self.started = time.time()
        with zenoh_errors(f"cannot start the router on {config.listen}"):
            self._session = zenoh.open(config.zenoh_config())
        self.zid = str(self._session.zid())

    def info(self) -> dict[str, Any]:
        """Who is connected: the routers and the peers/clients it sees (zenoh ids), and its uptime."""
        with zenoh_errors("router info"):
            inf = self._session.info
            routers = [str(z) for z in inf.routers_zid()]
            peers = [str(z) for z in inf.peers_zid()]
        return {"zid": self.zid, "listen": self.config.listen, "connect": self.config.connect,
                "routers": routers, "peers": peers, "uptime_s": round(time.time() - self.started, 3)}

    def close(self) -> bool:
        """Close the router's session (in a helper thread, at most ``close_timeout_s``).

        Returns
        -------
        bool
            True if the close finished in time.
        """
        return close_session(self._session, self.close_timeout_s)

    def __enter__(self) -> Router:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def run_router(config: RouterConfig, stop: threading.Event, duration_s: float | None = None,
               on_ready=None) -> dict[str, Any]:
    """Run a router until ``stop`` is set (SIGTERM/SIGINT in ``dt router``) or ``duration_s`` passes.

    Parameters
    ----------
    config : RouterConfig
    stop : threading.Event
    duration_s : float or None
        s; None runs until ``stop``.
    on_ready : callable or None
        Called with the Router once it listens.

    Returns
    -------
    dict
        The router's last ``info()`` (zid and listen only if that fails).

    Raises
    ------
    BusError
        When the router cannot start.
    """
    with Router(config) as r:
        if on_ready is not None:
            on_ready(r)
        stop.wait(duration_s)
        try:
            return r.info()
        except BusError as exc:
            log.warning("%s", exc)
            return {"zid": r.zid, "listen": config.listen}
