"""Serial controller and tracker drivers against the emulators on a real pseudo-terminal."""
import math
import threading
import time

import numpy as np
import pytest
import serial

from drivers.base import LaserTracker, RobotController
from drivers.serial import protocol as lp
from drivers.serial.controller import SerialController
from drivers.serial.tracker import SerialTracker
from dt_kernel.errors import ConfigError, DriverError, StateError, UnreachableError
from dt_kernel.geometry import spherical_to_cartesian
from emulators.serial import ControllerEmulator, Faults, TrackerEmulator
from tests.support.serial_plant import HOME, FakePlant


@pytest.fixture
def plant():
    return FakePlant()


def make(plant, faults=None, endpoint=None, **cfg):
    emu = ControllerEmulator(plant, endpoint, faults=faults)
    drv = SerialController({"url": emu.port, "timeout_s": 0.2, "move_timeout_s": 0.5, "retries": 3, **cfg})
    drv.activate()
    return emu, drv


@pytest.fixture
def rig(plant):
    emu, drv = make(plant)
    yield emu, drv
    drv.close()
    emu.stop()


# --- codec ------------------------------------------------------------------------------
def test_crc_is_ccitt_false():
    assert lp.crc16(b"123456789") == 0x29B1  # the catalogue check value of CRC-16/CCITT-FALSE


def test_codec_round_trip_is_exact_and_resyncs_on_last_frame_start():
    x = 0.1 + 0.2  # not representable in short decimal: repr must round-trip it
    line = lp.encode(65535, "MOVL", x, -1e-9, 3, "ok")
    assert line.endswith(b"\n") and line.startswith(b"$65535,MOVL,")
    f = lp.decode(b"$12,ACK,0.5" + line)  # half-written frame glued in front
    assert f == lp.Frame(65535, "MOVL", (repr(x), "-1e-09", "3", "ok"))
    assert float(f.fields[0]) == x
    assert lp.next_seq(65535) == 0


def test_codec_rejects_bad_checksum_garbage_and_reserved_characters():
    good = lp.encode(7, "GETJ")
    bad = good.replace(b"GETJ", b"GETT")
    with pytest.raises(lp.ChecksumError) as err:
        lp.decode(bad)
    assert err.value.seq == 7
    for junk in (b"", b"hello", b"$7,GETJ", b"$7,GETJ*12", b"\x00\xff$,*ZZZZ"):
        with pytest.raises(lp.FrameError):
            lp.decode(junk)
    for field in ("a,b", "a*b", "$", "tab\there"):
        with pytest.raises(lp.FrameError):
            lp.encode(1, "X", field)
    assert isinstance(lp.FrameError("x"), DriverError)


def test_line_buffer_splits_lines_and_bounds_noise():
    buf = lp.LineBuffer(max_line=64)
    assert buf.feed(b"ab") == []
    assert buf.feed(b"c\n$1,PING*0000\nxy") == [b"abc", b"$1,PING*0000"]
    buf.feed(b"z" * 1000)  # endless noise without newline
    assert len(buf._buf) <= 64


# --- controller round trip --------------------------------------------------------------
def test_round_trip_move_and_read(rig, plant):
    emu, drv = rig
    assert isinstance(drv, RobotController)
    target = np.array([0.6, -0.2, 0.4])
    drv.move_linear(target, 0.25)
    assert len(plant.moves) == 1 and np.array_equal(plant.moves[0][0], target) and plant.moves[0][1] == 0.25
    assert np.array_equal(drv.read_commanded_tcp(), target)  # exact: floats travel as repr
    js = drv.read_joint_state()
    assert js.q.shape == (6,) and np.array_equal(js.q, np.concatenate([target, -target]))
    assert math.isfinite(js.t)
    assert drv.status() == {"state": "idle", "moves": 1}
    assert drv.link.stats["retries"] == 0


def test_same_driver_over_socket_url(plant):
    emu, drv = make(plant, endpoint="tcp://127.0.0.1:0")
    try:
        assert emu.port.startswith("socket://")
        drv.move_linear([0.5, 0.1, 0.3], 0.5)
        assert np.array_equal(drv.read_commanded_tcp(), [0.5, 0.1, 0.3])
        emu.pause(0.35)  # forces a reconnect: a new TCP connection
        assert np.array_equal(drv.read_commanded_tcp(), [0.5, 0.1, 0.3])
        assert drv.link.stats["reconnects"] >= 1
    finally:
        drv.close()
        emu.stop()


def test_streamed_setpoint_is_acknowledged_before_the_move_ends():
    plant = FakePlant(move_delay_s=2.0)
    emu, drv = make(plant, timeout_s=4.0)
    try:
        drv.stream_setpoint([0.5, 0.0, 0.5], 0.3)
        assert plant.moves == []  # acknowledged while the plant still moves (no clock read: load-proof)
        assert np.array_equal(drv.read_commanded_tcp(), [0.5, 0.0, 0.5])  # served after the move
        assert len(plant.moves) == 1
    finally:
        drv.close()
        emu.stop()


def test_sequence_number_wraps(rig):
    emu, drv = rig
    drv.link._seq = 65534
    for _ in range(3):
        drv.read_commanded_tcp()
    assert drv.link._seq == 1 and drv.link.stats["retries"] == 0


# --- line faults ------------------------------------------------------------------------
def test_garbage_lines_are_ignored(plant):
    emu, drv = make(plant, faults=Faults(garbage=1.0, seed=3))
    try:
        for i in range(5):
            drv.move_linear([0.5, 0.0, 0.3 + 0.01 * i], 0.5)
            assert np.allclose(drv.read_commanded_tcp(), [0.5, 0.0, 0.3 + 0.01 * i])
        assert drv.link.stats["garbage"] >= 10 and drv.link.stats["retries"] == 0
    finally:
        drv.close()
        emu.stop()


def test_emulator_ignores_garbage_and_naks_bad_checksum_on_the_wire(rig):
    emu, drv = rig
    drv.deactivate()  # free the line; talk raw pyserial to the device
    with serial.serial_for_url(emu.port, timeout=0.3) as port:
        port.write(b"\x01\x02 just noise\n")
        port.write(b"$41,GETJ*0000\n")  # frame-shaped, wrong CRC
        assert lp.decode(port.readline()) == lp.Frame(41, lp.NAK, (lp.NAK_CRC,))
        port.write(lp.encode(42, "FOO"))
        reply = lp.decode(port.readline())
        assert (reply.seq, reply.word, reply.nak_reason) == (42, lp.NAK, lp.NAK_UNKNOWN)
        port.write(lp.encode(43, "MOVL", "nan", 0.0, 0.5, 0.1))
        assert lp.decode(port.readline()).nak_reason == lp.NAK_RANGE
        port.write(lp.encode(44, "MOVL", 0.5))
        assert lp.decode(port.readline()).nak_reason == lp.NAK_SYNTAX
    assert emu.stats["garbage_in"] == 1 and emu.stats["nak_crc"] == 1


def test_half_written_frame_is_survived(rig, plant):
    emu, drv = rig
    emu.inject("half_frame", 3)
    drv.move_linear([0.4, 0.1, 0.2], 0.5)
    assert np.array_equal(drv.read_commanded_tcp(), [0.4, 0.1, 0.2])
    assert drv.read_joint_state().q.shape == (6,)
    assert drv.link.stats["retries"] == 0 and len(plant.moves) == 1


def test_bad_checksum_is_nakked_and_retried_once(rig, plant):
    emu, drv = rig
    emu.inject("corrupt_request")
    drv.move_linear([0.4, 0.0, 0.5], 0.5)
    assert emu.stats["nak_crc"] == 1
    assert drv.link.stats["naks"] == 1 and drv.link.stats["retries"] == 1
    assert len(plant.moves) == 1


@pytest.mark.parametrize("fault, counter", [("corrupt_reply", "corrupt"), ("drop", "timeouts")])
def test_lost_or_corrupt_reply_is_retried_without_moving_twice(rig, plant, fault, counter):
    emu, drv = rig
    emu.inject(fault)
    drv.move_linear([0.4, 0.2, 0.5], 0.5)
    assert drv.link.stats[counter] == 1 and drv.link.stats["retries"] == 1
    assert emu.stats["duplicates"] == 1  # the retransmission was answered from the reply cache
    assert len(plant.moves) == 1


def test_stale_reply_with_wrong_seq_is_discarded(rig):
    emu, drv = rig
    for _ in range(3):
        drv.status()  # fill the device's reply history with 2-field STATUS replies
    emu.inject("stale", 2)
    tcp = drv.read_commanded_tcp()  # a stale 2-field reply would fail the 4-field check
    js = drv.read_joint_state()
    assert np.array_equal(tcp, HOME) and js.q.shape == (6,)
    assert drv.link.stats["stale"] == 2 and drv.link.stats["retries"] == 0


def test_seeded_reply_drops_are_recovered(plant):
    emu, drv = make(plant, faults=Faults(drop=0.3, seed=11), timeout_s=0.05,
                     move_timeout_s=0.05, retries=10)
    try:
        for i in range(20):
            drv.move_linear([0.5, 0.01 * i, 0.4], 0.5)
            assert np.allclose(drv.read_commanded_tcp(), [0.5, 0.01 * i, 0.4])
        assert drv.link.stats["timeouts"] > 0
        assert len(plant.moves) == 20  # every move executed exactly once
    finally:
        drv.close()
        emu.stop()


# --- device stops answering -------------------------------------------------------------
def test_device_pause_then_recovery_with_reconnect(rig):
    emu, drv = rig  # timeout 0.2 s, 3 retries, reconnect after 2 time-outs
    emu.pause(0.5)
    assert np.array_equal(drv.read_commanded_tcp(), HOME)
    st = drv.link.stats
    assert st["timeouts"] >= 2 and st["reconnects"] >= 1


def test_device_silent_too_long_raises_driver_error_then_works_again(rig):
    emu, drv = rig
    emu.pause(30.0)
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="after 4 attempts") as err:
        drv.read_joint_state()
    assert 0.75 < time.monotonic() - t0 < 5.0  # 4 attempts x 0.2 s, plus reconnects
    assert "no reply within 0.2 s" in str(err.value)
    assert drv.state == "active" and drv.link.stats["reconnects"] == 2
    emu.pause(0.0)  # the device comes back
    assert np.array_equal(drv.read_commanded_tcp(), HOME)


def test_activate_fails_cleanly_when_nothing_answers(plant):
    emu = ControllerEmulator(plant)
    try:
        emu.pause(5.0)
        drv = SerialController({"url": emu.port, "timeout_s": 0.05, "retries": 1})
        with pytest.raises(DriverError, match="PING"):
            drv.activate()
        assert drv.state == "inactive" and not drv.link.is_open
        drv.close()
    finally:
        emu.stop()
    missing = SerialController({"url": "/dev/does-not-exist-tty", "retries": 0})
    with pytest.raises(DriverError, match="cannot open") as err:
        missing.activate()
    assert err.value.__cause__ is not None


# --- values: NaN, range, refusal --------------------------------------------------------
def test_nan_from_device_is_rejected_and_link_stays_usable(rig, plant):
    emu, drv = rig
    emu.inject("nan")
    with pytest.raises(DriverError, match="non-finite"):
        drv.read_joint_state()
    emu.inject("nan")
    with pytest.raises(DriverError, match="non-finite"):
        drv.read_commanded_tcp()
    plant.bad_joint = 7.0  # beyond the 2 pi joint limit
    with pytest.raises(DriverError, match="outside"):
        drv.read_joint_state()
    plant.bad_joint = None
    assert drv.read_joint_state().q.shape == (6,)


def test_bad_commands_are_refused_before_sending(rig):
    emu, drv = rig
    before = emu.stats["requests"]
    for target, speed in (([np.nan, 0, 0.5], 0.1), ([0.5, 0, 9.0], 0.1), ([0.5, 0, 0.5], 0.0),
                          ([0.5, 0, 0.5], 5.0), ([0.5, 0.5], 0.1)):
        with pytest.raises(DriverError):
            drv.move_linear(np.array(target, dtype=float), speed)
    assert emu.stats["requests"] == before


def test_unreachable_target_surfaces_as_unreachable_error(rig, plant):
    emu, drv = rig
    with pytest.raises(UnreachableError, match="unreachable"):
        drv.move_linear([1.4, 1.0, 0.5], 0.2)
    assert drv.status()["state"] == "fault" and plant.moves == []


# --- config and lifecycle ---------------------------------------------------------------
def test_config_is_validated_with_key_value_and_allowed():
    with pytest.raises(ConfigError, match="url"):
        SerialController({})
    with pytest.raises(ConfigError, match="retries") as err:
        SerialController({"url": "/dev/null", "retries": -1})
    assert err.value.value == -1
    with pytest.raises(ConfigError, match="limits.max_speed"):
        SerialController({"url": "/dev/null", "limits": {"max_speed": 1.0}})
    with pytest.raises(ConfigError):
        Faults(drop=2.0)
    with pytest.raises(ConfigError):
        ControllerEmulator(FakePlant(), "/dev/ttyS99")


def test_lifecycle_violations_raise_state_error(plant):
    drv = SerialController()
    with pytest.raises(StateError):
        drv.read_joint_state()
    with pytest.raises(StateError):
        drv.activate()
    emu = ControllerEmulator(plant)
    try:
        drv.configure({"url": emu.port})
        with pytest.raises(StateError):
            drv.move_linear(HOME, 0.1)
        drv.activate()
        with pytest.raises(StateError):
            drv.configure({"url": emu.port})
        drv.close()
        drv.close()
        with pytest.raises(StateError):
            drv.read_commanded_tcp()
        assert not drv.link.is_open
    finally:
        emu.stop()
    emu.stop()  # idempotent


def test_driver_is_safe_to_share_between_threads(rig, plant):
    emu, drv = rig
    errors = []

    def worker(k):
        try:
            for i in range(10):
                drv.read_joint_state()
                drv.stream_setpoint([0.5, 0.01 * k, 0.3 + 0.001 * i], 0.5)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and drv.link.stats["retries"] == 0
    assert drv.status()["moves"] == 30


# --- tracker ----------------------------------------------------------------------------
class FakeTracker:
    def __init__(self, readings):
        self.readings = list(readings)

    def __call__(self):
        return self.readings.pop(0)


def make_tracker(readings, faults=None):
    emu = TrackerEmulator(FakeTracker(readings), faults=faults)
    drv = SerialTracker({"url": emu.port, "timeout_s": 0.2, "retries": 2})
    drv.activate()
    return emu, drv


def test_tracker_measures_and_beam_broken_surfaces_as_status():
    nan = float("nan")
    emu, drv = make_tracker([(2.5, 0.3, -0.1, "ok"), (nan, nan, nan, "beam_broken"), (2.4, 0.2, 0.1, "ok")])
    try:
        assert isinstance(drv, LaserTracker)
        r = drv.measure()
        assert r.ok and r.spherical == (2.5, 0.3, -0.1)
        assert np.allclose(r.point, spherical_to_cartesian(2.5, 0.3, -0.1), atol=0, rtol=1e-15)
        r = drv.measure()
        assert r.status == "beam_broken" and not r.ok and np.all(np.isnan(r.point))
        assert drv.measure().ok
    finally:
        drv.close()
        emu.stop()


def test_tracker_rejects_nan_and_out_of_range_and_recovers_from_faults():
    emu, drv = make_tracker([(2.0, 0.1, 0.1, "ok"), (2.0, 0.1, 2.0, "ok"), (-1.0, 0.1, 0.1, "ok"),
                             (2.0, 0.1, 0.1, "ok")])
    try:
        emu.inject("nan")
        with pytest.raises(DriverError, match="non-finite"):
            drv.measure()
        with pytest.raises(DriverError, match="elevation"):
            drv.measure()
        with pytest.raises(DriverError, match="MEAS d"):
            drv.measure()
        emu.inject("half_frame")
        emu.inject("corrupt_request")
        assert drv.measure().ok
        assert emu.stats["nak_crc"] == 1
    finally:
        drv.close()
        emu.stop()
