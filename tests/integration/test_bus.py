"""Bus: real zenoh sessions on loopback (distinct free ports, no multicast), real SQLite outbox."""
from __future__ import annotations

import json
import threading
import time

import pytest

from dt_kernel.config import validate
from dt_kernel.errors import ConfigError, StateError
from dt_runtime.fabric import BusConfig, MaintenanceConsumer, _open, load_bus_config
from dt_runtime.service.publisher import Bus
from dt_runtime.service.store import Store
from tests.support.loopback import free_port, wait_until

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]
PERIOD = 0.2  # fast republish for tests




def ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def robot_cfg(robot: str, consumer_port: int, **kw) -> BusConfig:
    return BusConfig(cell="c1", robot=robot, listen=[ep(free_port())],
                     connect=[ep(consumer_port)], republish_period_s=PERIOD,
                     close_timeout_s=3.0, **kw)


def consumer_cfg(port: int) -> BusConfig:
    return BusConfig(cell="c1", robot="maint", listen=[ep(port)], close_timeout_s=3.0)




def test_two_robots_one_consumer_requests_acked_and_outbox_empties(tmp_path):
    cport = free_port()
    with MaintenanceConsumer(consumer_cfg(cport)) as cons, \
            Store(tmp_path / "r1.db") as s1, Store(tmp_path / "r2.db") as s2, \
            Bus(robot_cfg("r1", cport), s1) as b1, Bus(robot_cfg("r2", cport), s2) as b2:
        i1 = b1.request_maintenance({"reason": "out_of_control", "cusum": 4.75})
        i2 = b2.request_maintenance({"reason": "out_of_control", "cusum": 5.0})
        assert s1.outbox_get(i1).payload["robot"] == "r1"  # written durably, with a uid
        assert len(s1.outbox_get(i1).payload["uid"]) == 32
        assert cons.wait_for(2, timeout=10)
        assert wait_until(lambda: not s1.outbox_pending() and not s2.outbox_pending(), 10)
        keys = sorted(r["key"] for r in cons.requests)
        assert keys == ["dt/c1/r1/maintenance/request", "dt/c1/r2/maintenance/request"]
        assert {r["robot"] for r in cons.requests} == {"r1", "r2"}
        assert all(r["reason"] == "out_of_control" for r in cons.requests)
        assert b1.acked == 1 and b2.acked == 1
        time.sleep(3 * PERIOD)  # acked: no more republishes, no duplicates recorded
        assert len(cons.requests) == 2 and i2 >= 1


def test_consumer_started_after_request_still_receives_it(tmp_path):
    cport = free_port()
    with Store(tmp_path / "r1.db") as s, Bus(robot_cfg("r1", cport), s) as bus:
        oid = bus.request_maintenance({"reason": "late consumer"})
        time.sleep(3 * PERIOD)  # published into the void a few times
        assert [o.id for o in s.outbox_pending()] == [oid]
        assert s.outbox_pending()[0].attempts >= 2
        with MaintenanceConsumer(consumer_cfg(cport)) as cons:
            assert cons.wait_for(1, timeout=15)
            assert wait_until(lambda: not s.outbox_pending(), 10)
            assert cons.requests[0]["id"] == oid


def test_restart_republishes_unacked_request(tmp_path):
    cport = free_port()
    db = tmp_path / "r1.db"
    with Store(db) as s:
        bus = Bus(robot_cfg("r1", cport), s)
        oid = bus.request_maintenance({"reason": "before crash"})
        assert bus.close(timeout=3)
    # daemon restart: new Store handle, new Bus; the consumer appears meanwhile
    with MaintenanceConsumer(consumer_cfg(cport)) as cons, Store(db) as s2:
        assert [o.id for o in s2.outbox_pending()] == [oid]
        with Bus(robot_cfg("r1", cport), s2):
            assert cons.wait_for(1, timeout=15)
            assert wait_until(lambda: not s2.outbox_pending(), 10)
        assert cons.requests[0]["reason"] == "before crash"


def test_vanished_peer_does_not_hang_the_publisher(tmp_path):
    cport = free_port()
    with Store(tmp_path / "r1.db") as s:
        bus = Bus(robot_cfg("r1", cport), s)
        cons = MaintenanceConsumer(consumer_cfg(cport))
        bus.request_maintenance({"n": 1})
        assert cons.wait_for(1, timeout=10)
        assert cons.close(timeout=3)
        t0 = time.monotonic()
        oid = bus.request_maintenance({"n": 2})
        for i in range(200):
            bus.publish_state({"state": "suspect", "i": i})
            bus.publish_correction({"dx": 1e-4, "i": i})
            bus.publish_telemetry({"i": i})
        assert time.monotonic() - t0 < 1.0
        time.sleep(3 * PERIOD)  # the worker keeps republishing into the void
        assert oid in [o.id for o in s.outbox_pending()]
        t0 = time.monotonic()
        assert bus.close(timeout=3)
        assert time.monotonic() - t0 < 3.5
        with pytest.raises(StateError):
            bus.publish_state({"x": 1})


def test_telemetry_publish_never_blocks_even_with_a_stalled_subscriber(tmp_path):
    cport = free_port()
    slow = _open(consumer_cfg(cport))
    got = []

    def stalled(sample):  # a deliberately bad subscriber: blocks zenoh's receive path
        got.append(1)
        time.sleep(0.05)

    sub = slow.declare_subscriber("dt/**/telemetry", stalled)
    try:
        with Bus(robot_cfg("r1", cport)) as bus:
            assert wait_until(lambda: bus._pub["telemetry"].matching_status, 10)
            payload = {"q": [0.1] * 6, "pad": "x" * 2000}
            t_all = time.monotonic()
            for _ in range(20_000):
                bus.publish_telemetry(payload)
            delivered_meanwhile, t_all = len(got), time.monotonic() - t_all
            # a publisher that waited for this subscriber (50 ms a sample) would need 1,000 s and
            # deliver every sample before its loop ended: no clock threshold near the real cost
            assert t_all < 500, t_all
            assert 0 < delivered_meanwhile < 10_000, delivered_meanwhile  # delivered some, dropped the rest
    finally:
        sub.undeclare()
        slow.close()


def test_state_and_correction_are_delivered_as_json(tmp_path):
    cport = free_port()
    listener = _open(consumer_cfg(cport))
    got: list[tuple[str, dict]] = []
    ev = threading.Event()

    def cb(sample):
        got.append((str(sample.key_expr), json.loads(sample.payload.to_bytes())))
        if len(got) >= 2:
            ev.set()

    sub = listener.declare_subscriber("dt/c1/r1/**", cb)
    try:
        with Bus(robot_cfg("r1", cport)) as bus:
            assert wait_until(lambda: bus._pub["state"].matching_status, 10)
            assert bus.publish_state({"state": "suspect", "evidence": {"cusum": 2.5}})
            assert bus.publish_correction({"dx": 1e-4, "dy": 0.0, "dz": -2e-4})
            assert ev.wait(10)
        assert dict(got)["dt/c1/r1/state"]["state"] == "suspect"
        assert dict(got)["dt/c1/r1/correction"]["dz"] == -2e-4
        with Bus(robot_cfg("r2", cport)) as no_store, pytest.raises(StateError):
            no_store.request_maintenance({})  # no store: no durability, so refused
    finally:
        sub.undeclare()
        listener.close()


def test_bad_ack_is_ignored(tmp_path):
    cport = free_port()
    with Store(tmp_path / "r1.db") as s, Bus(robot_cfg("r1", cport), s) as bus:
        oid = bus.request_maintenance({"x": 1})
        key = f"dt/c1/r1/maintenance/ack/{oid}"
        uid = s.outbox_get(oid).payload["uid"]
        bus._tasks.put(("ack", key, bus.signer.sign(key, {"id": oid, "uid": "forged", "t": time.time()})))
        bus._tasks.put(("ack", key, b"not json"))
        bus._tasks.put(("ack", key, b'{"id": ' + b"9" * 5000 + b', "uid": "u"}'))  # a huge integer
        bus._tasks.put(("ack", key, b"[" * 100_000 + b"]" * 100_000))  # deep nesting, and over the size cap
        bus._tasks.put(("ack", key, b'{"id": 1, "uid": "' + b"u" * 10 ** 6 + b'"}'))  # 1 MB
        bus._tasks.put(("ack", key, json.dumps({"id": oid, "uid": uid, "t": time.time()}).encode()))  # unsigned
        time.sleep(2 * PERIOD)
        assert [o.id for o in s.outbox_pending()] == [oid]
        assert bus.refused == 1 and "not signed" in bus.last_refused
        bus._tasks.put(("ack", key, bus.signer.sign(key, {"id": oid, "uid": uid, "t": time.time()})))
        assert wait_until(lambda: not s.outbox_pending(), timeout=5)  # the worker survived all of them


def test_configs_validate_and_map_onto_zenoh():
    cfg = load_bus_config(ROOT / "configs" / "bus.yaml")
    assert cfg.mode == "peer" and cfg.multicast_scouting is False
    assert all("127.0.0.1" in e for e in cfg.listen)
    assert cfg.key("maintenance/request") == "dt/cell1/r1/maintenance/request"
    ex = load_bus_config(ROOT / "configs" / "bus_tls_acl_example.yaml")
    z = ex.zenoh_config()  # zenoh itself accepts the mapped TLS and ACL sections
    assert json.loads(z.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(z.get_json("access_control"))
    assert acl["enabled"] is True and acl["policies"][0]["rules"] == ["with_twin_own_keys", "with_twin_subscriptions"]
    assert json.loads(cfg.zenoh_config().get_json("scouting/multicast/enabled")) is False


@pytest.mark.parametrize("data, key", [
    ({"robot": "r/1"}, "robot"),
    ({"listen": ["127.0.0.1:7447"]}, "listen"),
    ({"mode": "router"}, "mode"),
    ({"mode": "client"}, "<root>"),
    ({"tls": {"root_ca_certificate": "ca.pem"}}, "<root>"),  # TLS without a tls/ endpoint
    ({"listen": ["tls/127.0.0.1:1"], "tls": {"root_ca_certificate": "ca.pem",
                                             "listen_certificate": "c.pem"}}, "tls"),
    ({"access_control": {"rules": [], "subjects": [],
                         "policies": [{"rules": ["nope"], "subjects": []}]}}, "access_control"),
    ({"access_control": {"rules": [{"id": "r", "messages": ["shout"], "permission": "allow",
                                    "key_exprs": ["a"]}]}}, "access_control.rules.0.messages.0"),
])
def test_bad_bus_config_names_the_key(data, key):
    with pytest.raises(ConfigError) as ei:
        validate(BusConfig, data, "bus.yaml")
    assert ei.value.key == key or ei.value.key.startswith(key)
