"""The plant across network namespaces: `dt router`, three `dt run` daemons on the simulated cell and
the plant's inbox (`dt consume` into a history), each in a namespace of its own, joined to the
router's by links with 5-20 ms of added latency (seeded; tests.support.netns).

The facts: the cells start before their router (they connect when it comes); one query from the
inbox's namespace names all three; c1's fault pages; the router is killed (-9) and restarted with the
request pending; the inbox comes, and the request is recorded exactly once and acknowledged (the
cell's open requests back to 0). Skipped, saying why, without root, `ip` or `tc`, or where
namespaces cannot be made. Waits are generous (wait_until); nothing is timed."""
from __future__ import annotations

import json
import sqlite3
import subprocess
import sys

import pytest

from tests.support.loopback import wait_until
from tests.support.netns import PORT, netns_links, unavailable
from tests.support.plant_cells import runtime, stop

CELLS = ("c1", "c2", "c3")
DT = [sys.executable, "-m", "dt_runtime.cli.main"]


@pytest.fixture
def links():
    why = unavailable()
    if why:
        pytest.skip(f"the namespaced plant needs network namespaces: {why}")
    with netns_links([*CELLS, "inbox"], delay_ms=(5.0, 20.0), seed=3) as lk:
        yield lk


def test_the_plant_across_namespaces_with_link_latency_loses_nothing(twin_dir, links, tmp_path):
    lk = links
    assert all(5.0 <= ms <= 20.0 for ms in lk.delay_ms.values())
    cfg = tmp_path / "plant.yaml"
    cfg.write_text(json.dumps({"router": {"listen": [lk.router_listen]},
                               "bus": {"cell": "plant", "robot": "inbox", "mode": "client",
                                       "connect": [lk.endpoint("inbox")]},
                               "cells": [f"{c}/r1" for c in CELLS], "history": {"url": "history.sqlite"}}))
    logs = {name: tmp_path / f"{name}.log" for name in (*CELLS, "router", "inbox")}
    procs: dict[str, subprocess.Popen] = {}
    try:
        # The cells first: their router is not up yet, they keep trying.
        for c in CELLS:
            rc = runtime(tmp_path, twin_dir, c, PORT, faulty=c == "c1", endpoint=lk.endpoint(c))
            procs[c] = lk.popen(c, [*DT, "run", "--config", str(rc)], logs[c])

        def start_router(n: int) -> None:
            before = logs["router"].read_text() if logs["router"].exists() else ""
            procs["router"] = lk.popen("router", [*DT, "router", "--config", str(cfg)], logs["router"])
            assert wait_until(lambda: logs["router"].read_text().count("dt router: listening") > before.count(
                "dt router: listening") or procs["router"].poll() is not None, 60), f"router {n} did not start"
            assert procs["router"].poll() is None, logs["router"].read_text()[-2000:]

        def status(kind: str = "status") -> dict:
            out = subprocess.run(lk.argv("inbox", [*DT, "status", "--bus", str(cfg), "dt/*/*", "--kind", kind,
                                                   "--timeout", "3", "--json"]),
                                 capture_output=True, text=True, timeout=120)
            return json.loads(out.stdout) if out.returncode == 0 else {"cells": [], "error": out.stderr[-500:]}

        def c1_paged() -> bool:
            s = status()
            return [c["cell"] for c in s["cells"]] == list(CELLS) and any(
                c["cell"] == "c1" and c["escalation"] == "maintenance_requested" and c["open_requests"] == 1
                for c in s["cells"])

        started = "bus: no router reachable"  # each cell's daemon runs, connecting in the background
        assert wait_until(lambda: all(started in logs[c].read_text() for c in CELLS), 180), [
            (c, procs[c].poll(), logs[c].read_text()[-1500:]) for c in CELLS]
        start_router(1)
        assert wait_until(c1_paged, 180), [(c, procs[c].poll(), logs[c].read_text()[-1500:]) for c in CELLS]
        s = status("health")
        assert s["answered"] == [f"{c}/r1" for c in CELLS] and s["missing"] == []
        assert {c["cell"]: c["bus"] for c in s["cells"]} == {c: "connected" for c in CELLS}

        # The router dies mid-escalation (c1's request pending) and comes back; then the inbox.
        procs["router"].kill()
        procs["router"].wait(10)
        start_router(2)
        procs["inbox"] = lk.popen("inbox", [*DT, "consume", "--bus", str(cfg), "--count", "1", "--duration", "300",
                                            "--json"], logs["inbox"], stdout=subprocess.PIPE)
        out, _ = procs["inbox"].communicate(timeout=330)
        summary = json.loads(out.strip().splitlines()[-1])
        assert summary["recorded"] == 1 and summary["history_rows"] == 1, (summary, logs["inbox"].read_text()[-2000:])
        with sqlite3.connect(tmp_path / "history.sqlite") as db:
            rows = db.execute("SELECT cell, robot, kind, uid FROM maintenance_requests").fetchall()
        assert [r[:3] for r in rows] == [("c1", "r1", "t_test")]
        # Acknowledged through the namespaces: nothing left open in any cell, and c1 sent only that one.
        assert wait_until(lambda: (lambda s: len(s["cells"]) == 3 and all(c["open_requests"] == 0 for c in s["cells"]))(
            status()), 120), status()
        sent = {c["cell"]: c["latest"] for c in status("requests")["cells"]}
        assert [(r["uid"], r["acked"]) for r in sent["c1"]] == [(rows[0][3], True)]
        assert sent["c2"] == [] and sent["c3"] == []
        for c in CELLS:
            assert procs[c].poll() is None, logs[c].read_text()[-2000:]
    finally:
        for p in procs.values():
            stop(p)
