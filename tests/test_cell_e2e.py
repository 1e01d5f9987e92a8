"""Issue 14's end to end: the calibration campaign (`dt campaign`) and the twin daemon (`dt run`)
with `robot: ur_rtde` against the UR emulator, `camera: natnet` against the NatNet emulator and
the serial laser tracker, all in the emulated cell (`python -m drivers.emulated_cell`, one
plant), on loopback. No timing assertions: counts, states and magnitudes only."""
from __future__ import annotations

import json
import subprocess
import sys

from dt_runtime.twin.twin import Twin
from tests.emulated_cell_process import ROOT


def test_the_campaign_through_rtde_natnet_and_the_serial_tracker_makes_a_twin_of_those_drivers(ur_natnet_campaign):
    rc, out, cfg = ur_natnet_campaign
    assert rc == 0, out
    assert out["drivers"] == {"robot": "ur_rtde", "tracker": "serial", "camera": "natnet"}
    assert out["registration_rows"] == 36 and out["doe_rows"] == 60 and out["refusals"] == 0, out["refusal_examples"]
    res = out["registration_residuals_mm"]
    # sub-millimetre registration residuals for both instruments (their noise: tens of um)
    assert all(0 < res[k][a]["std_mm"] < 0.5 for k in ("lt", "mvs") for a in "xyz"), res
    # the arm's errors are there (the plant's effects, ~1 mm) and the twin's map explains them
    e = out["e_lt_doe_mm"]
    assert 0.1 < max(abs(e[a]["mean_mm"]) + e[a]["std_mm"] for a in "xyz") < 5.0, e
    assert out["precision_after_mm"] < out["precision_before_mm"]
    assert Twin.load(out["twin"]).instruments == out["drivers"]  # dt run refuses it with another camera


def test_dt_run_drives_the_ur_over_rtde_and_tests_natnet_readings(ur_natnet_cell, ur_natnet_campaign):
    rc, _, cfg = ur_natnet_campaign
    assert rc == 0
    before = ur_natnet_cell.control("stats")
    p = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "run", "--config", str(cfg), "--duration", "4",
                        "--json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-3000:]
    run = json.loads(p.stdout)
    after = ur_natnet_cell.control("stats")
    assert run["ticks"] > 0
    # every command was sent once over the script port and arrived (the UR emulator's count)
    sent = after["ur"]["movel"] - before["ur"]["movel"]
    done = after["ur"]["moves_done"] - before["ur"]["moves_done"]
    assert sent == done == run["ticks"], (sent, done, run)
    assert run["driver_faults"] == run["refused_commands"] == 0 and run["halt_reason"] is None
    assert run["stale_measurements"] == 0 and run["mvs_refused"] <= run["ticks"] // 10, run
    assert after["natnet"]["frames_sent"] > before["natnet"]["frames_sent"]
    assert run["state"] in ("nominal", "suspect"), run  # the twin's own cell: no maintenance
    st = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "status", "--store", run["store"], "--json"],
                        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert st.returncode == 0, st.stderr[-2000:]
    tested = json.loads(st.stdout)["t_tests"]["n"]
    assert 0 < tested == run["ticks"] - run["mvs_refused"] - run["stale_measurements"]  # NatNet readings t-tested
