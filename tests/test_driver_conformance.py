"""One conformance suite for every driver implementation (docs/drivers.md: the conformance suite).

The suite runs on every driver the registry knows (drivers.registry: the built-in ones and any
installed plugin), of every kind, cameras included. `FIXTURES` gives each (kind, name) one or
more fixtures: a factory taking no arguments and returning a context manager that yields
`(driver, config)`: a driver built by `registry.create` and *not* configured yet, and the options
that `driver.configure(config)` accepts. Everything the driver needs (a simulated world, an
emulator on a pseudo-terminal) is set up and torn down by the factory. A registered driver
without a fixture fails `test_every_registered_driver_has_a_fixture`: add one here.
`run_suite(kind, factory)` runs every check of a kind on one factory (tests/test_driver_plugin.py
runs it on a plugin installed during the test).
"""
from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable

import numpy as np
import pytest

from drivers import registry
from drivers.base import CameraRig, JointState, LaserTracker, RigReading, RobotController, TrackerReading
from drivers.serial.emulator import ControllerEmulator, TrackerEmulator
from dt_kernel.errors import DriverError, StateError
from tests.test_serial import FakePlant

SCENARIO, CELL = "configs/scenarios/paper_default.yaml", "configs/cell.yaml"
Factory = Callable[[], contextlib.AbstractContextManager]


@contextlib.contextmanager
def _sim_world():
    from pathlib import Path

    from drivers.simulated.devices import SimWorld

    root = Path(__file__).resolve().parents[1]
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
    from drivers.ur.emulator import UrEmulator

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
    from drivers.natnet.emulator import NatNetEmulator
    from drivers.natnet.rig_source import SimRigMarkers
    from sim.kinematics import TOOL_DOWN

    src = SimRigMarkers(lambda: (TOOL_DOWN, np.array([0.9, 0.05, 0.5])), seed=3)
    with NatNetEmulator(src, {"command_port": 0}) as emu:
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
                                        "conformance fixture: add one to FIXTURES in tests/test_driver_conformance.py")


STREAM_AGE_S = 0.5  # the oldest receipt a streamed reading may have (the UR driver's stale_after_s)


def _timed(read: Callable):
    """A reading and the host's monotonic clock around the call: its `host_time` (receipt) is not
    after the call returned, and not older than STREAM_AGE_S before it (a streaming device, an
    RTDE controller, hands out the package received last); its device time is a finite number
    (drivers.base: clocks)."""
    before = time.monotonic()
    r = read()
    after = time.monotonic()
    assert before - STREAM_AGE_S <= r.host_time <= after, (before, r.host_time, after)
    assert math.isfinite(r.device_time) and r.device_time == r.t
    return r


def _check_lifecycle_order(drv, config, calls):
    """Reads/writes before configure, before activate and after close raise StateError."""
    assert drv.state == "unconfigured"
    for call in calls:
        with pytest.raises(StateError):
            call()
    with pytest.raises(StateError):
        drv.activate()
    with pytest.raises(StateError):
        drv.deactivate()
    drv.configure(config)
    assert drv.state == "inactive"
    for call in calls:
        with pytest.raises(StateError):
            call()
    drv.activate()
    assert drv.state == "active"
    with pytest.raises(StateError):
        drv.activate()
    with pytest.raises(StateError):
        drv.configure(config)
    drv.deactivate()
    assert drv.state == "inactive"
    for call in calls:
        with pytest.raises(StateError):
            call()
    drv.activate()  # re-activation after deactivate is allowed
    drv.close()
    assert drv.state == "closed"
    drv.close()  # idempotent
    for call in calls:
        with pytest.raises(StateError):
            call()
    with pytest.raises(StateError):
        drv.activate()
    with pytest.raises(StateError):
        drv.configure(config)


# --- robot controllers ------------------------------------------------------------------
@_robot
def test_robot_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, RobotController)
        p = np.array([0.8, 0.0, 0.6])
        _check_lifecycle_order(drv, config, [
            lambda: drv.move_linear(p, 0.1), lambda: drv.stream_setpoint(p, 0.1),
            drv.read_joint_state, drv.read_commanded_tcp])


@_robot
def test_robot_move_then_read(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        p0 = np.asarray(drv.read_commanded_tcp(), dtype=float)
        assert p0.shape == (3,) and np.all(np.isfinite(p0))
        target = p0 + np.array([0.02, -0.03, -0.05])
        drv.move_linear(target, 0.2)
        assert np.allclose(drv.read_commanded_tcp(), target, atol=2e-6)  # controller resolution
        js = _timed(drv.read_joint_state)
        assert isinstance(js, JointState) and js.q.ndim == 1 and js.q.size >= 6
        assert np.all(np.isfinite(js.q)) and math.isfinite(js.t)
        drv.stream_setpoint(p0, 0.2)
        assert np.allclose(drv.read_commanded_tcp(), p0, atol=2e-6)


@_robot
def test_robot_refuses_nan_target(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        with pytest.raises(DriverError):
            drv.move_linear(np.array([np.nan, 0.0, 0.5]), 0.1)
        assert np.all(np.isfinite(drv.read_commanded_tcp()))


@_robot
def test_robot_abort_refuses_moves_until_cleared(factory):
    """The daemon's SIGTERM path: abort() (from any thread) makes moves fail at once; clear_abort
    restores them."""
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        p0 = np.asarray(drv.read_commanded_tcp(), dtype=float)
        drv.abort("test")
        with pytest.raises(DriverError, match="abort"):
            drv.move_linear(p0 + np.array([0.01, 0.0, 0.0]), 0.2)
        drv.clear_abort()
        drv.move_linear(p0 + np.array([0.01, 0.0, 0.0]), 0.2)
        assert np.allclose(drv.read_commanded_tcp(), p0 + np.array([0.01, 0.0, 0.0]), atol=2e-6)


@_robot
def test_robot_close_is_idempotent_from_active(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        drv.close()
        drv.close()
        assert drv.state == "closed"
        with pytest.raises(StateError):
            drv.read_joint_state()


# --- laser trackers ---------------------------------------------------------------------
@_tracker
def test_tracker_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, LaserTracker)
        _check_lifecycle_order(drv, config, [drv.measure])


@_tracker
def test_tracker_measure_is_consistent(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        for _ in range(5):
            r = _timed(drv.measure)
            assert isinstance(r, TrackerReading) and isinstance(r.status, str) and math.isfinite(r.t)
            if r.ok:
                d, az, el = r.spherical
                assert r.point.shape == (3,) and np.all(np.isfinite(r.point))
                assert np.isclose(np.linalg.norm(r.point), d, rtol=1e-12)
                assert np.isclose(np.arctan2(r.point[1], r.point[0]), az, rtol=1e-12)
            else:
                assert np.all(np.isnan(r.point))
        drv.close()
        drv.close()
        assert drv.state == "closed"


# --- camera rigs ------------------------------------------------------------------------
@_camera
def test_camera_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, CameraRig)
        _check_lifecycle_order(drv, config, [drv.read])


@_camera
def test_camera_read_is_consistent(factory):
    """A reading is either a point with a covariance or a refusal with its reason, never both."""
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        n_ok = 0
        for _ in range(4):
            r = _timed(drv.read)
            assert isinstance(r, RigReading) and math.isfinite(r.t) and isinstance(dict(r.quality), dict)
            if r.ok:
                n_ok += 1
                assert r.point.shape == (3,) and np.all(np.isfinite(r.point))
                if r.cov is not None:
                    assert r.cov.shape == (3, 3) and np.allclose(r.cov, r.cov.T)
                    assert np.all(np.linalg.eigvalsh(r.cov) > 0)
            else:
                assert r.point is None and isinstance(r.refused, str) and r.refused
        assert n_ok >= 1  # a healthy rig measures
        drv.close()
        drv.close()
        assert drv.state == "closed"
        with pytest.raises(StateError):
            drv.read()


CHECKS: dict[str, list[Callable]] = {
    "robot": [test_robot_satisfies_protocol_and_lifecycle_order, test_robot_move_then_read,
              test_robot_refuses_nan_target, test_robot_abort_refuses_moves_until_cleared,
              test_robot_close_is_idempotent_from_active],
    "tracker": [test_tracker_satisfies_protocol_and_lifecycle_order, test_tracker_measure_is_consistent],
    "camera": [test_camera_satisfies_protocol_and_lifecycle_order, test_camera_read_is_consistent],
}


def run_suite(kind: str, factory: Factory) -> list[str]:
    """Every check of `kind` on `factory` (a plugin's test calls this); returns the checks' names."""
    for check in CHECKS[kind]:
        check(factory)
    return [c.__name__ for c in CHECKS[kind]]
