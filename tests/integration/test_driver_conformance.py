"""One conformance suite for every driver implementation (docs/drivers.md: the conformance suite).

The suite runs on every driver the registry knows (drivers.registry: the built-in ones and any
installed plugin), of every kind, cameras included. `FIXTURES` gives each (kind, name) one or
more fixtures: a factory taking no arguments and returning a context manager that yields
`(driver, config)`: a driver built by `registry.create` and *not* configured yet, and the options
that `driver.configure(config)` accepts. Everything the driver needs (a simulated world, an
emulator on a pseudo-terminal) is set up and torn down by the factory. A registered driver
without a fixture fails `test_every_registered_driver_has_a_fixture`: add one here.
The checks live in tests/support/conformance.py (`run_suite(kind, factory)` runs every check of a
kind on one factory; tests/integration/test_driver_plugin.py runs it on a plugin installed during
the test).
"""
from __future__ import annotations

import contextlib

import numpy as np
import pytest

from drivers import registry
from emulators.serial import ControllerEmulator, TrackerEmulator
from tests.support import conformance
from tests.support.serial_plant import FakePlant

SCENARIO, CELL = "configs/scenarios/paper_default.yaml", "configs/cell.yaml"
Factory = conformance.Factory


@contextlib.contextmanager
def _sim_world():
    from pathlib import Path

    from drivers.simulated.devices import SimWorld

    root = Path(__file__).resolve().parents[2]
    world = SimWorld(root / SCENARIO, root / CELL)
    try:
        yield world
    finally:
        world.close()


def on_world(kind: str, name: str) -> Factory:
    """A simulated driver on a fresh simulated cell; it takes no options but its own."""
    @contextlib.contextmanager
    def factory():
        with _sim_world() as world:
            drv = registry.create(kind, name, world=world)
            try:
                yield drv, {}
            finally:
                drv.close()
    return factory


@contextlib.contextmanager
def serial_robot_fake_plant():
    with ControllerEmulator(FakePlant()) as emu:
        drv = registry.create("robot", "serial")
        try:
            yield drv, {"url": emu.port, "timeout_s": 0.5, "retries": 2}
        finally:
            drv.close()


@contextlib.contextmanager
def serial_robot_sim_plant_over_socket():
    # The real simulated plant behind the emulator, reached through pyserial's socket:// URL.
    with _sim_world() as world, ControllerEmulator(world.cell.plant, "tcp://127.0.0.1:0") as emu:
        drv = registry.create("robot", "serial")
        try:
            yield drv, {"url": emu.port, "timeout_s": 2.0, "retries": 2}
        finally:
            drv.close()


@contextlib.contextmanager
def ur_rtde_sim_plant():
    # A Universal Robots controller emulated on loopback (RTDE + script port) over the simulated plant.
    from drivers.ur.driver import UrRtdeController
    from emulators.ur import UrEmulator

    with _sim_world() as world, UrEmulator(world.cell.plant, "127.0.0.1", 0, 0, time_scale=0.25) as emu:
        drv = UrRtdeController()
        try:
            yield drv, {"host": "127.0.0.1", "rtde_port": emu.rtde_port, "script_port": emu.script_port,
                        "timeout_s": 2.0, "move_timeout_s": 10.0}
        finally:
            drv.close()


@contextlib.contextmanager
def serial_tracker_fake():
    rng = np.random.default_rng(5)

    def measure():
        return 2.0 + 0.01 * rng.standard_normal(), 0.3, -0.1, "ok"

    with TrackerEmulator(measure) as emu:
        drv = registry.create("tracker", "serial")
        try:
            yield drv, {"url": emu.port, "timeout_s": 0.5, "retries": 2}
        finally:
            drv.close()


@contextlib.contextmanager
def natnet_camera():
    # The NatNet driver against its emulator streaming the simulated rig (static tool) on loopback.
    from drivers.natnet.driver import NatNetRig
    from emulators.natnet import NatNetEmulator, SimRigMarkers
    from sim.kinematics import TOOL_DOWN

    src = SimRigMarkers(lambda: (TOOL_DOWN, np.array([0.9, 0.05, 0.5])), seed=3)
    with NatNetEmulator(src, {"command_port": 0, "data_port": 0}) as emu:
        drv = NatNetRig()
        try:
            # Generous age limit: the machine is shared; staleness has its own test (test_natnet).
            yield drv, {"command_port": emu.command_port, "max_age_s": 0.5, "read_timeout_s": 5.0}
        finally:
            drv.close()


# (kind, name) -> [(fixture id, factory)]: every registered driver needs at least one.
FIXTURES: dict[tuple[str, str], list[tuple[str, Factory]]] = {
    ("robot", "sim"): [("sim", on_world("robot", "sim"))],
    ("robot", "serial"): [("pty-fakeplant", serial_robot_fake_plant),
                          ("socket-simplant", serial_robot_sim_plant_over_socket)],
    ("robot", "ur_rtde"): [("simplant", ur_rtde_sim_plant)],
    ("tracker", "sim"): [("sim", on_world("tracker", "sim"))],
    ("tracker", "serial"): [("pty", serial_tracker_fake)],
    ("camera", "sim_point"): [("sim", on_world("camera", "sim_point"))],
    ("camera", "sim_images"): [("sim", on_world("camera", "sim_images"))],
    ("camera", "natnet"): [("emulator", natnet_camera)],
}

REGISTERED = [(k, n) for k in registry.KINDS for n in registry.known(k)]


def _cases(kind: str) -> list:
    return [pytest.param(f, id=f"{name}-{fid}") for k, name in REGISTERED if k == kind
            for fid, f in FIXTURES.get((k, name), [])]


_robot = pytest.mark.parametrize("factory", _cases("robot"))
_tracker = pytest.mark.parametrize("factory", _cases("tracker"))
_camera = pytest.mark.parametrize("factory", _cases("camera"))


@pytest.mark.parametrize("kind, name", REGISTERED, ids=[f"{k}-{n}" for k, n in REGISTERED])
def test_every_registered_driver_has_a_fixture(kind, name):
    assert FIXTURES.get((kind, name)), (f"{kind} driver {name!r} ({registry.entries(kind)[name].target}) has no "
                                        "conformance fixture: add one to FIXTURES in tests/integration/test_driver_conformance.py")


@_robot
def test_robot_satisfies_protocol_and_lifecycle_order(factory):
    conformance.robot_satisfies_protocol_and_lifecycle_order(factory)


@_robot
def test_robot_move_then_read(factory):
    conformance.robot_move_then_read(factory)


@_robot
def test_robot_streams_setpoints(factory):
    conformance.robot_streams_setpoints(factory)


def test_streaming_is_declared_by_the_drivers_that_stream():
    """Streaming is a capability a driver declares (drivers.base.SetpointStreamer), not a method
    every driver fakes: the simulated and UR drivers declare it, the serial controller does not."""
    from drivers.base import SetpointStreamer

    declared = {n for n in registry.known("robot") if issubclass(registry.driver_class("robot", n), SetpointStreamer)}
    assert declared == {"sim", "ur_rtde"}


@_robot
def test_robot_refuses_nan_target(factory):
    conformance.robot_refuses_nan_target(factory)


@_robot
def test_robot_abort_refuses_moves_until_cleared(factory):
    conformance.robot_abort_refuses_moves_until_cleared(factory)


@_robot
def test_robot_close_is_idempotent_from_active(factory):
    conformance.robot_close_is_idempotent_from_active(factory)


@pytest.mark.parametrize("factory", _cases("robot") + _cases("tracker") + _cases("camera"))
def test_counters_answer_in_every_state(factory):
    conformance.counters_answer_in_every_state(factory)


@_tracker
def test_tracker_satisfies_protocol_and_lifecycle_order(factory):
    conformance.tracker_satisfies_protocol_and_lifecycle_order(factory)


@_tracker
def test_tracker_measure_is_consistent(factory):
    conformance.tracker_measure_is_consistent(factory)


@_camera
def test_camera_satisfies_protocol_and_lifecycle_order(factory):
    conformance.camera_satisfies_protocol_and_lifecycle_order(factory)


@_camera
def test_camera_read_is_consistent(factory):
    conformance.camera_read_is_consistent(factory)
