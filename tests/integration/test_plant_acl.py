"""The shipped plant ACL (configs/plant/plant_acl.yaml), unchanged but for certificate paths and
the port, on a router over real mutual TLS on loopback: each cell's requests reach the inbox and
its acks reach the cell; a cell that publishes under another cell's key is refused at the router
(the inbox never sees it, the request stays pending); the inbox asks every cell; hall A's operator
gets hall A's cell only, and nothing for a question to the whole plant (this test can fail)."""
from __future__ import annotations

import shutil

import pytest

from dt_runtime.common.paths import CONFIGS
from dt_runtime.fabric import BusConfig, MaintenanceConsumer
from dt_runtime.fabric.queries import QueryServer
from dt_runtime.plant.config import PlantConfig, load_plant_config
from dt_runtime.plant.router import Router
from dt_runtime.plant.status import plant_status
from dt_runtime.service.publisher import Bus
from dt_runtime.service.store import Store
from tests.support.loopback import free_port, wait_until
from tests.support.tls_certs import make_certs

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")

NAMES = {"router": "plant-router.plant.local", "a1": "hall-a-cell1.plant.local", "b1": "hall-b-cell1.plant.local",
         "maint": "maintenance.plant.local", "opa": "operator-hall-a.plant.local"}


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("plant-tls"), NAMES)


def _client(shipped: PlantConfig, certs, who: str, port: int, **bus) -> BusConfig:
    tls = shipped.bus.tls.model_copy(update={"root_ca_certificate": str(certs / "ca.pem"),
                                             "connect_certificate": str(certs / f"{who}.pem"),
                                             "connect_private_key": str(certs / f"{who}.key")})
    return shipped.bus.model_copy(update={"tls": tls, "connect": [f"tls/localhost:{port}"],
                                          "republish_period_s": 0.3, **bus})


def test_the_shipped_plant_acl_keeps_each_cell_to_its_own_keys(certs, tmp_path):
    shipped = load_plant_config(CONFIGS / "plant" / "plant_acl.yaml")
    port = free_port()
    rc = shipped.router
    router_cfg = rc.model_copy(update={"listen": [f"tls/localhost:{port}"], "tls": rc.tls.model_copy(update={
        "root_ca_certificate": str(certs / "ca.pem"), "listen_certificate": str(certs / "router.pem"),
        "listen_private_key": str(certs / "router.key"), "connect_certificate": str(certs / "router.pem"),
        "connect_private_key": str(certs / "router.key")})})
    opened = []
    try:
        opened.append(Router(router_cfg))
        stores = {n: Store(tmp_path / f"{n}.sqlite") for n in ("a1", "b1", "rogue")}
        opened += stores.values()
        a1 = Bus(_client(shipped, certs, "a1", port, cell="hall-a-cell1", robot="r1"), stores["a1"])
        b1 = Bus(_client(shipped, certs, "b1", port, cell="hall-b-cell1", robot="r1"), stores["b1"])
        # hall B's cell, with its own certificate, publishing under hall A's cell's key
        rogue = Bus(_client(shipped, certs, "b1", port, cell="hall-a-cell1", robot="r9"), stores["rogue"])
        opened += [a1, b1, rogue]
        for bus in (a1, b1):
            opened.append(QueryServer(bus.config, bus.session, {"status": lambda: {"status": "running"}}))
        inbox = MaintenanceConsumer(_client(shipped, certs, "maint", port))
        opened.append(inbox)

        ids = {n: b.request_maintenance({"reason": n}) for n, b in (("a1", a1), ("b1", b1), ("rogue", rogue))}
        assert wait_until(lambda: not stores["a1"].outbox_pending() and not stores["b1"].outbox_pending(), 30), \
            "a cell's own request or its ack was blocked"
        assert wait_until(lambda: stores["rogue"].outbox_get(ids["rogue"]).attempts >= 5, 30)
        assert sorted(r["key"] for r in inbox.requests) == ["dt/hall-a-cell1/r1/maintenance/request",
                                                             "dt/hall-b-cell1/r1/maintenance/request"]
        assert [i.id for i in stores["rogue"].outbox_pending()] == [ids["rogue"]]  # refused: never delivered

        whole = PlantConfig(bus=_client(shipped, certs, "maint", port), cells=shipped.cells)
        s = plant_status(whole, "dt/*/*", "status", timeout_s=3.0)
        assert s["answered"] == ["hall-a-cell1/r1", "hall-b-cell1/r1"] and s["missing"] == []
        operator = PlantConfig(bus=_client(shipped, certs, "opa", port, robot="operator"), cells=shipped.cells)
        assert plant_status(operator, "dt/hall-a-$*/*", "status", timeout_s=3.0)["answered"] == ["hall-a-cell1/r1"]
        assert plant_status(operator, "dt/*/*", "status", timeout_s=2.0)["answered"] == []
    finally:
        for o in reversed(opened):
            o.close()
