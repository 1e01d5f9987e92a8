"""The `correct` request-reply on a real Zenoh session on loopback: the cell's program asks the
twin for a corrected command and gets the command, its U and the calibrated-volume flag."""

import numpy as np
import pytest

from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.correction_client import request_correction
from dt_runtime.fabric.session import close_session, open_session
from dt_runtime.service.correction_server import CorrectionServer
from dt_runtime.twin.bounds import CorrectionFault, Guard, Limits
from dt_runtime.twin.twin import Twin
from tests.support.loopback import free_port


@pytest.fixture
def served(quick_demo):
    twin = Twin.load(quick_demo[2] / "model")
    port = free_port()
    cfg = BusConfig(cell="c1", robot="r1", listen=[f"tcp/127.0.0.1:{port}"])
    server = CorrectionServer(Guard(twin, Limits()), cfg)
    client = open_session(BusConfig(cell="c1", robot="prog", listen=[f"tcp/127.0.0.1:{free_port()}"],
                                    connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        yield twin, server, client, cfg.key("correct")
    finally:
        close_session(client, 3.0)
        assert server.close(3.0)


def ask(client, key, target_mm, speed_mm_s, **kw):
    for _ in range(20):  # the first query may go out before the peers have met
        try:
            return request_correction(client, key, target_mm, speed_mm_s, timeout_s=1.0, **kw)
        except CorrectionFault:
            raise
        except Exception:  # noqa: BLE001 - BusError: no reply yet
            continue
    raise AssertionError("no reply from the correction server")


def test_a_correct_request_is_answered_as_the_twin_corrects(served):
    twin, server, client, key = served
    r = ask(client, key, [900.0, 0.0, 550.0], 500.0, request_id="p1")
    c = twin.correct(np.array([0.9, 0.0, 0.55]), 0.5)
    assert r["id"] == "p1" and r["inside"] is True and r["distance_mm"] < 0
    assert np.allclose(r["command_mm"], c.command * 1e3, atol=1e-9)
    assert np.allclose(r["U_mm"], c.U * 1e3, atol=1e-9)
    assert np.allclose(r["correction_mm"], (c.command - c.target) * 1e3, atol=1e-9)


@pytest.mark.parametrize("target, speed, message", [
    ([900.0, 0.0], 500.0, "3 numbers"),
    ([900.0, float("nan"), 550.0], 500.0, "not a finite 3-vector"),
    ([5000.0, 0.0, 550.0], 500.0, "outside the workspace"),
    ([900.0, 0.0, 550.0], 1e9, "speed"),
])
def test_refused_requests_get_the_reason_and_the_server_goes_on(served, target, speed, message):
    twin, server, client, key = served
    ask(client, key, [900.0, 0.0, 550.0], 500.0)  # the peers have met
    with pytest.raises(CorrectionFault, match=message):
        request_correction(client, key, target, speed, timeout_s=2.0)
    assert ask(client, key, [900.0, 0.0, 550.0], 500.0)["inside"]  # still serving
    assert server.refused >= 1 and server.served >= 2


def test_malformed_payloads_are_refused_without_reaching_the_model(quick_demo):
    twin = Twin.load(quick_demo[2] / "model")
    server = CorrectionServer.__new__(CorrectionServer)  # answer() alone: no session needed
    server.corrector, server.refused, server.served = Guard(twin, Limits()), 0, 0
    import threading

    server._lock = threading.Lock()
    for raw, msg in ((b"not json", "not JSON"), (b"[1, 2]", "JSON object"), (b'{"target_mm": [1, 2, 3]}', "speed_mm_s"),
                     (b'{"target_mm": "abc", "speed_mm_s": 1}', "3 numbers")):
        r = server.answer(raw)
        assert msg in r["error"] and r["type"] == "DataError"
    assert server.refused == 4 and server.served == 0


def test_the_daemon_serves_correct_requests_on_its_bus(quick_demo, tmp_path):
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.service.daemon import Daemon, RuntimeConfig

    port = free_port()
    cfg = RuntimeConfig.model_validate({
        "twin": str(quick_demo[2] / "model"), "store": str(tmp_path / "dt.sqlite"), "realtime": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml")},
        "publish": True, "bus": {"cell": "c2", "robot": "r2", "listen": [f"tcp/127.0.0.1:{port}"]}})
    d = Daemon(cfg, CONFIGS)
    client = open_session(BusConfig(cell="c2", robot="prog", listen=[f"tcp/127.0.0.1:{free_port()}"],
                                    connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        r = ask(client, "dt/c2/r2/correct", [880.0, 40.0, 560.0], 250.0)
        c = d.twin.correct(np.array([0.88, 0.04, 0.56]), 0.25)
        assert np.allclose(r["command_mm"], c.command * 1e3, atol=1e-9) and r["inside"]
    finally:
        close_session(client, 3.0)
        d.close()


def test_the_benchmark_runs_its_real_path(quick_demo):
    from benchmarks.correct import run

    r = run(20, str(quick_demo[2] / "model"))  # the figures are the benchmark's; here: it runs
    assert r["n"] == 20 and {"bus_median_ms", "inproc_median_ms", "ratio"} <= set(r)
    assert r["bus_median_ms"] > 0 and r["inproc_median_ms"] > 0
