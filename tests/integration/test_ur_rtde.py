"""Universal Robots over RTDE: the codec, the URScript subset, the driver against the emulator
on loopback over the simulated plant (moves, faults through the real protocols), and the
third-party `ur_rtde` receive client reading our emulator."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.ur import protocol as rp
from drivers.ur import urscript


# --- codec ------------------------------------------------------------------------------
def test_header_is_big_endian_size_then_type():
    pkg = rp.protocol_version_request(2)
    assert pkg == b"\x00\x05V\x00\x02"  # size 5 (header included), 'V' = 86, uint16 2
    assert rp.pack(rp.START) == b"\x00\x03S"


def test_package_reader_splits_a_stream_fed_byte_by_byte():
    stream = rp.protocol_version_request(2) + rp.text_message("hello", "emu", rp.ERROR_MESSAGE) + rp.pack(rp.PAUSE)
    reader, got = rp.PackageReader(), []
    for b in stream:
        got.extend(reader.feed(bytes([b])))
    assert [t for t, _ in got] == [rp.REQUEST_PROTOCOL_VERSION, rp.TEXT_MESSAGE, rp.PAUSE]
    assert rp.parse_protocol_version_request(got[0][1]) == 2
    msg = rp.parse_text_message(got[1][1])
    assert (msg.message, msg.source, msg.level, msg.is_error) == ("hello", "emu", rp.ERROR_MESSAGE, True)


def test_bad_size_is_a_protocol_error():
    with pytest.raises(rp.ProtocolError, match="smaller than its header"):
        list(rp.PackageReader().feed(b"\x00\x01U"))


def test_setup_outputs_round_trip():
    names = ["timestamp", "actual_q", "robot_mode"]
    (ptype, payload), = rp.PackageReader().feed(rp.setup_outputs_request(names, 125.0))
    assert ptype == rp.SETUP_OUTPUTS and payload[:8] == struct.pack(">d", 125.0)
    assert rp.parse_setup_outputs_request(payload) == (125.0, names)
    (_, reply), = rp.PackageReader().feed(rp.setup_reply(rp.SETUP_OUTPUTS, 1, ["DOUBLE", "VECTOR6D", "INT32"]))
    assert rp.parse_setup_reply(reply) == (1, ["DOUBLE", "VECTOR6D", "INT32"])


def test_data_package_round_trip_every_type():
    types = ("BOOL", "UINT8", "UINT32", "UINT64", "INT32", "DOUBLE", "VECTOR3D", "VECTOR6D", "VECTOR6INT32",
             "VECTOR6UINT32")
    names = tuple(f"f{i}" for i in range(len(types)))
    values = [True, 200, 4_000_000_000, 2**60, -7, 0.125, (1.0, 2.0, 3.0), tuple(np.linspace(-1, 1, 6)),
              (-3, -2, -1, 0, 1, 2), (0, 1, 2, 3, 4, 5)]
    recipe = rp.Recipe(3, names, types)
    (ptype, payload), = rp.PackageReader().feed(recipe.pack(values))
    assert ptype == rp.DATA_PACKAGE and rp.data_recipe_id(payload) == 3
    got = recipe.unpack(payload)
    assert list(got.values()) == [tuple(v) if isinstance(v, tuple) else v for v in values]
    # 1 id + 1 + 1 + 4 + 8 + 4 + 8 + 24 + 48 + 24 + 24 bytes, no padding
    assert len(payload) == 1 + 1 + 1 + 4 + 8 + 4 + 8 + 24 + 48 + 24 + 24


def test_data_package_of_the_wrong_size_or_recipe_is_refused():
    recipe = rp.Recipe(1, ("timestamp",), ("DOUBLE",))
    with pytest.raises(rp.ProtocolError, match="expected 9"):
        recipe.unpack(b"\x01" + b"\x00" * 4)
    with pytest.raises(rp.ProtocolError, match="for recipe 2"):
        recipe.unpack(b"\x02" + b"\x00" * 8)
    with pytest.raises(rp.ProtocolError, match="without a data type"):
        rp.Recipe(1, ("nope",), (rp.NOT_FOUND,))


def test_urcontrol_version_round_trip():
    (_, payload), = rp.PackageReader().feed(rp.urcontrol_version_reply(5, 11, 2, 108))
    assert rp.parse_urcontrol_version(payload) == (5, 11, 2, 108)


# --- URScript ---------------------------------------------------------------------------
def test_movel_text_parses_back_exactly_to_the_nanometre():
    pose = [0.81234567891, -0.1, 0.5, 0.0, 3.14159265359, -1e-12]
    text = urscript.movel(pose, 1.2, 0.25)
    assert text.startswith("movel(p[0.812345679,-0.100000000,") and text.endswith(", a=1.200000000, v=0.250000000)\n")
    (cmd,) = urscript.parse(text)
    assert cmd.kind == "movel" and cmd.a == 1.2 and cmd.v == 0.25 and cmd.q is None
    assert np.allclose(cmd.pose, pose, atol=1e-9)


def test_program_block_and_joint_moves_parse():
    prog = ("def move():\n  movej([0,0.1,0.5,0,0.9,0], a=1.4, v=1.05)  # home\n"
            "  movel(p[.9,0,.7,0,3.1,0], a=1, v=.2)\n  stopl(2)\nend\n")
    cmds = urscript.parse(prog)
    assert [c.kind for c in cmds] == ["movej", "movel", "stopl"]
    assert cmds[0].q == (0, 0.1, 0.5, 0, 0.9, 0) and cmds[2].a == 2.0


@pytest.mark.parametrize("bad", [
    "set_digital_out(1, True)\n", "movel([0,0,0,0,0,0], a=1, v=1)\n", "movel(p[0,0,0], a=1, v=1)\n",
    "movel(p[0,0,0,0,0,0], a=1, v=0)\n", "def f():\n movel(p[0,0,0,0,0,0], a=1, v=1)\n", "",
    "movel(p[nan,0,0,0,0,0], a=1, v=1)",
])
def test_anything_else_is_a_script_error(bad):
    with pytest.raises(urscript.ScriptError):
        urscript.parse(bad)


def test_non_finite_numbers_are_never_written():
    with pytest.raises(urscript.ScriptError):
        urscript.movel([float("nan"), 0, 0, 0, 0, 0], 1.2, 0.1)


# --- the driver against the emulator over the simulated plant ---------------------------
SCENARIO, CELL = "configs/scenarios/paper_default.yaml", "configs/cell.yaml"
TIME_SCALE = 0.25  # the emulated arm moves 4x faster than the profile (tests stay short)


@pytest.fixture
def world():
    from pathlib import Path

    from drivers.simulated.devices import SimWorld

    root = Path(__file__).resolve().parents[2]
    w = SimWorld(root / SCENARIO, root / CELL, seed=11)
    yield w
    w.close()


@pytest.fixture
def emu(world):
    from emulators.ur import UrEmulator

    e = UrEmulator(world.cell.plant, "127.0.0.1", 0, 0, time_scale=TIME_SCALE)
    yield e
    e.stop()


def ur_config(emu, **over):
    return {"host": "127.0.0.1", "rtde_port": emu.rtde_port, "script_port": emu.script_port,
            "frequency_hz": 125.0, "timeout_s": 2.0, "move_timeout_s": 10.0, **over}


@pytest.fixture
def drv(emu):
    from drivers import registry

    d = registry.create("robot", "ur_rtde", ur_config(emu), source="<test>")
    d.activate()
    yield d
    d.close()


def test_activate_negotiates_and_reads_the_plant(drv, world):
    st = drv.status()
    assert st["controller_version"] == (5, 11, 0, 0) and st["connects"] == 1
    assert (st["robot_mode"], st["safety_mode"], st["runtime_state"]) == ("RUNNING", "NORMAL", "STOPPED")
    js = drv.read_joint_state()
    assert np.array_equal(js.q, world.cell.plant.joint_angles())  # doubles on the wire: bit-exact
    assert np.array_equal(drv.read_commanded_tcp(), world.cell.plant.controller_tcp())
    pose = drv.read_sample().values["actual_TCP_pose"]
    assert np.allclose(pose[3:], [0.0, np.pi / 2, 0.0], atol=1e-9)  # tool-down as a rotation vector


def test_every_reading_carries_device_and_host_times_both_increasing(drv):
    import time

    readings = []
    for _ in range(5):
        readings.append(drv.read_joint_state())
        time.sleep(0.03)
    t_dev = [r.t for r in readings]
    t_host = [r.host_time for r in readings]
    assert all(b > a for a, b in zip(t_dev, t_dev[1:])) and all(b > a for a, b in zip(t_host, t_host[1:]))
    # the device's clock is not the host's: the controller counts from its own start
    assert abs(t_dev[0] - t_host[0]) > 1.0


def test_movel_arrives_at_the_commanded_position_with_the_plant_s_error(drv, emu, world):
    p0 = drv.read_commanded_tcp()
    target = p0 + np.array([0.03, -0.02, -0.05])
    drv.move_linear(target, 0.2)
    assert np.allclose(drv.read_commanded_tcp(), target, atol=1e-6)  # controller resolution 1 um
    assert np.allclose(world.cell.plant.controller_tcp(), target, atol=1e-6)
    err = np.linalg.norm(world.truth_tcp() - target)  # the plant's real error effects, as an instrument sees them
    assert 1e-6 < err < 5e-3
    assert emu.stats["movel"] == 1 and emu.stats["moves_done"] == 1 and drv.stats["moves_arrived"] == 1
    assert drv.status()["runtime_state"] == "STOPPED"


def test_the_stream_shows_the_arm_moving_before_it_arrives(drv, emu):
    import threading

    seen = []
    stop = threading.Event()

    def watch():
        while not stop.is_set():
            s = drv.read_sample()
            seen.append((s.values["runtime_state"], np.linalg.norm(s.values["actual_TCP_speed"][:3])))
            stop.wait(0.01)

    th = threading.Thread(target=watch)
    th.start()
    try:
        drv.move_linear(drv.read_commanded_tcp() + np.array([0.0, 0.1, 0.0]), 0.25)
    finally:
        stop.set()
        th.join()
    assert any(rs == rp.RUNTIME_PLAYING and v > 0.05 for rs, v in seen)  # moving, program playing
    assert max(v for _, v in seen) <= 0.25 + 1e-9  # never faster than commanded


def test_an_unknown_recipe_field_is_a_config_error_naming_it(emu):
    from drivers.ur.driver import UrRtdeController
    from dt_kernel.errors import ConfigError

    d = UrRtdeController.from_config(ur_config(emu, extra_outputs=["actual_q", "actual_TCP_pos"]), source="robot.yaml")
    with pytest.raises(ConfigError, match="actual_TCP_pos.*NOT_FOUND") as ei:
        d.activate()
    assert ei.value.value == "actual_TCP_pos" and ei.value.file == "robot.yaml"
    assert d.state == "inactive"
    d.close()


def test_known_extra_outputs_are_recorded(emu):
    from drivers.ur.driver import UrRtdeController

    d = UrRtdeController.from_config(ur_config(emu, extra_outputs=["output_int_register_2", "speed_scaling"]))
    d.activate()
    try:
        v = d.read_sample().values
        assert v["output_int_register_2"] == 0 and v["speed_scaling"] == 1.0
    finally:
        d.close()


def test_a_script_the_controller_refuses_is_a_driver_error_naming_its_reason(emu, world):
    from drivers.ur.driver import UrRtdeController
    from dt_kernel.errors import DriverError

    d = UrRtdeController.from_config(ur_config(emu, tool_rotvec=[0.0, 0.0, 0.0]))
    d.activate()
    try:
        p0 = world.cell.plant.controller_tcp()
        with pytest.raises(DriverError, match="refused the move.*orientation"):
            d.move_linear(p0 + np.array([0.01, 0.0, 0.0]), 0.1)
        assert np.array_equal(world.cell.plant.controller_tcp(), p0)  # nothing moved
    finally:
        d.close()


def test_config_errors_name_the_key():
    from drivers.ur.driver import UrRtdeController
    from dt_kernel.errors import ConfigError

    with pytest.raises(ConfigError, match="frequency_hz"):
        UrRtdeController.from_config({"host": "127.0.0.1", "frequency_hz": 1000})
    with pytest.raises(ConfigError, match="url"):
        UrRtdeController.from_config({"host": "127.0.0.1", "url": "/dev/ttyUSB0"})


def test_no_controller_is_a_driver_error_on_activate():
    from drivers.ur.driver import UrRtdeController
    from dt_kernel.errors import DriverError
    from tests.support.loopback import free_port

    d = UrRtdeController.from_config({"host": "127.0.0.1", "rtde_port": free_port(), "timeout_s": 0.5})
    with pytest.raises(DriverError, match="cannot connect"):
        d.activate()
    assert d.state == "inactive"


# --- faults through the real protocols --------------------------------------------------
def test_rtde_dropped_while_idle_is_detected_and_restored(drv, emu):
    from tests.support.loopback import wait_until

    emu.inject_drop(after_packages=0)  # the emulator closes the connection at its next package
    assert wait_until(lambda: drv.link.stats["drops"] == 1 and drv.link.stats["connects"] == 2, 10.0)
    assert emu.stats["drops"] == 1 and emu.stats["rtde_connections"] == 2
    t0 = drv.read_joint_state().t
    assert wait_until(lambda: drv.read_joint_state().t > t0, 5.0)  # streaming again
    assert "closed the connection" in drv.link.last_error


def test_rtde_dropped_during_a_move_the_move_is_not_repeated(drv, emu, world):
    p0 = drv.read_commanded_tcp()
    target = p0 + np.array([0.15, 0.0, 0.0])  # ~0.4 s of wall time at 0.1 m/s and TIME_SCALE
    emu.inject_drop(after_packages=5)  # ~40 ms into the move
    drv.move_linear(target, 0.1)
    assert drv.link.stats["drops"] == 1 and drv.link.stats["connects"] == 2  # detected and restored mid-move
    assert np.allclose(drv.read_commanded_tcp(), target, atol=1e-6)
    # sent once, executed once: nothing moved twice
    assert emu.stats["scripts"] == 1 and emu.stats["movel"] == 1 and emu.stats["moves_done"] == 1
    assert drv.stats == {"moves_sent": 1, "moves_arrived": 1, "refused": 0, "setpoints_sent": 0, "streams": 0}


def test_protective_stop_during_a_move_is_reported_and_nothing_moves_again(drv, emu, world):
    from dt_kernel.errors import DriverError

    p0 = drv.read_commanded_tcp()
    target = p0 + np.array([0.0, 0.1, 0.0])
    emu.inject_protective_stop()
    with pytest.raises(DriverError, match="protective stop during movel") as ei:
        drv.move_linear(target, 0.2)
    assert "not re-sent" in str(ei.value)
    half = p0 + 0.5 * (target - p0)  # the emulator stops the arm half way
    assert np.allclose(drv.read_commanded_tcp(), half, atol=1e-6)
    assert np.allclose(world.cell.plant.controller_tcp(), half, atol=1e-6)  # the plant stopped there too
    assert drv.status()["safety_mode"] == "PROTECTIVE_STOP"
    truth = world.truth_tcp()
    # a second move is refused by the driver before anything is sent ...
    with pytest.raises(DriverError, match="PROTECTIVE_STOP"):
        drv.move_linear(target, 0.2)
    assert emu.stats["scripts"] == 1 and emu.stats["movel"] == 1 and drv.stats["refused"] == 1
    # ... and a program sent anyway is refused by the controller
    emu.run_program(f"movel(p[{target[0]},{target[1]},{target[2]},0,1.570796327,0], a=1.2, v=0.2)\n")
    assert emu.stats["script_errors"] == 1
    assert np.array_equal(world.truth_tcp(), truth)  # the arm did not move again
    # the operator clears it (the dashboard's "unlock protective stop"); then moves work
    from tests.support.loopback import wait_until

    emu.unlock_protective_stop()
    assert wait_until(lambda: drv.status()["safety_mode"] == "NORMAL", 5.0)
    drv.move_linear(target, 0.2)
    assert np.allclose(drv.read_commanded_tcp(), target, atol=1e-6)


def test_abort_during_a_move_stops_the_arm_short_of_the_target(drv, emu):
    import threading

    from dt_kernel.errors import DriverError

    p0 = drv.read_commanded_tcp()
    target = p0 + np.array([0.0, 0.0, -0.2])  # ~0.55 s of wall time
    threading.Timer(0.15, drv.abort, args=("operator stop",)).start()
    with pytest.raises(DriverError, match="abort"):
        drv.move_linear(target, 0.1)
    from tests.support.loopback import wait_until

    assert wait_until(lambda: drv.status()["runtime_state"] == "STOPPED", 5.0)
    here = drv.read_commanded_tcp()
    assert emu.stats["scripts"] == 2 and emu.stats["stops"] == 1  # movel, then the driver's stopl halted it
    assert 1e-3 < np.linalg.norm(here - p0) and np.linalg.norm(here - target) > 1e-3  # stopped part-way
    drv.clear_abort()
    drv.move_linear(target, 0.2)
    assert np.allclose(drv.read_commanded_tcp(), target, atol=1e-6)


# --- a third-party RTDE client against our emulator -------------------------------------
@pytest.fixture
def emulator_process():
    """The emulator in its own process (`python -m emulators.ur`, the documented command)."""
    from tests.support.ur_emulator_process import ur_emulator_process

    with ur_emulator_process("--seed", "3", "--time-scale", "0.25") as served:
        yield served


def test_ur_rtde_receive_client_reads_our_emulator(emulator_process):
    rtde_receive = pytest.importorskip(
        "rtde_receive", reason="the third-party RTDE client `ur_rtde` is not installed (pip install ur_rtde)")
    from drivers.ur.driver import UrRtdeController

    host, script_port = emulator_process
    ours = UrRtdeController.from_config({"host": host, "rtde_port": 30004, "script_port": script_port,
                                         "move_timeout_s": 20.0})
    ours.activate()  # first: ur_rtde's constructor would wait forever on a silent server
    try:
        theirs = rtde_receive.RTDEReceiveInterface(
            host, 125.0, ["timestamp", "actual_q", "actual_TCP_pose", "robot_mode", "safety_mode", "runtime_state"])
        try:
            assert theirs.isConnected()
            # at rest, both clients decode the same joints and pose from the same controller
            assert np.array_equal(theirs.getActualQ(), ours.read_joint_state().q)
            assert np.array_equal(theirs.getActualTCPPose(), ours.read_sample().values["actual_TCP_pose"])
            assert np.allclose(theirs.getActualTCPPose()[:3], [0.9, 0.0, 0.7], atol=1e-6)  # the plant's home
            assert (theirs.getRobotMode(), theirs.getSafetyMode()) == (rp.ROBOT_MODE_RUNNING, rp.SAFETY_NORMAL)
            # after a move of ours, they read where the arm went
            target = np.array([0.85, 0.05, 0.62])
            ours.move_linear(target, 0.25)
            from tests.support.loopback import wait_until

            assert wait_until(lambda: np.allclose(theirs.getActualTCPPose()[:3], target, atol=1e-6), 5.0)
            # the two clients read the stream independently: while the arm settles their latest
            # packages may differ, so wait until both hold the same package, decoded alike
            assert wait_until(lambda: np.array_equal(theirs.getActualQ(), ours.read_joint_state().q), 5.0)
            t0 = theirs.getTimestamp()
            assert wait_until(lambda: theirs.getTimestamp() > t0, 5.0)  # the device clock runs on
        finally:
            theirs.disconnect()
    finally:
        ours.close()
