"""The shipped TLS/ACL example (configs/bus_tls_acl_example.yaml), unchanged, over real mutual
TLS on loopback with certificates made here: the shipped consumer receives and acknowledges the
twin's maintenance request; a peer with a certificate of the same CA but another name can
neither read requests nor acknowledge one. (The first version's rule, which does not cover the
consumer's subscription, is not tested: whether a request still reached the consumer under it
depended on zenoh's timing, so no test can assert it.) Zenoh applies the ACL on each node to the
messages it exchanges with a peer, by the rules of that peer's subject (the common name of its
certificate), so both nodes load the same file."""
from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest

from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig, MaintenanceConsumer, load_bus_config
from dt_runtime.service.publisher import Bus
from dt_runtime.service.store import Store
from tests.support.loopback import free_port as _free_port
from tests.support.loopback import wait_until as _wait

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None,
                                reason="needs the openssl command to make certificates")




@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("tls")

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=cobot-dt test CA")
    for name, cn in (("twin", "twin-r1.plant.local"), ("maint", "maintenance-host.plant.local"),
                     ("rogue", "rogue.plant.local")):
        (d / f"{name}.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                                       "extendedKeyUsage=serverAuth,clientAuth\n")
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
            "-subj", f"/CN={cn}")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext")
    return d


def _peer(shipped: BusConfig, certs: Path, who: str, listen: list[str], connect: list[str],
          robot: str | None = None) -> BusConfig:
    """The shipped config with only this peer's certificate paths and endpoints replaced."""
    tls = shipped.tls.model_copy(update={
        "root_ca_certificate": str(certs / "ca.pem"),
        "listen_certificate": str(certs / f"{who}.pem"), "listen_private_key": str(certs / f"{who}.key"),
        "connect_certificate": str(certs / f"{who}.pem"), "connect_private_key": str(certs / f"{who}.key")})
    return shipped.model_copy(update={"tls": tls, "listen": listen, "connect": connect,
                                      "republish_period_s": 0.3, **({"robot": robot} if robot else {})})




def _run(certs: Path, tmp_path: Path, shipped: BusConfig, consumer_cert: str = "maint"):
    port = _free_port()
    twin_cfg = _peer(shipped, certs, "twin", [f"tls/localhost:{port}"], [])
    cons_cfg = _peer(shipped, certs, consumer_cert, [f"tls/localhost:{_free_port()}"], [f"tls/localhost:{port}"],
                     robot="maint")
    store = Store(tmp_path / "dt.sqlite")
    bus = Bus(twin_cfg, store)
    cons = MaintenanceConsumer(cons_cfg)
    return store, bus, cons


def _ours(consumer: MaintenanceConsumer, uid: str) -> list[dict]:
    """The requests of this test's twin the consumer received (by the request's uid): a session of
    an earlier test whose close a loaded machine abandoned may still republish its own request."""
    return [r for r in list(consumer.requests) if str(r.get("uid")) == uid]


def test_the_shipped_consumer_receives_and_acknowledges_under_the_shipped_acl(certs, tmp_path):
    shipped = load_bus_config(CONFIGS / "bus_tls_acl_example.yaml")
    store, bus, cons = _run(certs, tmp_path, shipped)
    try:
        oid = bus.request_maintenance({"reason": "acl test"})
        uid = store.outbox_get(oid).payload["uid"]
        assert _wait(lambda: _ours(cons, uid), 30), "the consumer received nothing: the ACL blocks it"
        (req,) = _ours(cons, uid)
        assert req["id"] == oid and req["key"] == "dt/cell1/r1/maintenance/request"
        assert _wait(lambda: not store.outbox_pending(), 30), "the ack did not reach the twin"
    finally:
        cons.close()
        bus.close()
        store.close()


def test_a_peer_of_another_name_can_neither_read_nor_acknowledge(certs, tmp_path):
    shipped = load_bus_config(CONFIGS / "bus_tls_acl_example.yaml")
    store, bus, rogue = _run(certs, tmp_path, shipped, consumer_cert="rogue")
    try:
        oid = bus.request_maintenance({"reason": "acl test"})
        uid = store.outbox_get(oid).payload["uid"]
        time.sleep(3.0)  # several republish periods
        assert not _ours(rogue, uid)  # nothing of this twin came through
        rogue.ack("dt/cell1/r1", oid, uid)  # it knows the uid: still refused
        time.sleep(1.5)
        assert [i.id for i in store.outbox_pending()] == [oid]
    finally:
        rogue.close()
        bus.close()
        store.close()
