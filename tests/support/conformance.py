"""The driver conformance checks (docs/drivers.md: the conformance suite), shared by the suite's
own tests (tests/integration/test_driver_conformance.py runs them on every registered driver)
and a plugin's (tests/integration/test_driver_plugin.py: `run_suite` on a plugin installed during
the test). Each check takes a factory: no arguments, a context manager yielding `(driver,
config)`, the driver built and not configured yet."""
from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable

import numpy as np
import pytest

from drivers.base import (
    CameraRig,
    JointState,
    LaserTracker,
    RigReading,
    RobotController,
    TrackerReading,
    streams,
)
from dt_kernel.errors import DriverError, StateError

Factory = Callable[[], contextlib.AbstractContextManager]

STREAM_AGE_S = 0.5  # the oldest receipt a streamed reading may have (the UR driver's stale_after_s)


def timed(read: Callable):
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


def check_lifecycle_order(drv, config, calls):
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
def robot_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, RobotController)
        p = np.array([0.8, 0.0, 0.6])
        calls = [lambda: drv.move_linear(p, 0.1), drv.read_joint_state, drv.read_commanded_tcp]
        if streams(drv):  # a declared capability is held to the same lifecycle
            calls += [lambda: drv.start_stream(125.0), lambda: drv.stream(p, 0.0)]
        check_lifecycle_order(drv, config, calls)


def robot_move_then_read(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        p0 = np.asarray(drv.read_commanded_tcp(), dtype=float)
        assert p0.shape == (3,) and np.all(np.isfinite(p0))
        target = p0 + np.array([0.02, -0.03, -0.05])
        drv.move_linear(target, 0.2)
        assert np.allclose(drv.read_commanded_tcp(), target, atol=2e-6)  # controller resolution
        js = timed(drv.read_joint_state)
        assert isinstance(js, JointState) and js.q.ndim == 1 and js.q.size >= 6
        assert np.all(np.isfinite(js.q)) and math.isfinite(js.t)
        drv.move_linear(p0, 0.2)
        assert np.allclose(drv.read_commanded_tcp(), p0, atol=2e-6)


def robot_streams_setpoints(factory):
    """Only for drivers that declare streaming (drivers.base.SetpointStreamer): out-of-range
    look-ahead or gain refused; a 5 mm line of set-points at 125 Hz, then the end held: the arm
    follows and settles at the end; stop_stream leaves the driver idle. The set-points are paced
    with sleep (a controller expects one per cycle); nothing asserts on time."""
    with factory() as (drv, config):
        if not streams(drv):
            return
        drv.configure(config)
        drv.activate()
        for bad in ((125.0, 0.5, 300.0), (125.0, 0.1, 5000.0), (0.0, 0.1, 300.0)):
            with pytest.raises(DriverError):
                drv.start_stream(*bad)
        with pytest.raises(StateError):
            drv.stream(np.zeros(3), 0.0)  # before start_stream
        p0 = np.asarray(drv.read_commanded_tcp(), dtype=float)
        end = p0 + np.array([0.005, 0.0, -0.002])
        drv.start_stream(125.0, 0.1, 300.0)
        assert drv.stream_status().state == "streaming"
        for k in range(75):
            drv.stream(p0 + (end - p0) * min(k / 25, 1.0), k / 125.0)
            time.sleep(1 / 125.0)
        with pytest.raises(DriverError):
            drv.stream(np.array([np.nan, 0.0, 0.5]), 1.0)
        status = drv.stream_status()
        assert status.sent == 75 and (status.rate_hz, status.lookahead_s, status.gain) == (125.0, 0.1, 300.0)
        drv.stop_stream()
        assert drv.stream_status().state == "idle"
        assert np.linalg.norm(drv.read_commanded_tcp() - end) < 1e-4, drv.read_commanded_tcp() - end


def robot_refuses_nan_target(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        with pytest.raises(DriverError):
            drv.move_linear(np.array([np.nan, 0.0, 0.5]), 0.1)
        assert np.all(np.isfinite(drv.read_commanded_tcp()))


def robot_abort_refuses_moves_until_cleared(factory):
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


def robot_close_is_idempotent_from_active(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        drv.close()
        drv.close()
        assert drv.state == "closed"
        with pytest.raises(StateError):
            drv.read_joint_state()


def counters_answer_in_every_state(factory):
    """A driver that keeps counters (`counters()`: no I/O, read by the health report from another
    thread) answers in every state, before activate() and after close() included: a report must not
    depend on the driver's lifecycle."""
    with factory() as (drv, config):
        counters = getattr(drv, "counters", None)
        if counters is None:
            pytest.skip("this driver keeps no counters")
        seen = [counters()]
        drv.configure(config)
        seen.append(counters())
        drv.activate()
        seen.append(counters())
        drv.close()
        seen.append(counters())
        assert all(isinstance(c, dict) and all(isinstance(v, (int, float)) for v in c.values()) for c in seen), seen


# --- laser trackers ---------------------------------------------------------------------
def tracker_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, LaserTracker)
        check_lifecycle_order(drv, config, [drv.measure])


def tracker_measure_is_consistent(factory):
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        for _ in range(5):
            r = timed(drv.measure)
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
def camera_satisfies_protocol_and_lifecycle_order(factory):
    with factory() as (drv, config):
        assert isinstance(drv, CameraRig)
        check_lifecycle_order(drv, config, [drv.read])


def camera_read_is_consistent(factory):
    """A reading is either a point with a covariance or a refusal with its reason, never both."""
    with factory() as (drv, config):
        drv.configure(config)
        drv.activate()
        n_ok = 0
        for _ in range(4):
            r = timed(drv.read)
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
    "robot": [robot_satisfies_protocol_and_lifecycle_order, robot_move_then_read,
              robot_refuses_nan_target, robot_abort_refuses_moves_until_cleared,
              robot_close_is_idempotent_from_active, robot_streams_setpoints],
    "tracker": [tracker_satisfies_protocol_and_lifecycle_order, tracker_measure_is_consistent],
    "camera": [camera_satisfies_protocol_and_lifecycle_order, camera_read_is_consistent],
}


def run_suite(kind: str, factory: Factory) -> list[str]:
    """Every check of `kind` on `factory` (a plugin's test calls this); returns the checks' names."""
    for check in CHECKS[kind]:
        check(factory)
    return [c.__name__ for c in CHECKS[kind]]
