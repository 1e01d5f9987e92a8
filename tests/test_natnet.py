"""OptiTrack NatNet 4.1: wire format, emulator of the simulated rig, NatNetRig driver, faults.

Everything runs on 127.0.0.1 with ports the OS picks; waits are polled with generous deadlines,
no timing is asserted. Values in the round trips are exactly representable in float32.
"""
from __future__ import annotations

import struct

import pytest

from drivers.natnet import protocol as nn
from dt_kernel.errors import DriverError


def _frame(n_markers: int = 5, number: int = 42) -> nn.FrameOfData:
    lm = tuple(nn.LabeledMarker(nn.marker_id(3, i + 1), (0.5 + i / 8, -0.25, 1.0 + i / 16), 0.015625,
                                nn.MARKER_MODEL_SOLVED | nn.MARKER_HAS_MODEL | (nn.MARKER_OCCLUDED if i == 1 else 0),
                                i / 1024) for i in range(n_markers))
    return nn.FrameOfData(
        number, (nn.MarkerSet("tool", tuple(m.pos for m in lm)), nn.MarkerSet("empty", ())),
        ((0.125, 0.25, 0.5),),
        (nn.RigidBody(3, (0.75, -0.5, 1.25), (0.0, 0.5, -0.5, 0.70703125), 1 / 4096, nn.RB_TRACKING_VALID),
         nn.RigidBody(4, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, 0)),
        lm, 7, 8, 12.345678901234, 2**40 + 1, 2**40 + 5000, 2**40 + 9000, 11, 12, nn.FRAME_RECORDING)


# ----------------------------------------------------------------------------- protocol
def test_frame_round_trip_with_markers_and_rigid_bodies():
    f = _frame()
    msg, payload = nn.unpack_message(nn.pack_frame(f))
    assert msg == nn.NAT_FRAMEOFDATA
    g = nn.unpack_frame(payload)
    assert g == f
    assert g.labeled_markers[2].model_id == 3 and g.labeled_markers[2].member_id == 3
    assert g.labeled_markers[1].occluded and not g.labeled_markers[0].occluded
    assert g.rigid_bodies[0].tracking_valid and not g.rigid_bodies[1].tracking_valid
    assert g.stamp_transmit - g.stamp_mid_exposure == 8999  # uint64 stamps survive exactly


def test_frame_sections_are_sized_and_unknown_ones_skipped():
    """4.1 puts a byte size after every count: a reader skips sections it does not decode."""
    data = bytearray(nn.pack_frame(_frame(n_markers=2)))
    _, payload = nn.unpack_message(bytes(data))
    # Splice a fake skeleton section (count 1, 12 bytes of content) in place of the empty one:
    # frame number, marker sets (2 sets, 2 markers), other markers (1), rigid bodies (2 x 38 bytes).
    f0 = nn.unpack_frame(payload)
    skel = 4 + 8 + (5 + 4 + 24 + 6 + 4) + 8 + 12 + 8 + 2 * 38
    assert payload[skel:skel + 8] == struct.pack("<ii", 0, 0)
    patched = payload[:skel] + struct.pack("<ii", 1, 12) + b"x" * 12 + payload[skel + 8:]
    g = nn.unpack_frame(patched)
    assert g.skipped == {"skeletons": 1}
    assert g.labeled_markers == f0.labeled_markers and g.stamp_transmit == f0.stamp_transmit


def test_truncated_frame_is_a_protocol_error_naming_the_offset():
    payload = nn.unpack_message(nn.pack_frame(_frame()))[1]
    with pytest.raises(nn.NatNetProtocolError, match="truncated at byte"):
        nn.unpack_frame(payload[:-30])
    with pytest.raises(nn.NatNetProtocolError, match="header says"):
        nn.unpack_message(nn.pack_frame(_frame())[:50])
    assert issubclass(nn.NatNetProtocolError, DriverError)


def test_server_info_connect_and_text_round_trips():
    info = nn.ServerInfo("Motive", (3, 1, 2, 0), (4, 1, 0, 0), 10_000_000, 1511, True, (239, 255, 42, 99))
    msg, payload = nn.unpack_message(nn.pack_server_info(info))
    assert msg == nn.NAT_SERVERINFO and len(payload) == 256 + 8 + 15
    assert nn.unpack_server_info(payload) == info
    req = nn.ConnectRequest("Ping", (1, 2, 3, 4), (4, 1, 0, 0), True, (4, 0, 0, 0))
    msg, payload = nn.unpack_message(nn.pack_connect(req))
    assert msg == nn.NAT_CONNECT and nn.unpack_connect(payload) == req
    msg, payload = nn.unpack_message(nn.pack_text(nn.NAT_RESPONSE, "Bitstream,4.1.0.0"))
    assert msg == nn.NAT_RESPONSE and nn.unpack_text(payload) == "Bitstream,4.1.0.0"
    # A zero-length request followed by the NUL some clients append: the count rules.
    assert nn.unpack_message(nn.pack_request(nn.NAT_KEEPALIVE) + b"\0") == (nn.NAT_KEEPALIVE, b"")


def test_model_definition_round_trip():
    descs = [nn.MarkerSetDescription("tool", ("a", "b", "c")),
             nn.RigidBodyDescription("tool", 3, -1, (0.0, 0.0, 0.0),
                                     ((-0.125, 0.0625, 0.0), (0.25, 0.5, -0.75), (0.0, 0.0, 0.125)),
                                     (0, 0, 0), ("a", "b", "c"))]
    msg, payload = nn.unpack_message(nn.pack_model_def(descs))
    assert msg == nn.NAT_MODELDEF and nn.unpack_model_def(payload) == descs
    # A description of another kind (camera, type 5) is skipped by its size.
    extra = struct.pack("<iii", 1, nn.DESC_CAMERA, 8) + b"\1" * 8
    only = nn.unpack_model_def(extra)
    assert only == []
