"""The plant config at its boundary (errors name the key and what is allowed), the shipped
examples, and the query key a plant status sends."""
from __future__ import annotations

import pytest

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.plant.config import history_url, load_plant_config
from dt_runtime.plant.status import query_key


@pytest.mark.parametrize("name", ["plant.yaml", "hall_router.yaml", "cell_bus.yaml", "plant_acl.yaml"])
def test_the_shipped_plant_configs_load_and_map_onto_zenoh(name):
    cfg = load_plant_config(CONFIGS / "plant" / name)
    cfg.bus.zenoh_config()
    if cfg.router is not None:
        cfg.router.zenoh_config()


def test_the_shipped_plant_names_its_cells_and_a_hall_router_joins_the_plant_router():
    plant = load_plant_config(CONFIGS / "plant" / "plant.yaml")
    hall = load_plant_config(CONFIGS / "plant" / "hall_router.yaml")
    assert plant.cells == ["cell1/r1", "cell2/r1", "cell3/r1"] and plant.bus.mode == "client"
    assert hall.router.connect == plant.router.listen
    # the history is run-time state: out/plant/ of the clone, not beside the configs (and normalised)
    assert history_url(plant, CONFIGS / "plant") == str(CONFIGS.parent / "out" / "plant" / "plant_history.sqlite")


def test_the_shipped_cells_join_the_plant_router_and_each_links_its_own_dashboard():
    """The walkthrough of docs/plant.md: a shipped cell config per expected cell, a client of the
    plant's router (no listening port beside the router's), and the plant page (dt dashboard's
    default port) linking each cell to a page on a port of its own."""
    from urllib.parse import urlsplit

    from dt_runtime.cli.main import build_parser
    from dt_runtime.service.runtime_config import load_runtime_config

    plant = load_plant_config(CONFIGS / "plant" / "plant.yaml")
    for name in plant.cells:
        cell = load_runtime_config(CONFIGS / "plant" / f"{name.split('/')[0]}.yaml")
        assert f"{cell.bus.cell}/{cell.bus.robot}" == name
        assert cell.bus.mode == "client" and cell.bus.connect == plant.router.listen
    page_port = build_parser().parse_args(["dashboard", "--plant", "p.yaml"]).port
    ports = [urlsplit(url).port for url in plant.dashboards.values()]
    assert sorted(plant.dashboards) == sorted(plant.cells)
    assert len(set(ports)) == len(ports) and page_port not in ports, (page_port, ports)


def test_a_plain_bus_config_is_a_plant_of_that_bus(tmp_path):
    cfg = load_plant_config(CONFIGS / "bus.yaml")
    assert cfg.router is None and cfg.cells == [] and "history" not in cfg.model_fields_set


@pytest.mark.parametrize("text, key, seen", [
    ("cells: [c1]\n", "cells", "['c1']"),
    ("cells: [c1/r1, c1/r1]\n", "cells", "c1/r1"),
    ("router: {listen: []}\n", "router", "listen"),
    ("history: {url: 'mysql://db/plant'}\n", "history.url", "mysql"),
    ("bus: {mode: router}\n", "bus.mode", "router"),
    ("routers: {}\n", "routers", "{}"),
    ("dashboards: {c1: 'http://h:1/'}\n", "dashboards", "c1"),
    ("dashboards: {c1/r1: 'javascript:alert(1)'}\n", "dashboards", "javascript"),
])
def test_a_bad_plant_config_names_the_key(tmp_path, text, key, seen):
    p = tmp_path / "plant.yaml"
    p.write_text("bus: {}\n" + text if not text.startswith("bus") else text)
    with pytest.raises(ConfigError) as err:
        load_plant_config(p)
    assert err.value.key == key and seen in str(err.value) and str(p) in str(err.value)


def test_the_query_key_of_a_selector():
    assert query_key("dt/*/*", "status") == "dt/*/*/status"
    assert query_key("dt/hall-a-$*/*/", "health") == "dt/hall-a-$*/*/health"
    assert query_key("dt/c1/r1/health", "status") == "dt/c1/r1/health"  # a selector naming its kind
    with pytest.raises(DataError, match="unknown kind"):
        query_key("dt/*/*", "*")  # a wildcard kind would also reach the daemon's `correct` queryable
    with pytest.raises(DataError, match="unknown kind 'state'"):
        query_key("dt/*/*", "state")
    with pytest.raises(DataError, match="selector 'dt/\\*\\*\\*'"):
        query_key("dt/***", "status")
