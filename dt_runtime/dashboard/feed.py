"""The dashboard's side of the bus: it joins the cell's Zenoh network as one more peer, reads what
the daemon publishes for robot `dt/<cell>/<robot>` (telemetry, health, state, maintenance
requests: docs/bus.md) into the Hub, and publishes the operators' acknowledgements and
confirmations, signed with the service's key as `dt consume` and `dt ack --bus` do
(`fabric.consumer.publish_ack` / `publish_done`).

The same bus section as `dt run` (`joining`): the dashboard connects to the daemon's listen
endpoints and its connects (the plant's routers), with the same TLS and access-control settings,
and listens only on an ephemeral loopback port of its own. Zenoh callbacks only enqueue (a
bounded queue; overflow is counted, never waited on); one worker parses, checks and files.

With the key (`bus.auth.key_file`: needed to act, `--token-file`), health, state and requests
that do not carry the service's signature are refused and counted (anyone on the bus can publish
a 'state'); without it the dashboard can only read, and shows what it reads.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.common.safe_json import loads
from dt_runtime.dashboard.hub import Hub
from dt_runtime.dashboard.scene import Scene
from dt_runtime.fabric.auth import Signer
from dt_runtime.fabric.config import MAX_MESSAGE_BYTES, BusConfig
from dt_runtime.fabric.consumer import publish_ack, publish_done
from dt_runtime.fabric.session import (
    BusError,
    close_session,
    open_session,
    serve_tasks,
    shut_down,
    zenoh_errors,
)

log = logging.getLogger("dt.dashboard")
QUEUE = 10_000  # messages between the zenoh callbacks and the worker (80 s of telemetry at 125 Hz)
_WILDCARD_HOSTS = ("0.0.0.0", "[::]", "::")


def joining(cfg: BusConfig, source: str = "<runtime config>") -> BusConfig:
    """The bus config of another process of the same cell (the dashboard).

    It connects to the daemon's listen endpoints (a wildcard address as loopback; a peer daemon's
    only) and to its connects, and listens on an ephemeral port of the same protocol on loopback.

    Parameters
    ----------
    cfg : BusConfig
        The daemon's bus section.
    source : str
        Names the config in errors.

    Returns
    -------
    BusConfig

    Raises
    ------
    ConfigError
        When there is nothing to connect to (the daemon listens on port 0: a port only it knows).
    """
    connect: list[str] = []
    for ep in cfg.listen if cfg.mode == "peer" else []:
        proto, _, rest = ep.partition("/")
        host, sep, port = rest.rpartition(":")
        if proto == "unixsock-stream":
            connect.append(ep)
            continue
        if not sep or port in ("0", ""):
            continue
        connect.append(f"{proto}/{'127.0.0.1' if host in _WILDCARD_HOSTS else host}:{port}")
    connect += [e for e in cfg.connect if e not in connect]
    if not connect:
        raise ConfigError(source, "bus.listen", cfg.listen,
                          "an endpoint with a fixed port (e.g. tcp/127.0.0.1:7447) or bus.connect to a router: "
                          "the dashboard joins the daemon there (or give --bus with a config of its own)")
    proto = next((e.partition("/")[0] for e in cfg.listen if e.partition("/")[0] in ("tcp", "tls", "quic")), "tcp")
    listen = [f"{proto}/127.0.0.1:0"] if cfg.mode == "peer" else []
    return cfg.model_copy(update={"listen": listen, "connect": connect})


def _vec(msg: dict[str, Any], key: str, n: int | None = 3) -> list[float] | None:
    v = msg.get(key)
    if not isinstance(v, list) or (n is not None and len(v) != n):
        return None
    if not all(x is None or (isinstance(x, (int, float)) and not isinstance(x, bool)) for x in v):
        return None
    return v


class BusFeed:
    """Subscribes to one robot's keys, files what arrives in `hub`, publishes acks and dones."""

    def __init__(self, cfg: BusConfig, hub: Hub, scene: Scene, signer: Signer | None = None,
                 group: str = "maintenance"):
        self.cfg, self.hub, self.scene, self.signer, self.group = cfg, hub, scene, signer, group
        self.prefix = f"dt/{cfg.cell}/{cfg.robot}"
        self.dropped = 0  # messages lost because the worker fell behind (the queue was full)
        self._tasks: queue.Queue = queue.Queue(maxsize=QUEUE)
        self._closed = False
        self._session = open_session(cfg)
        try:
            self._subs = []
            for kind in ("telemetry", "health", "state", "maintenance/request"):
                key = f"{self.prefix}/{kind}"
                with zenoh_errors(f"cannot subscribe to {key}"):
                    self._subs.append(self._session.declare_subscriber(key, self._callback(kind)))
        except BusError:
            close_session(self._session, cfg.close_timeout_s)
            raise
        self._worker = threading.Thread(target=self._run, name="dashboard-feed", daemon=True)
        self._worker.start()

    def _callback(self, kind: str):
        def on_sample(sample: Any) -> None:
            try:
                self._tasks.put_nowait((kind, str(sample.key_expr), sample.payload.to_bytes(), time.time()))
            except queue.Full:
                self.dropped += 1
        return on_sample

    def _run(self) -> None:
        serve_tasks(self._tasks, lambda task: self._handle(*task),
                    lambda task: f"dashboard: message on {task[1]} not handled", log)

    def _handle(self, kind: str, key: str, raw: bytes, rx: float) -> None:
        try:
            msg = loads(raw, f"message on {key}", max_bytes=MAX_MESSAGE_BYTES)
        except DataError as exc:
            log.warning("dashboard: %s", exc)
            return
        if not isinstance(msg, dict):
            return
        if kind == "telemetry":
            self.hub.add_telemetry(self._telemetry(msg, rx))
            return
        if self.signer is not None:
            why = self.signer.check(key, msg, fresh=False)
            if why:
                self.hub.refused()
                log.warning("dashboard: %s on %s refused: %s", kind, key, why)
                return
        msg.pop("sig", None)
        msg["rx"] = rx
        if kind == "health":
            self.hub.add_health(msg)
        elif kind == "state":
            self.hub.add_state(msg)
        else:
            self.hub.add_request(msg)

    def _telemetry(self, msg: dict[str, Any], rx: float) -> dict[str, Any]:
        """What the page draws of one telemetry message (m, robot frame): the arm through the
        twin's kinematics at the controller's joint angles, the points, Eq. 17's t, U."""
        q = _vec(msg, "q", None)
        t = msg.get("t")
        return {"t": t if isinstance(t, (int, float)) else None, "rx": rx,
                "target": _vec(msg, "target"), "command": _vec(msg, "command"), "measured": _vec(msg, "measured"),
                "U": _vec(msg, "U"), "t_stat": _vec(msg, "t_stat"), "passed": msg.get("passed") is True,
                "state": str(msg.get("state")), "inside": msg.get("inside"), "arm": self.scene.arm(q)}

    # --- the operators' actions ------------------------------------------------------------------
    def ack(self, oid: int, uid: str) -> str:
        """Acknowledge delivery of this dashboard's group's copy of a request (signed with the bus key).

        Parameters
        ----------
        oid : int
            The copy's id.
        uid : str
            The request's uid.

        Returns
        -------
        str
            The key it was put on.

        Raises
        ------
        BusError
            When the put fails.
        """
        assert self.signer is not None
        return publish_ack(self._session, self.signer, self.prefix, oid, uid, self.group)

    def done(self, oid: int, uid: str, by: str, note: str) -> str:
        """Tell the twin the maintenance a request asked for is done (signed with the bus key).

        Parameters
        ----------
        oid : int
            The request copy's id.
        uid : str
            The request's uid.
        by : str
            Who did it (the operator the token named).
        note : str
            Why, or what was done.

        Returns
        -------
        str
            The key it was put on.

        Raises
        ------
        BusError
            When the put fails.
        """
        assert self.signer is not None
        return publish_done(self._session, self.signer, self.prefix, oid, uid, by, note)

    def close(self) -> bool:
        """Stop the worker and close the session (once), within the bus's close timeout.

        Returns
        -------
        bool
            True when both are down.
        """
        if self._closed:
            return True
        self._closed = True

        def wake() -> None:
            try:
                self._tasks.put_nowait(None)
            except queue.Full:  # the worker drains it: make room for the stop
                try:
                    self._tasks.get_nowait()
                except queue.Empty:
                    pass
                self._tasks.put_nowait(None)
        return shut_down(self._session, self._worker, wake, self.cfg.close_timeout_s)
