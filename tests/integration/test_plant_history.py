"""The plant's maintenance history on SQLite and on a real PostgreSQL server (pgserver), and the
inbox that records a request before it acknowledges it: through a router on loopback, a cell's
Bus with its outbox; a failing history commit leaves the request unacknowledged, and the cell's
next republication brings it again (at least once, exactly one row)."""
from __future__ import annotations

import pytest

from dt_runtime.fabric import BusConfig
from dt_runtime.plant.config import RouterConfig
from dt_runtime.plant.history import SCHEMA, open_history
from dt_runtime.plant.inbox import PlantInbox
from dt_runtime.plant.router import Router
from dt_runtime.service.publisher import Bus
from dt_runtime.service.store import Store, StoreError
from tests.support.loopback import free_port, wait_until
from tests.support.postgres import postgres_server


@pytest.fixture(scope="module")
def pg_url():
    with postgres_server() as url:
        yield url


@pytest.fixture(params=["sqlite", "postgres"])
def history_url(request, tmp_path):
    if request.param == "sqlite":
        return str(tmp_path / "history.sqlite")
    import psycopg

    url = request.getfixturevalue("pg_url")
    with psycopg.connect(url, autocommit=True) as c:  # each test its own table
        c.execute("DROP TABLE IF EXISTS maintenance_requests")
    return url


def _req(uid: str, cell: str = "c1", group: str = "maintenance", attempt: int = 1) -> dict:
    return {"id": 7, "uid": uid, "group": group, "kind": "t_test", "episode": 2, "state": "maintenance_requested",
            "reason": "repeated Eq. 17 t-test failures", "created": 1700000000.5, "attempt": attempt,
            "evidence": {"cusum": 6.75}, "key": f"dt/{cell}/r1/maintenance/request", "sig": "hmac-sha256:00"}


def test_the_history_keeps_one_row_per_request_and_group(history_url):
    with open_history(history_url) as h:
        assert h.record(_req("u1"), 10.0) is True
        assert h.record(_req("u1", attempt=2), 11.0) is False  # a republished copy: no second row
        assert h.record(_req("u1", group="mes"), 12.0) is True  # another group's copy is its own row
        assert h.record(_req("u1", cell="c2"), 13.0) is True  # the same uid from another cell
        assert h.count() == 3
        assert h.seen("maintenance") == {("dt/c1/r1", "u1"), ("dt/c2/r1", "u1")}
        first = [r for r in h.rows() if r["cell"] == "c1" and r["grp"] == "maintenance"][0]
        assert (first["attempt"], first["received"], first["episode"], first["request_id"]) == (1, 10.0, 2, 7)
        assert first["payload"]["evidence"] == {"cusum": 6.75}
    with open_history(history_url) as again:  # reopened: the rows are there
        assert again.count() == 3


def test_an_unreachable_postgres_is_a_store_error_naming_it_without_the_password():
    with pytest.raises(StoreError, match=r"postgresql://cobot@127\.0\.0\.1:1/plant") as err:
        open_history("postgresql://cobot:secret@127.0.0.1:1/plant?connect_timeout=2")
    assert "secret" not in str(err.value)


def test_the_inbox_records_before_it_acks_through_a_router(history_url, tmp_path):
    port = free_port()
    router = Router(RouterConfig(listen=[f"tcp/127.0.0.1:{port}"]))
    client = {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}
    store = Store(tmp_path / "cell.sqlite")
    bus = Bus(BusConfig(cell="c1", robot="r1", republish_period_s=0.2, **client), store)
    inbox = PlantInbox(BusConfig(cell="plant", robot="inbox", **client), history_url)
    try:
        oid = bus.request_maintenance({"reason": "first", "kind": "t_test", "episode": 1})
        assert wait_until(lambda: not store.outbox_pending(), 30), "not acknowledged"
        assert inbox.history.count() == 1 and inbox.recorded == 1
        uid = store.outbox_get(oid).payload["uid"]
        assert inbox.history.seen("maintenance") == {("dt/c1/r1", uid)}

        # The history cannot commit: the request is not acked and not remembered ...
        with inbox.history._lock:
            inbox.history._db.execute("DROP TABLE maintenance_requests")
        oid2 = bus.request_maintenance({"reason": "second", "kind": "halt", "episode": 2})
        assert wait_until(lambda: store.outbox_get(oid2).attempts >= 3, 30)
        assert [i.id for i in store.outbox_pending()] == [oid2]
        assert len(inbox.requests) == 1
        # ... and when it can again, the next republication is recorded once and acked.
        with inbox.history._lock:
            inbox.history._db.execute(SCHEMA)
        assert wait_until(lambda: not store.outbox_pending(), 30)
        assert inbox.history.count() == 1 and [r["reason"] for r in inbox.history.rows()] == ["second"]
    finally:
        inbox.close()
        bus.close()
        store.close()
        router.close()


def test_dt_consume_with_a_plant_config_records_through_dt_router(tmp_path):
    """The commands as an operator runs them: `dt router` and `dt consume --bus plant.yaml` (its
    history: a SQLite file beside the config), a cell's Bus sending one request."""
    import json
    import subprocess
    import sys

    port = free_port()
    plant = tmp_path / "plant.yaml"
    plant.write_text(f"router: {{listen: ['tcp/127.0.0.1:{port}']}}\n"
                     f"bus: {{cell: plant, robot: inbox, mode: client, connect: ['tcp/127.0.0.1:{port}']}}\n"
                     "history: {url: history.sqlite}\n")
    dt = [sys.executable, "-m", "dt_runtime.cli.main"]
    bad = subprocess.run([*dt, "router", "--config", str(tmp_path / "none.yaml"), "--json"], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2 and json.loads(bad.stdout)["type"] == "ConfigError"
    router = subprocess.Popen([*dt, "router", "--config", str(plant), "--duration", "120"], stderr=subprocess.PIPE,
                              text=True)
    try:
        assert "dt router: listening on" in router.stderr.readline()
        consume = subprocess.Popen([*dt, "consume", "--bus", str(plant), "--count", "1", "--duration", "60", "--json"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert "listening on dt/**/maintenance/request, history" in consume.stderr.readline()
        store = Store(tmp_path / "cell.sqlite")
        bus = Bus(BusConfig(cell="c7", robot="r1", mode="client", connect=[f"tcp/127.0.0.1:{port}"],
                            republish_period_s=0.2), store)
        try:
            bus.request_maintenance({"reason": "cli", "kind": "t_test", "episode": 1})
            out, _ = consume.communicate(timeout=60)
            assert wait_until(lambda: not store.outbox_pending(), 30)
        finally:
            bus.close()
            store.close()
        lines = out.strip().splitlines()
        assert json.loads(lines[0])["cell"] == "c7"
        summary = json.loads(lines[-1])
        assert (summary["recorded"], summary["history_rows"]) == (1, 1)
        assert summary["history"] == str(tmp_path / "history.sqlite")
    finally:
        router.terminate()
        router.wait(30)
