"""The dashboard's parts without a browser or a bus: the operators' token file, how it joins a
daemon's bus, the calibrated volume's edges, and the live state's bounds."""
from __future__ import annotations

import os

import numpy as np
import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.dashboard.feed import joining
from dt_runtime.dashboard.hub import Hub
from dt_runtime.dashboard.operators import load_operators
from dt_runtime.dashboard.scene import volume_edges
from dt_runtime.fabric import BusConfig
from dt_runtime.frames.volume import CalibratedVolume


def _private(path, text: str):
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.write(fd, text.encode())
    os.close(fd)
    return path


def test_operators_are_found_by_their_token_and_a_readable_file_is_refused(tmp_path):
    ops = load_operators(_private(tmp_path / "ops", "# who\nalice aaaaaaaaaaaaaaaa1\n\nbob  bbbbbbbbbbbbbbbb2\n"))
    assert ops.names == ["alice", "bob"]
    assert ops.who("bbbbbbbbbbbbbbbb2") == "bob" and ops.who("aaaaaaaaaaaaaaaa") is None and ops.who(None) is None
    (tmp_path / "ops").chmod(0o640)
    with pytest.raises(ConfigError, match="mode 0640"):
        load_operators(tmp_path / "ops")


@pytest.mark.parametrize("text, where", [("alice short\n", "line 1"), ("alice aaaaaaaaaaaaaaaa1 extra\n", "line 1"),
                                         ("a aaaaaaaaaaaaaaaa1\nb aaaaaaaaaaaaaaaa1\n", "line 2"),
                                         ("a aaaaaaaaaaaaaaaa1\na bbbbbbbbbbbbbbbb1\n", "line 2"),
                                         ("# nobody\n", "--token-file")])
def test_a_malformed_token_file_names_the_line_and_never_shows_a_token(tmp_path, text, where):
    with pytest.raises(ConfigError) as exc:
        load_operators(_private(tmp_path / "ops", text))
    assert f"key '{where}'" in str(exc.value)
    assert "aaaaaaaaaaaaaaaa1" not in str(exc.value) and "short" not in str(exc.value)


def test_the_dashboard_joins_the_daemon_where_it_listens():
    cfg = BusConfig(listen=["tcp/0.0.0.0:7447", "tcp/127.0.0.1:0"], connect=["tcp/10.1.2.3:7448"])
    j = joining(cfg)
    assert j.connect == ["tcp/127.0.0.1:7447", "tcp/10.1.2.3:7448"] and j.listen == ["tcp/127.0.0.1:0"]
    assert (j.cell, j.robot, j.auth) == (cfg.cell, cfg.robot, cfg.auth)
    with pytest.raises(ConfigError, match="bus.listen"):
        joining(BusConfig(listen=["tcp/127.0.0.1:0"]))  # a port only the daemon knows


def test_the_calibrated_volume_of_a_box_has_its_8_corners_and_12_edges():
    corners = np.array([[x, y, z] for x in (0.6, 1.2) for y in (-0.3, 0.3) for z in (0.2, 0.9)])
    pts, edges = volume_edges(CalibratedVolume.of_points(corners))
    assert len(pts) == 8 and len(edges) == 12
    P = np.array(pts)
    assert np.allclose(sorted(map(tuple, P.round(9))), sorted(map(tuple, corners)))
    lengths = sorted(float(np.linalg.norm(P[a] - P[b])) for a, b in edges)
    assert np.allclose(lengths, [0.6] * 4 + [0.6] * 4 + [0.7] * 4)


def test_the_live_state_stays_bounded_and_a_stream_sees_only_what_is_new():
    hub = Hub(telemetry_ring=100)
    for i in range(1000):
        hub.add_telemetry({"i": i})
    for i in range(80):
        hub.add_request({"id": i, "uid": f"u{i}", "group": "maintenance"})
    hub.add_request({"id": 100, "uid": "u79", "group": "operator"})  # another group's copy: the same request
    snap = hub.snapshot()
    assert len(hub.telemetry) == 100 and len(snap["requests"]) == 50
    assert snap["requests"][-1]["copies"] == {"maintenance": 79, "operator": 100}
    seq = snap["seq"]
    hub.add_telemetry({"i": 1000})
    hub.add_state({"src": "nominal", "dst": "suspect"})
    new_seq, tel, ev = hub.since(seq, 0.0)
    assert new_seq == seq + 2 and [m["i"] for _, m in tel] == [1000] and [k for k, _ in ev] == ["state"]
    assert tel[0][0] == 1001  # the telemetry's own number: a stream sees what the ring dropped


def test_a_plant_page_refuses_to_link_a_cell_to_itself():
    """`dashboards:` naming the plant page's own address would open the plant page again on a click."""
    from dt_runtime.dashboard.plant import check_links
    from dt_runtime.plant.config import PlantConfig

    cfg = PlantConfig.model_validate({"cells": ["c1/r1", "c2/r1"],
                                      "dashboards": {"c1/r1": "http://127.0.0.1:8766/",
                                                     "c2/r1": "http://localhost:8765/"}})
    with pytest.raises(ConfigError) as e:
        check_links(cfg, "plant.yaml", "127.0.0.1", 8765)
    assert "dashboards.c2/r1" in str(e.value) and "port of its own" in str(e.value)
    check_links(cfg, "plant.yaml", "127.0.0.1", 8770)  # another port: fine
    check_links(cfg, "plant.yaml", "10.1.0.5", 8765)  # another host: fine
    check_links(cfg, "plant.yaml", "127.0.0.1", 0)  # a free port is never a listed one


def test_a_return_to_nominal_by_an_operators_done_closes_the_requests_made_before_it():
    # `dt ack --store` publishes nothing of its own: the page learns of it from the daemon's
    # transition; before, the request stayed "waiting (sent 85x)" while dt status said acknowledged
    hub = Hub()
    hub.add_request({"id": 1, "uid": "a", "group": "maintenance", "t": 100.0, "attempt": 85})
    hub.add_state({"src": "maintenance_requested", "dst": "nominal", "t": 150.0, "rx": 1.0,
                   "evidence": {"acknowledged": True, "by": "kim", "note": "joint 2 re-referenced"}})
    hub.add_request({"id": 2, "uid": "b", "group": "maintenance", "t": 200.0, "attempt": 1})  # a later episode's
    a, b = hub.request("a"), hub.request("b")
    assert a is not None and b is not None
    assert a["done_by"] == "kim" and a["done_note"] == "joint 2 re-referenced"
    assert "done_by" not in b
    hub.add_state({"src": "suspect", "dst": "nominal", "t": 300.0, "evidence": {}})  # no operator: closes nothing
    assert "done_by" not in (hub.request("b") or {})
