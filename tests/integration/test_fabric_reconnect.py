"""A cell that starts while its router is down: its bus says `connecting`, the loop runs (rows are
stored, a fault pages into the outbox), and when the router comes the cell connects, says so, and
every maintenance request raised meanwhile reaches the plant's inbox, recorded once and acked.
Also the session opener on its own: retries in the background, stops at once when closed.
Waits are generous (wait_until); nothing is timed. Seeded: the simulated cell's scenario."""
from __future__ import annotations

import json
import sqlite3
import threading

import zenoh

from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.session import SessionOpener, close_session, open_session
from dt_runtime.plant.config import RouterConfig
from dt_runtime.plant.inbox import PlantInbox
from dt_runtime.plant.router import Router
from dt_runtime.service.daemon import Daemon, RuntimeConfig
from tests.support.loopback import free_port, wait_until

FAULT = {"at_s": 0.0, "joint_offset_rad": [0, 1.0e-3, 0, 0, 0, 0]}  # ~1 mm from the first tick: pages soon


def _client(port: int, cell: str, robot: str, **over) -> BusConfig:
    return BusConfig(cell=cell, robot=robot, mode="client", connect=[f"tcp/127.0.0.1:{port}"], **over)


def test_the_opener_retries_until_the_router_comes_and_stops_when_closed():
    port = free_port()
    seen: list[zenoh.Session] = []
    opener = SessionOpener(_client(port, "c1", "r1"), on_connected=seen.append)
    try:
        assert opener.state == "connecting" and opener.session is None and not seen
        assert wait_until(lambda: opener.attempts >= 3, 60), "no retries"
        with Router(RouterConfig(listen=[f"tcp/127.0.0.1:{port}"])):
            assert opener.wait(60) and wait_until(lambda: opener.state == "connected", 60)
            assert seen == [opener.session]  # the hook ran once, with the session
    finally:
        assert opener.close()
    assert opener.state == "closed" and opener.session is None
    idle = SessionOpener(_client(free_port(), "c1", "r2"))  # never connects: closing ends the retries
    assert idle.state == "connecting" and idle.close(5.0) and idle.state == "closed"


def _cfg(twin_dir, tmp_path, port: int) -> RuntimeConfig:
    return RuntimeConfig.model_validate({
        "twin": str(twin_dir), "store": str(tmp_path / "cell.sqlite"), "realtime": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml"),
                "faults": [FAULT]},
        "bus": {"cell": "c1", "robot": "r1", "mode": "client", "connect": [f"tcp/127.0.0.1:{port}"],
                "republish_period_s": 0.3, "health_period_s": 0.3}})


def _outbox_uids(path) -> set[str]:
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        return {json.loads(p)["uid"] for (p,) in db.execute("SELECT payload FROM outbox")}


def test_a_cell_started_before_its_router_catches_up_when_it_comes(twin_dir, tmp_path):
    port = free_port()
    d = Daemon(_cfg(twin_dir, tmp_path, port), CONFIGS)
    loop = threading.Thread(target=d.run, name="test-daemon-loop", daemon=True)
    router = inbox = watch = None
    health: list[dict] = []
    try:
        assert d.bus is not None and d.bus.state == "connecting"
        assert d.health()["bus"] == "connecting"
        text, fields = d.status_line()
        assert fields["bus"] == "connecting" and "bus connecting" in text
        loop.start()
        # The loop runs without a bus: rows are stored, and the fault pages into the outbox.
        assert wait_until(lambda: d.counters.ticks >= 20 and len(d.paging.requests) >= 1, 300), d.summary()
        assert d.bus.state == "connecting" and d.health()["bus"] == "connecting"
        assert d.store.outbox_pending(), "the request waits in the outbox"
        assert d.bus.dropped > 0 and d.bus.published == 0  # telemetry had nowhere to go

        # The router comes, then the plant's inbox and a watcher of the cell's health.
        router = Router(RouterConfig(listen=[f"tcp/127.0.0.1:{port}"]))
        inbox = PlantInbox(_client(port, "plant", "inbox"), str(tmp_path / "history.sqlite"))
        watch = open_session(_client(port, "plant", "watch"))
        sub = watch.declare_subscriber("dt/c1/r1/health", lambda s: health.append(json.loads(s.payload.to_bytes())))
        assert wait_until(lambda: d.bus.state == "connected", 120), d.bus.state
        assert wait_until(lambda: any(h.get("bus") == "connected" for h in health), 60), health[-3:]
        assert d.health()["bus"] == "connected" and "bus connecting" not in d.status_line()[0]

        # Nothing lost: stop producing, then every request the store ever raised is recorded once and acked.
        d.stop()
        loop.join(60)
        assert not loop.is_alive()
        assert wait_until(lambda: not d.store.outbox_pending(), 120), d.store.outbox_pending()
        raised = _outbox_uids(tmp_path / "cell.sqlite")
        rows = inbox.history.rows()
        assert raised and {r["uid"] for r in rows} == raised and len(rows) == len(raised)
        assert all((r["cell"], r["robot"]) == ("c1", "r1") for r in rows)
        sub.undeclare()
    finally:
        d.stop()
        if loop.is_alive():
            loop.join(60)
        d.close()
        if watch is not None:
            close_session(watch, 3.0)
        if inbox is not None:
            inbox.close()
        if router is not None:
            router.close()
