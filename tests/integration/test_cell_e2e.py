"""Issue 14's end to end: the calibration campaign (`dt campaign`) and the twin daemon (`dt run`)
with `robot: ur_rtde` against the UR emulator, `camera: natnet` against the NatNet emulator and
the serial laser tracker, all in the emulated cell (`python -m emulators.emulated_cell`, one
plant), on loopback. No timing assertions: counts, states and magnitudes only."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from dt_runtime.twin.twin import Twin
from tests.support.emulated_cell_process import ROOT, campaign, cell_process


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


def _e_lt(reg, doe):
    """The DOE's errors seen by the tracker (Eq. 8, GL), every row (the MVS plays no part)."""
    from dt_runtime.twin import calibration as cal

    fr = cal.register(reg)
    return fr.T_rdk.apply(doe.p_rdk) - fr.T_lt.apply(doe.p_lt)


def test_the_campaigns_errors_match_the_simulated_drivers_on_the_same_scenario(ur_natnet_campaign):
    """The same rows through the simulated drivers on a fresh world of the cell's scenario and
    seed: the same arm, so the DOE errors seen by the tracker agree up to the instruments' noise."""
    rc, out, _ = ur_natnet_campaign
    assert rc == 0
    _same_errors_as_the_simulated_drivers(out)


@pytest.mark.soak
def test_the_whole_quick_plan_through_the_cell_matches_the_simulated_drivers(tmp_path):
    """The full campaign of `dt demo --quick` (36 registration + 558 DOE rows) through the
    emulated cell (`-m soak`: about a minute)."""
    with cell_process("--time-scale", "0.05", "--seed", "1") as cell:
        rc, out, _ = campaign(cell, tmp_path, doe_rows=None)
    assert rc == 0, out
    assert out["doe_rows"] == 558 and out["refusals"] == 0, out["refusal_examples"]
    assert out["precision_after_mm"] < out["precision_before_mm"]
    _same_errors_as_the_simulated_drivers(out)


def _same_errors_as_the_simulated_drivers(out: dict) -> None:
    import numpy as np

    from drivers import registry
    from drivers.simulated.devices import SimWorld
    from dt_runtime.cli.campaign import spread
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.measurements.plans import build_plan, load_plan
    from dt_runtime.workflows.campaign import Instruments, run_rows
    from dt_runtime.workflows.campaign_dir import read_manifest

    c = read_manifest(out["campaign"]).load()
    e1 = _e_lt(c.registration, c.doe)
    plan = build_plan(load_plan(CONFIGS / "plan_quick.yaml"))
    w = SimWorld(CONFIGS / "scenarios/paper_default.yaml", CONFIGS / "cell.yaml", seed=1)
    sim = Instruments(*(registry.create(k, n, {}, world=w, source="<test>")
                        for k, n in (("robot", "sim"), ("tracker", "sim"), ("camera", "sim_point"))),
                      world=w, max_speed=w.max_speed())
    try:
        sim.activate()
        doe = plan.doe if out["doe_rows"] == len(plan.doe) else spread(plan.doe, out["doe_rows"])
        e2 = _e_lt(run_rows(sim, plan.registration), run_rows(sim, doe))
    finally:
        sim.close()
        w.close()
    assert e1.shape == e2.shape and np.all(np.isfinite(e1))
    diff = np.sqrt(np.mean((e1 - e2) ** 2))
    print(f"e_LT through the cell vs simulated drivers: RMS difference {diff * 1e3:.4f} mm, "
          f"RMS error {np.sqrt(np.mean(e1 ** 2)) * 1e3:.4f} mm")
    assert diff < 0.05e-3
    assert np.sqrt(np.mean(e1 ** 2)) > 0.2e-3  # and the errors are there to be compared
