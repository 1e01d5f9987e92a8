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
