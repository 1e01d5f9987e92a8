"""Set-points streamed to a Universal Robots controller over RTDE input registers (issue 23, item 3):
the driver against the emulator on loopback over the simulated plant. The emulator runs the
driver's servo program (servoj with look-ahead and gain, a watchdog of N control cycles) with the
follower of sim.servo, so its logs show what the controller took, cycle by cycle.

Load-proof: the host paces its set-points with sleep, but nothing asserts on time: the checks are
on the registers' arrival order, the emulator's control-cycle counts and a replay of the follower
over the targets the controller took."""
from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.ur import protocol as rp
from drivers.ur import urscript
from dt_kernel.errors import ConfigError, DriverError, StateError
from tests.support.loopback import wait_until

SCENARIO, CELL = "configs/scenarios/paper_default.yaml", "configs/cell.yaml"
RATE = 125.0  # a CB3's control loop (servoj t = 0.008 s)


@pytest.fixture
def world():
    from pathlib import Path

    from drivers.simulated.devices import SimWorld

    root = Path(__file__).resolve().parents[2]
    w = SimWorld(root / SCENARIO, root / CELL, seed=11)
    yield w
    w.close()


def _emulator(world, **kw):
    from emulators.ur import UrEmulator

    return UrEmulator(world.cell.plant, "127.0.0.1", 0, 0, **kw)


@pytest.fixture
def emu(world):
    e = _emulator(world)
    yield e
    e.stop()


def _driver(emu, **stream):
    from drivers.ur.driver import UrRtdeController

    return UrRtdeController.from_config({"host": "127.0.0.1", "rtde_port": emu.rtde_port,
                                         "script_port": emu.script_port, "timeout_s": 5.0, "stream": stream},
                                        source="<test>")


@pytest.fixture
def drv(emu):
    d = _driver(emu, watchdog_cycles=250)  # 2 s at 125 Hz: a loaded machine's host never trips it
    d.activate()
    yield d
    d.close()


def _paced(drv, points, t0: float = 0.0) -> None:
    """Stream `points` at RATE, one per period of the host's clock (sleep pacing, no assertion)."""
    start = time.monotonic()
    for k, p in enumerate(points):
        drv.stream(p, t0 + k / RATE)
        time.sleep(max(0.0, start + (k + 1) / RATE - time.monotonic()))


def _seqs(emu, register: int = 24) -> list[int]:
    return [int(v[f"input_int_register_{register}"]) for v in list(emu.input_writes)]


def test_a_streamed_line_arrives_once_in_order_and_the_servo_lags_then_overshoots(drv, emu):
    p0 = drv.read_commanded_tcp()
    ramp = [p0 + np.array([0.1 * k / RATE, 0.0, 0.0]) for k in range(1, 51)]  # 40 mm at 100 mm/s
    hold = [ramp[-1]] * 40
    # look-ahead 0.03 s, gain 1200: the parameters of the public reports (~34 ms of lag), under-damped
    drv.start_stream(RATE, 0.03, 1200.0)
    _paced(drv, ramp + hold)
    n = len(ramp) + len(hold)
    # every set-point written once, in order (1: start_stream's hold of the current pose)
    assert _seqs(emu) == list(range(1, n + 2))
    wait_until(lambda: drv.stream_status().consumed == n, 5.0)
    status = drv.stream_status()
    assert (status.state, status.sent, status.consumed) == ("streaming", n, n)
    with pytest.raises(StateError, match="a stream is running"):  # a movel would replace the servo program
        drv.move_linear(p0, 0.1)
    assert emu.stats["scripts"] == 1
    drv.stop_stream()
    assert emu.stats["host_stops"] == 1 and emu.stats["watchdog_stops"] == 0
    assert emu.register("output_int_register_24") == urscript.STREAM_HOST_STOP

    # the controller took the set-points in order; replaying the servo model over the targets it
    # took, cycle by cycle, gives exactly the positions it commanded the plant
    from sim.servo import ServoFollower

    log = list(emu.servo_log)
    taken = [s for s, _ in log]
    assert taken == sorted(taken) and taken[-1] == n + 1
    target = {1: p0, **{k + 2: p for k, p in enumerate(ramp + hold)}}
    f = ServoFollower(p0, 0.03, 1200.0)
    replay = np.array([f.step(target[s], 1 / RATE)[0] for s, _ in log])
    assert np.allclose(replay, [x for _, x in log], atol=1e-12)
    x = np.array([x for _, x in log])[:, 0]
    lag = np.array([target[s][0] for s in taken]) - x
    ramp_cycles = [i for i, s in enumerate(taken) if 10 < s <= len(ramp) + 1]
    assert lag[ramp_cycles].max() > 1e-3  # trails the moving target (3 mm = 100 mm/s x 0.03 s at full pace)
    assert x.max() - ramp[-1][0] > 1e-5  # and overshoots when it stops (zeta 0.52)
    assert abs(x[-1] - ramp[-1][0]) < 1e-4  # settles at the end of the line
    # the plant is where the follower put it: the controller's TCP reads it back
    assert np.allclose(drv.read_commanded_tcp(), emu.servo_log[-1][1], atol=2e-6)


def test_the_watchdog_stops_the_arm_when_the_host_stops_streaming(emu):
    drv = _driver(emu, watchdog_cycles=10)
    drv.activate()
    try:
        p0 = drv.read_commanded_tcp()
        drv.start_stream(RATE, 0.1, 300.0)
        for k in range(1, 11):  # written back to back: the controller takes the newest
            drv.stream(p0 + np.array([0.0, 0.002 * k, 0.0]), k / RATE)
        # ... and then the host goes quiet
        assert wait_until(lambda: drv.stream_status().state == "stopped", 10.0)
        assert emu.stats["watchdog_stops"] == 1 and emu.stats["host_stops"] == 0
        assert emu.register("output_int_register_24") == urscript.STREAM_WATCHDOG
        # counted in the controller's cycles: the cycle that took the last set-point, then 10 quiet ones
        last = [s for s, _ in emu.servo_log if s == 11]
        assert len(last) == 1 + 10
        cycles = emu.stats["servo_cycles"]
        assert wait_until(lambda: drv.read_sample().values["runtime_state"] == rp.RUNTIME_STOPPED, 5.0)
        assert np.allclose(drv.read_sample().values["actual_TCP_speed"], 0.0)  # stopj: standing still
        sent = emu.stats["input_packages"]
        with pytest.raises(DriverError, match="watchdog stopped the arm: no new set-point for 10 control cycles"):
            drv.stream(p0, 1.0)
        assert emu.stats["input_packages"] == sent and emu.stats["servo_cycles"] == cycles  # nothing sent, nothing ran
        status = drv.stream_status()
        assert status.state == "stopped" and "watchdog" in status.reason and status.sent == 10
    finally:
        drv.close()


def test_a_protective_stop_mid_stream_is_refused_with_its_reason_then_resumed(drv, emu):
    p0 = drv.read_commanded_tcp()
    drv.start_stream(RATE, 0.1, 300.0)
    _paced(drv, [p0 + np.array([0.0, 0.0, -0.1 * k / RATE]) for k in range(1, 21)])
    emu.inject_protective_stop()
    assert wait_until(lambda: drv.read_sample().values["safety_mode"] == rp.SAFETY_PROTECTIVE_STOP, 5.0)
    sent, cycles = emu.stats["input_packages"], emu.stats["servo_cycles"]
    with pytest.raises(DriverError, match="set-point 21 not sent: protective stop: the arm stopped at"):
        drv.stream(p0, 1.0)
    assert emu.stats["input_packages"] == sent and emu.stats["servo_cycles"] == cycles
    assert drv.stream_status().state == "stopped" and "protective stop" in drv.stream_status().reason
    with pytest.raises(DriverError, match="protective stop"):  # and it stays refused
        drv.stream(p0, 1.1)
    # resumed from where it stopped, once the stop is cleared: a new stream, set-points counted anew
    stopped_at = drv.read_commanded_tcp()
    emu.unlock_protective_stop()
    assert wait_until(lambda: drv.read_sample().values["safety_mode"] == rp.SAFETY_NORMAL, 5.0)
    drv.start_stream(RATE, 0.1, 300.0)
    _paced(drv, [stopped_at + np.array([0.001 * k / 10, 0.0, 0.0]) for k in range(1, 11)])
    assert drv.stream_status().sent == 10 and emu.stats["servo_programs"] == 2
    drv.stop_stream()


def test_rtde_dropped_mid_stream_stops_it_the_watchdog_stops_the_arm_and_a_new_stream_resumes(emu):
    # reconnection held off for a second, so the refusal is seen while the connection is down
    from drivers.ur.driver import UrRtdeController

    drv = UrRtdeController.from_config({"host": "127.0.0.1", "rtde_port": emu.rtde_port,
                                        "script_port": emu.script_port, "timeout_s": 5.0,
                                        "reconnect_interval_s": 1.0, "stream": {"watchdog_cycles": 25}})
    drv.activate()
    try:
        p0 = drv.read_commanded_tcp()
        drv.start_stream(RATE, 0.1, 300.0)
        _paced(drv, [p0 + np.array([0.0005 * k, 0.0, 0.0]) for k in range(1, 6)])
        emu.inject_drop(after_packages=0)
        assert wait_until(lambda: drv.link.stats["drops"] == 1, 5.0)
        sent = emu.stats["input_packages"]
        with pytest.raises(DriverError, match="set-point 6 not sent: the RTDE connection is down"):
            drv.stream(p0 + np.array([0.003, 0.0, 0.0]), 1.0)
        assert emu.stats["input_packages"] == sent
        # the controller's watchdog stops the arm; the restored connection does not revive the stream
        assert wait_until(lambda: emu.stats["watchdog_stops"] == 1, 10.0)
        assert wait_until(lambda: drv.link.stats["connects"] == 2, 10.0)
        with pytest.raises(DriverError, match="connection is down"):
            drv.stream(p0 + np.array([0.003, 0.0, 0.0]), 1.1)
        assert _seqs(emu) == list(range(1, 7))  # nothing written twice
        # resumed where the arm stands, as a new stream
        here = drv.read_commanded_tcp()
        drv.start_stream(RATE, 0.1, 300.0)
        _paced(drv, [here + np.array([0.0005 * k, 0.0, 0.0]) for k in range(1, 4)])
        drv.stop_stream()
        assert emu.stats["servo_programs"] == 2 and emu.stats["host_stops"] == 1
    finally:
        drv.close()


def test_input_registers_taken_by_a_fieldbus_are_a_config_error_naming_them(world):
    from emulators.ur import UrFaults

    with _emulator(world, faults=UrFaults(taken_inputs=("input_double_register_27",))) as emu:
        drv = _driver(emu)
        with pytest.raises(ConfigError, match="IN_USE for input_double_register_27") as ei:
            drv.activate()
        assert ei.value.key == "stream" and "choose another range" in str(ei.value)
        drv.close()
        # another range is free
        other = _driver(emu, double_register=30, seq_register=25, status_register=30)
        other.activate()
        other.close()


def test_registers_held_by_another_client_are_in_use_until_it_disconnects(emu):
    first = _driver(emu)
    first.activate()
    try:
        second = _driver(emu)
        with pytest.raises(ConfigError, match="IN_USE for input_int_register_24, input_double_register_24"):
            second.activate()
        second.close()
        # streaming disabled: the registers are not claimed, moving and reading work as before
        idle = _driver(emu, enabled=False)
        idle.activate()
        with pytest.raises(ConfigError, match="stream.enabled"):
            idle.start_stream(RATE)
        idle.close()
    finally:
        first.close()
    assert wait_until(lambda: not emu._input_owner, 5.0)  # released with the connection
    third = _driver(emu)
    third.activate()
    third.close()


# --- a third-party RTDE client reads the register interface ---------------------------
def test_ur_rtde_reads_the_registers_of_our_stream(tmp_path):
    """ur_rtde's receive interface (SDU's C++ client) reads the output registers the servo program
    writes while we stream: its state (1 running, 3 stopped by the host) and the sequence number
    it took from the input register our driver writes. (ur_rtde 1.6.5's receive interface has no
    getter for input registers: its recorder refuses `input_double_register_N` keys, so the inputs
    are read back through the program's copy.)"""
    rtde_receive = pytest.importorskip(
        "rtde_receive", reason="the third-party RTDE client `ur_rtde` is not installed (pip install ur_rtde)")
    from drivers.ur.driver import UrRtdeController
    from tests.support.ur_emulator_process import ur_emulator_process

    with ur_emulator_process("--seed", "3", seed=23) as (host, script_port):
        # status in the upper range ur_rtde reads (output int registers 36-43)
        ours = UrRtdeController.from_config({"host": host, "script_port": script_port, "timeout_s": 5.0,
                                             "stream": {"status_register": 36, "watchdog_cycles": 5000}})
        ours.activate()
        try:
            p0 = ours.read_commanded_tcp()
            ours.start_stream(RATE, 0.1, 300.0)
            _paced(ours, [p0 + np.array([0.0005 * k, 0.0, 0.0]) for k in range(1, 6)])
            theirs = rtde_receive.RTDEReceiveInterface(host, RATE, ["timestamp", "output_int_register_36",
                                                                    "output_int_register_37"], False, True)
            try:
                assert wait_until(lambda: theirs.getOutputIntRegister(37) == 6, 10.0), theirs.getOutputIntRegister(37)
                assert theirs.getOutputIntRegister(36) == urscript.STREAM_RUNNING
                _paced(ours, [p0 + np.array([0.003, 0.0, 0.0])] * 3, t0=1.0)
                assert wait_until(lambda: theirs.getOutputIntRegister(37) == 9, 10.0)
                ours.stop_stream()
                assert wait_until(lambda: theirs.getOutputIntRegister(36) == urscript.STREAM_HOST_STOP, 10.0)
            finally:
                theirs.disconnect()
        finally:
            ours.close()
