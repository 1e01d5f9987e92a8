"""The campaign runner with the serial controller and tracker drivers, against their emulators on
pseudo-terminals over the simulated plant: running the DOE on a real cell is a config change
(the drivers come from `drivers.registry` by name and config, as the daemon builds them)."""
import threading

import numpy as np

from drivers import registry
from drivers.simulated.devices import SimWorld
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.plans import build_plan, load_plan
from dt_runtime.twin import calibration as cal
from dt_runtime.workflows.campaign import Instruments, run_rows
from emulators.serial import ControllerEmulator, TrackerEmulator


def _campaign(inst, plan):
    reg = run_rows(inst, plan.registration)
    doe = run_rows(inst, plan.doe[:40])
    return reg, doe


def test_the_campaign_runs_through_the_serial_drivers(tmp_path):
    plan = build_plan(load_plan(CONFIGS / "plan_quick.yaml"))
    world = SimWorld(CONFIGS / "scenarios/paper_default.yaml", CONFIGS / "cell.yaml")
    lock = threading.Lock()  # one plant behind both emulators
    ctl = ControllerEmulator(world.cell.plant, plant_lock=lock)
    trk = TrackerEmulator(world.cell.tracker.measure_spherical, lock=lock)
    robot = registry.create("robot", "serial", {"url": ctl.port, "timeout_s": 2.0, "move_timeout_s": 10.0},
                            source="<test>")
    tracker = registry.create("tracker", "serial", {"url": trk.port, "timeout_s": 2.0}, source="<test>")
    camera = registry.create("camera", "sim_point", {}, world=world, source="<test>")
    inst = Instruments(robot, tracker, camera, world=None, max_speed=world.max_speed())  # no truth: a real cell
    try:
        inst.activate()
        reg, doe = _campaign(inst, plan)
    finally:
        inst.close()
        ctl.stop()
        trk.stop()
    assert np.all(np.isfinite(reg.p_rdk)) and np.all(np.isfinite(reg.p_lt)) and np.all(np.isfinite(doe.p_lt))
    assert reg.truth_lt is None and np.all(np.isnan(doe.temperature))  # a real cell logs its own
    frames = cal.register(reg)
    assert max(np.abs(r).max() for r in frames.residuals.values()) < 0.5e-3  # sub-mm registration residuals
    errs = cal.doe_errors(doe, frames)
    # The same rows through the simulated drivers on a fresh world of the same scenario: the same arm
    w2 = SimWorld(CONFIGS / "scenarios/paper_default.yaml", CONFIGS / "cell.yaml")
    sim = Instruments(*(registry.create(k, n, {}, world=w2, source="<test>")
                        for k, n in (("robot", "sim"), ("tracker", "sim"), ("camera", "sim_point"))),
                      world=w2, max_speed=w2.max_speed())
    try:
        sim.activate()
        reg2, doe2 = _campaign(sim, plan)
    finally:
        sim.close()
    e2 = cal.doe_errors(doe2, cal.register(reg2))
    # same positionings, the same arm's errors up to the instruments' noise (tens of um)
    assert errs.e_lt.shape == e2.e_lt.shape
    assert np.sqrt(np.mean((errs.e_lt - e2.e_lt) ** 2)) < 0.05e-3
    assert np.sqrt(np.mean(errs.e_lt ** 2)) > 0.2e-3  # and the errors are there to be compared
