"""A plant on one Zenoh fabric, end to end: `dt router` and three `dt run` daemons on the simulated
cell (each its own cell name and store, bus: a client of the router) as processes on loopback,
and the plant's maintenance inbox (two consumers of one group writing one history, as a
redundant maintenance host would).

The facts: the plant status query (one get) names all three cells; a fault in cell c1 pages once;
the request is raised while the maintenance host is away, then the router is killed (-9) and c1
too, mid-escalation (the request pending in c1's outbox); both restart, and the request arrives,
is recorded exactly once and acknowledged; c1 resumes `maintenance_requested` and pages nothing
more; a cell that is not running is named as missing. Waits are generous (wait_until); nothing is
timed."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from dt_runtime.plant.config import PlantConfig
from dt_runtime.plant.inbox import PlantInbox
from dt_runtime.plant.status import plant_status
from tests.support.loopback import free_port, wait_until
from tests.support.plant_cells import dt, router, runtime, stop

CELLS = ("c1", "c2", "c3")


@pytest.fixture
def plant(tmp_path):
    port = free_port()
    cfg = tmp_path / "plant.yaml"
    cfg.write_text(f"router: {{listen: ['tcp/127.0.0.1:{port}']}}\n"
                   f"bus: {{cell: plant, robot: inbox, mode: client, connect: ['tcp/127.0.0.1:{port}']}}\n"
                   f"cells: [{', '.join(f'{c}/r1' for c in CELLS)}, c4/r1]\n"
                   f"history: {{url: history.sqlite}}\n")
    procs: dict[str, subprocess.Popen] = {}
    yield port, cfg, procs
    for p in procs.values():
        stop(p)


def test_three_cells_one_router_one_inbox_through_restarts(twin_dir, plant, tmp_path):
    port, cfg_path, procs = plant
    cfg = PlantConfig.model_validate({"bus": {"cell": "plant", "robot": "inbox", "mode": "client",
                                              "connect": [f"tcp/127.0.0.1:{port}"]},
                                      "cells": [f"{c}/r1" for c in CELLS] + ["c4/r1"]})
    procs["router"] = router(cfg_path, tmp_path / "router1.log")
    for c in CELLS:
        cfg_c = runtime(tmp_path, twin_dir, c, port, faulty=c == "c1")
        procs[c] = dt("run", "--config", str(cfg_c), log=tmp_path / f"{c}.log")

    def status(kind: str = "status") -> dict:
        return plant_status(cfg, "dt/*/*", kind, timeout_s=2.0)

    def c1_paged() -> bool:
        s = status()
        return [c["cell"] for c in s["cells"]] == list(CELLS) and any(
            c["cell"] == "c1" and c["escalation"] == "maintenance_requested" and c["open_requests"] == 1
            for c in s["cells"])

    # One query names every running cell (and the one that is not), and c1 has paged: its request is
    # pending (the maintenance host is away).
    assert wait_until(c1_paged, 120), [(p.poll(), (tmp_path / f"{c}.log").read_text()[-1500:])
                                       for c, p in procs.items() if c != "router"]
    s = status()
    assert s["answered"] == ["c1/r1", "c2/r1", "c3/r1"] and s["missing"] == ["c4/r1"]
    assert {c["cell"]: c["escalation"] for c in s["cells"]}["c2"] == "nominal"
    assert all(c["open_requests"] == 0 for c in s["cells"] if c["cell"] != "c1")

    # Mid-escalation: the router dies, and c1 with it (kill -9), its request still pending.
    for name in ("router", "c1"):
        procs[name].kill()
        procs[name].wait(10)
    procs["router"] = router(cfg_path, tmp_path / "router2.log")
    procs["c1"] = dt("run", "--config", str(tmp_path / "c1.yaml"), log=tmp_path / "c1.log")

    # The maintenance host comes back: two consumers of one group, one history.
    history = str(tmp_path / "history.sqlite")
    with PlantInbox(cfg.bus, history) as a, PlantInbox(cfg.bus.model_copy(update={"robot": "inbox2"}), history) as b:
        assert wait_until(lambda: a.requests and b.requests, 120), (tmp_path / "c1.log").read_text()[-2000:]
        assert wait_until(lambda: all(c["open_requests"] == 0 for c in status()["cells"])
                          and len(status()["answered"]) == 3, 60), status()
        rows = a.history.rows()
        assert len(rows) == 1 and a.recorded + b.recorded == 1  # exactly once, after dedup
        assert (rows[0]["cell"], rows[0]["robot"], rows[0]["kind"]) == ("c1", "r1", "t_test")
        reqs = {c["cell"]: c for c in status("requests")["cells"]}
        sent = reqs["c1"]["latest"]  # every request c1's store ever opened: one, the recorded one, acknowledged
        assert [(r["uid"], r["acked"]) for r in sent] == [(rows[0]["uid"], True)]
        assert reqs["c1"]["escalation"] == "maintenance_requested"  # resumed from its store, waits for 'done'
        assert reqs["c2"]["latest"] == [] and reqs["c3"]["latest"] == []
        assert {r["uid"] for r in a.requests} == {r["uid"] for r in b.requests} == {rows[0]["uid"]}
    for c in CELLS:
        assert procs[c].poll() is None, (tmp_path / f"{c}.log").read_text()[-2000:]

    # The table a person reads: every cell, and the silent one named.
    out = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "status", "--bus", str(cfg_path), "dt/*/*"],
                         capture_output=True, text=True, timeout=60, env=os.environ)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "3 cell(s) answered dt/*/*/status" in out.stdout and "did not answer: c4/r1" in out.stdout
    assert "c1/r1" in out.stdout and "maintenance_requested" in out.stdout
