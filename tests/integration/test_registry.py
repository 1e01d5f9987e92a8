"""Every registered driver is built one way, `drivers.registry.create(kind, name, config, world=...)`,
and the conformance checks of tests/integration/test_driver_conformance.py run on what it builds, cameras included.
"""
from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest

from drivers import registry
from drivers.base import CameraRig, LaserTracker, RigReading, RobotController
from dt_kernel.errors import ConfigError, DriverError, StateError
from emulators.serial import ControllerEmulator, TrackerEmulator
from tests.support.conformance import check_lifecycle_order
from tests.support.serial_plant import FakePlant

ROOT = Path(__file__).resolve().parents[2]
PROTOCOLS = {"robot": RobotController, "tracker": LaserTracker, "camera": CameraRig}


@contextlib.contextmanager
def world():
    from drivers.simulated.devices import SimWorld

    w = SimWorld(ROOT / "configs/scenarios/paper_default.yaml", ROOT / "configs/cell.yaml")
    try:
        yield w
    finally:
        w.close()


@contextlib.contextmanager
def context(kind: str, name: str):
    """(world or None, the config the driver takes) for one registered driver."""
    if (kind, name) == ("robot", "ur_rtde"):  # a UR emulated on loopback over the simulated plant
        from emulators.ur import UrEmulator

        with world() as w, UrEmulator(w.cell.plant, "127.0.0.1", 0, 0, time_scale=0.25) as ur:
            yield None, {"host": "127.0.0.1", "rtde_port": ur.rtde_port, "script_port": ur.script_port}
    elif (kind, name) == ("camera", "natnet"):  # OptiTrack NatNet emulated on loopback (static tool)
        from emulators.natnet import NatNetEmulator, SimRigMarkers
        from sim.kinematics import TOOL_DOWN

        src = SimRigMarkers(lambda: (TOOL_DOWN, np.array([0.9, 0.05, 0.5])), seed=3)
        with NatNetEmulator(src, {"command_port": 0, "data_port": 0}) as nn:
            yield None, {"command_port": nn.command_port, "max_age_s": 0.5, "read_timeout_s": 5.0}
    elif not registry.needs_world(kind, name):
        emu = ControllerEmulator(FakePlant()) if kind == "robot" else TrackerEmulator(lambda: (2.0, 0.3, -0.1, "ok"))
        with emu:
            yield None, {"url": emu.port, "timeout_s": 0.5, "retries": 2}
    else:
        with world() as w:
            yield w, {}


ALL = [(k, n) for k in ("robot", "tracker", "camera") for n in registry.known(k)]


def _calls(kind: str, drv) -> list:
    if kind == "robot":
        return [lambda: drv.move_linear(np.array([0.9, 0.0, 0.6]), 0.1), drv.read_joint_state,
                drv.read_commanded_tcp]
    return [drv.measure] if kind == "tracker" else [drv.read]


@pytest.mark.parametrize("kind, name", ALL, ids=[f"{k}-{n}" for k, n in ALL])
def test_every_registered_driver_is_built_the_same_way_and_follows_the_lifecycle(kind, name):
    with context(kind, name) as (w, config):
        drv = registry.create(kind, name, world=w, source="runtime.yaml")  # no config: unconfigured
        try:
            assert isinstance(drv, PROTOCOLS[kind])
            check_lifecycle_order(drv, config, _calls(kind, drv))
        finally:
            drv.close()
        drv = registry.create(kind, name, config, world=w, source="runtime.yaml")  # configured
        try:
            assert drv.state == "inactive"
            drv.activate()
            if kind == "camera":
                assert isinstance(drv.read(), RigReading)
            elif kind == "tracker":
                assert drv.measure().ok
            else:
                assert np.all(np.isfinite(drv.read_commanded_tcp()))
        finally:
            drv.close()
        assert drv.state == "closed"
        with pytest.raises(StateError):
            _calls(kind, drv)[0]()


def test_unknown_names_list_the_known_ones_and_bad_keys_name_the_key():
    with pytest.raises(ConfigError) as ei:
        registry.create("robot", "ur10", source="runtime.yaml")
    assert ei.value.key == "drivers.robot" and "serial" in ei.value.allowed and "sim" in ei.value.allowed
    with world() as w:
        # a simulated driver takes no config: a stray serial url is an error, not ignored
        with pytest.raises(ConfigError) as ei:
            registry.create("robot", "sim", {"url": "/dev/ttyUSB0"}, world=w, source="runtime.yaml")
        assert ei.value.file == "runtime.yaml" and ei.value.key == "url"
        with pytest.raises(ConfigError) as ei:
            registry.create("camera", "sim_images", {"bogus": 1}, world=w, source="runtime.yaml")
        assert ei.value.key == "bogus"
    with pytest.raises(ConfigError) as ei:
        registry.create("robot", "serial", {"retries": -1}, source="runtime.yaml")
    assert ei.value.file == "runtime.yaml"


def test_the_built_in_drivers_are_the_entry_points_pyproject_declares():
    """drivers.registry.BUILTIN (the fallback of a checkout whose metadata predates them) must
    say what pyproject.toml says, and the installed metadata carries them (pip install -e .)."""
    import tomllib
    from importlib import metadata

    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    declared = {g.removeprefix(registry.GROUP_PREFIX): dict(v) for g, v in eps.items()
                if g.startswith(registry.GROUP_PREFIX)}
    assert declared == registry.BUILTIN
    for kind, names in registry.BUILTIN.items():
        installed = {ep.name: ep.value for ep in metadata.entry_points(group=registry.group(kind))
                     if ep.dist is not None and ep.dist.name == registry.PROJECT}
        assert installed == names, "entry points not installed: run `pip install -e .` again"
        ours = {n: e.package for n, e in registry.entries(kind).items() if n in names}
        assert ours == dict.fromkeys(names, "cobot-dt")


@pytest.fixture
def scratch_registry():
    """Registry changes made by a test are forgotten after it."""
    try:
        yield registry
    finally:
        registry.reload()


def test_a_broken_plugin_names_itself_and_its_error(scratch_registry):
    registry.register("tracker", "broken", "dt_no_such_package.tracker:Tracker")
    registry.register("tracker", "not_a_driver", "math:pi")
    assert "broken" in registry.known("tracker")  # listed: it is imported only when chosen
    with pytest.raises(ConfigError) as ei:
        registry.create("tracker", "broken", {}, source="runtime.yaml", key="drivers.tracker")
    e = ei.value
    assert e.file == "runtime.yaml" and e.key == "drivers.tracker.kind" and e.value == "broken"
    assert "dt_no_such_package" in e.allowed and "ModuleNotFoundError" in e.allowed
    with pytest.raises(ConfigError, match="Lifecycle subclass"):
        registry.driver_class("tracker", "not_a_driver")
    registry.create("tracker", "serial", source="x").close()  # the others are unaffected


def test_two_packages_claiming_one_name_is_an_error_naming_both(scratch_registry):
    registry.register("robot", "sim", "drivers.simulated.devices:SimRobot")  # the same class again: fine
    registry.register("robot", "twin_claim", "drivers.serial.controller:SerialController")
    registry.register("robot", "twin_claim", "drivers.simulated.devices:SimRobot")
    assert registry.needs_world("robot", "sim")
    with pytest.raises(ConfigError) as ei:
        registry.driver_class("robot", "twin_claim", "runtime.yaml")
    assert "SerialController" in ei.value.allowed and "SimRobot" in ei.value.allowed
    assert "uninstall one" in ei.value.allowed


def test_options_are_checked_without_building_the_driver_and_errors_carry_the_key_path():
    registry.check("tracker", "serial", {"url": "/dev/ttyUSB1"}, source="rt.yaml", key="drivers.tracker")
    registry.check("camera", "sim_images", {"render": {}, "seed": 3}, source="rt.yaml", key="drivers.camera")
    with pytest.raises(ConfigError) as ei:
        registry.check("tracker", "serial", {}, source="rt.yaml", key="drivers.tracker")
    assert (ei.value.file, ei.value.key, ei.value.value) == ("rt.yaml", "drivers.tracker.url", "<missing>")
    with pytest.raises(ConfigError) as ei:
        registry.check("robot", "sim", {"url": "x"}, source="rt.yaml", key="drivers.robot")
    assert ei.value.key == "drivers.robot.url" and "none" in ei.value.allowed
    with pytest.raises(ConfigError) as ei:
        registry.check("robot", "ur_rtde_typo", {}, source="rt.yaml", key="drivers.robot")
    assert ei.value.key == "drivers.robot.kind" and "serial, sim" in ei.value.allowed
    with pytest.raises(ConfigError) as ei:  # configure's own errors get the same key path
        registry.create("tracker", "serial", {"url": "x", "retries": -1}, source="rt.yaml", key="drivers.tracker")
    assert ei.value.key == "drivers.tracker.retries"


def test_simulated_drivers_say_they_need_a_world():
    assert [registry.needs_world("robot", n) for n in ("serial", "sim")] == [False, True]
    assert [registry.needs_world("camera", n) for n in ("natnet", "sim_images", "sim_point")] == [False, True, True]
    for kind, name in ALL:
        if registry.needs_world(kind, name):
            with pytest.raises(DriverError, match="world"):
                registry.create(kind, name)
