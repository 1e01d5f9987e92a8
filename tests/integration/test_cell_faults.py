"""Faults through the real protocols, at the daemon level (issue 14): the daemon runs the twin
of the emulated cell (`dt campaign`) through `ur_rtde`, `natnet` and the serial tracker; faults
are injected on the cell's control port: the RTDE connection dropped (and restored by the
driver), a protective stop during a move, NatNet frames lost or late, the rigid body not
tracked. Each is detected and reported on the bus (`dt/<cell>/<robot>/health`), and the UR
emulator's `movel` count shows that nothing moved twice. Sequenced by tick counts, never by
time; generous waits only to detect a hang."""
from __future__ import annotations

import json
import threading

import pytest

from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.session import close_session, open_session
from dt_runtime.service.daemon import Daemon
from dt_runtime.service.runtime_config import load_runtime_config
from tests.support.emulated_cell_process import runtime_yaml
from tests.support.loopback import free_port, wait_until


@pytest.fixture
def daemon(ur_natnet_cell, ur_natnet_campaign, tmp_path):
    """(daemon, the cell, the health messages seen on the bus); NatNet faults cleared after."""
    rc, out, _ = ur_natnet_campaign
    assert rc == 0, out
    port = free_port()
    seen: list[dict] = []
    listener = open_session(BusConfig(cell="cell1", robot="watch", listen=[f"tcp/127.0.0.1:{port}"]))
    sub = listener.declare_subscriber("dt/cell1/ur1/health", lambda s: seen.append(json.loads(s.payload.to_bytes())))
    bus = {"cell": "cell1", "robot": "ur1", "listen": [f"tcp/127.0.0.1:{free_port()}"],
           "connect": [f"tcp/127.0.0.1:{port}"], "health_period_s": 0.2}
    cfg = runtime_yaml(ur_natnet_cell, out["twin"], tmp_path, realtime=False, publish=True, bus=bus)
    d = Daemon(load_runtime_config(cfg), cfg.parent, source=str(cfg))
    try:
        yield d, ur_natnet_cell, seen
    finally:
        d.close()
        sub.undeclare()
        close_session(listener, 3.0)
        ur_natnet_cell.control("natnet drop_probability=0 delay_probability=0 delay_s=0 untracked_probability=0")
        ur_natnet_cell.control("unlock")


def _moves(cell) -> tuple[int, int]:
    ur = cell.control("stats")["ur"]
    return ur["movel"], ur["moves_done"]


def test_rtde_dropped_during_the_run_is_restored_reported_and_no_move_is_sent_twice(daemon):
    d, cell, seen = daemon
    sent0, done0 = _moves(cell)
    drops0 = d.inst.robot.counters()["drops"]
    result: dict = {}
    run = threading.Thread(target=lambda: result.update(d.run(max_ticks=30)))
    run.start()
    assert wait_until(lambda: d.counters.ticks >= 5, 60)
    assert cell.control("drop_rtde 0")["ok"]  # closed after the next data package, mid-run
    run.join(120)
    assert not run.is_alive() and result["ticks"] == 30
    assert result["driver_faults"] == 0  # the driver reconnected; the move in flight was judged on the new stream
    c = d.inst.robot.counters()
    assert c["drops"] == drops0 + 1 and c["connects"] >= 2
    assert wait_until(lambda: any(h.get("drivers", {}).get("robot", {}).get("drops", 0) > drops0 for h in seen), 20)
    sent, done = _moves(cell)
    assert sent - sent0 == done - done0 == 30  # each command sent once, executed once


def test_a_protective_stop_during_a_move_halts_on_the_bus_and_resumes_after_unlock(daemon):
    d, cell, seen = daemon
    d.run(max_ticks=2)
    sent0, _ = _moves(cell)
    ticks0 = d.counters.ticks
    stops0 = cell.control("stats")["ur"]["protective_stops"]
    assert cell.control("protective_stop")["ok"]  # the next motion stops half way
    s = d.run(max_ticks=4)  # the stopped move, then moves refused before anything is sent
    assert s["driver_faults"] >= 3 and s["state"] == "halted" and "protective stop" in s["halt_reason"].lower()
    assert cell.control("stats")["ur"]["protective_stops"] == stops0 + 1
    assert wait_until(lambda: any(h["status"] == "halted" and "protective stop" in (h["reason"] or "").lower()
                                  for h in seen), 20), seen[-3:]
    assert cell.control("unlock")["ok"]  # the pendant's "unlock protective stop"
    assert wait_until(lambda: d.inst.robot.status()["safety_mode"] == "NORMAL", 20)
    s = d.run(max_ticks=3)
    assert d.counters.ticks > ticks0 and s["state"] != "halted"
    assert wait_until(lambda: seen and seen[-1]["status"] != "halted", 20)
    sent, _ = _moves(cell)
    # the stopped move was sent once and not re-sent; the refused ones were never sent
    assert sent - sent0 == d.counters.ticks - ticks0 + 1


@pytest.mark.parametrize("fault, refused, counter", [
    ("drop_probability=0.5", None, "frames_lost"),
    ("delay_probability=1.0 delay_s=0.5", "stale", None),
    ("untracked_probability=1.0", "not tracked", None),
])
def test_natnet_faults_are_reported_and_nothing_moves_twice(daemon, fault, refused, counter):
    d, cell, seen = daemon
    d.run(max_ticks=2)
    sent0, _ = _moves(cell)
    ticks0, refused0 = d.counters.ticks, d.counters.mvs_refused
    lost0 = d.inst.camera.counters()["frames_lost"]
    assert cell.control(f"natnet {fault}")["ok"]
    s = d.run(max_ticks=8)
    sent, done = _moves(cell)
    assert sent - sent0 == d.counters.ticks - ticks0 == 8  # every command moved once, measured or not
    assert s["driver_faults"] == 0
    if counter:  # readings go on; the loss is counted by the driver and shows on the bus
        assert d.inst.camera.counters()[counter] > lost0
        assert wait_until(lambda: any(h.get("drivers", {}).get("camera", {}).get(counter, 0) > lost0
                                      for h in seen), 20)
    if refused:  # every reading refused, none tested: degraded on the bus, naming why
        assert s["mvs_refused"] - refused0 == 8
        assert wait_until(lambda: any(h["status"] == "degraded" and refused in (h["reason"] or "")
                                      for h in seen), 20), seen[-3:]
        assert wait_until(lambda: seen[-1]["mvs_refused"] >= refused0 + 8, 20)


def test_natnet_refused_longer_than_the_limit_halts_pages_stops_the_arm_and_resumes(daemon):
    """The rigid body out of view for longer than `halt.after_camera_refused_s` (1 s here, wall
    clock): halted with the driver's reason, paged (the halt's request in the outbox), on the bus;
    no move is sent while halted; tracked again, the first reading resumes."""
    d, cell, seen = daemon
    d.supervisor.halt = d.cfg.halt.model_copy(update={"after_camera_refused_s": 1.0})  # the policy's own config
    d.run(max_ticks=2)
    assert cell.control("natnet untracked_probability=1.0")["ok"]
    for _ in range(200):  # ticks until the limit passes (each one moves the arm and is refused)
        d.run(max_ticks=1)
        if d.escalator.state == "halted":
            break
    s = d.summary()
    assert s["state"] == "halted" and "no MVS reading tested for" in s["halt_reason"], s
    assert "not tracked" in s["halt_reason"]
    reqs = d.store.outbox_of_episode(d.escalator.episode)
    assert len(reqs) == 1 and reqs[0].payload["kind"] == "halt"
    assert wait_until(lambda: any(h["status"] == "halted" and "no MVS reading" in (h["reason"] or "")
                                  for h in seen), 20), seen[-3:]
    sent0, _ = _moves(cell)
    d.run(max_ticks=3)
    assert _moves(cell)[0] == sent0 and d.escalator.state == "halted"  # the arm stands
    assert cell.control("natnet untracked_probability=0")["ok"]
    assert wait_until(lambda: (d.run(max_ticks=1), d.escalator.state)[1] != "halted", 30)
    d.run(max_ticks=3)
    assert _moves(cell)[0] > sent0 and d.escalator.state == "nominal"
