"""OptiTrack NatNet 4.1: wire format, emulator of the simulated rig, NatNetRig driver, faults.

Everything runs on 127.0.0.1 with ports the OS picks; waits are polled with generous deadlines,
no timing is asserted. Values in the round trips are exactly representable in float32.
"""
from __future__ import annotations

import contextlib
import struct
import time

import numpy as np
import pytest

from drivers.natnet import protocol as nn
from dt_kernel.errors import DriverError
from tests.support.loopback import free_port, wait_until


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


# ----------------------------------------------------------------------------- driver against emulator
def _circle(center=(0.9, 0.0, 0.5), radius=0.05):
    """Tool poses on a circle, one step per capture: deterministic for a given frame number."""
    from sim.kinematics import TOOL_DOWN

    k = {"n": 0}

    def pose():
        k["n"] += 1
        a = 2 * np.pi * k["n"] / 600
        return TOOL_DOWN, np.asarray(center) + radius * np.array([np.cos(a), np.sin(a), 0.0])

    return pose


@contextlib.contextmanager
def _stream(emu_cfg=None, drv_cfg=None, seed=0, activate=True):
    from drivers.natnet.driver import NatNetRig
    from emulators.natnet import NatNetEmulator, SimRigMarkers

    src = SimRigMarkers(_circle(), seed=seed)
    with NatNetEmulator(src, {"command_port": 0, "data_port": 0, **(emu_cfg or {})}) as emu:
        drv = NatNetRig.from_config({"command_port": emu.command_port, "max_age_s": 0.5, "read_timeout_s": 5.0,
                                     **(drv_cfg or {})})
        try:
            if activate:
                drv.activate()
            yield emu, drv
        finally:
            drv.close()


def test_driver_reads_server_info_model_and_the_simulated_tcp_within_the_rig_noise():
    with _stream(drv_cfg={"marker_sigma_m": 70e-6}, seed=1) as (emu, drv):
        info = drv.server_info
        assert info.natnet_version == (4, 1, 0, 0) and info.app_name.startswith("Motive")
        assert drv.body.name == "tool" and drv.body.id == 1 and len(drv.body.marker_positions) == 5
        rs = [drv.read() for _ in range(60)]
        ok = [r for r in rs if r.ok]
        assert len(ok) == len(rs), [r.refused for r in rs if not r.ok][:3]
        err = np.array([r.point - emu.last_truth[r.quality["frame_number"]] for r in ok])
        # The MVS frame's TCP (scale error included) within the rig's noise: the normalised error
        # has chi^2 statistics (3 dof per reading) and the RMS is tens of micrometres.
        d2 = np.array([e @ np.linalg.solve(r.cov, e) for e, r in zip(err, ok)])
        assert d2.mean() < 3 * 2.0
        assert np.sqrt((err ** 2).sum(1).mean()) < 0.3e-3
        q = ok[-1].quality
        assert q["markers_seen"] == q["markers_used"] == 5 and q["tracking_valid"]
        assert 0 < q["residual_rms_m"] < 0.5e-3 and q["server_tcp_diff_m"] < 1e-5


def test_every_reading_carries_device_and_host_timestamps_increasing():
    with _stream() as (_, drv):
        rs = [drv.read() for _ in range(20)]
        frames = [r.quality["frame_number"] for r in rs]
        assert all(b > a for a, b in zip(frames, frames[1:]))  # each reading a newer frame
        for key in ("device_time", "host_time"):
            v = [getattr(r, key) for r in rs]
            assert all(x is not None and np.isfinite(x) for x in v)
            assert all(b > a for a, b in zip(v, v[1:])), key
        ts = [r.quality["timestamp_s"] for r in rs]
        assert all(b > a for a, b in zip(ts, ts[1:]))
        for r in rs:  # t: the mid-exposure on the server's clock; mapped to the host clock, before receipt
            assert r.t == r.quality["mid_exposure_s"] and r.quality["mid_exposure_host_s"] <= r.host_time
            assert r.quality["age_s"] >= r.quality["server_latency_s"] >= 0


def test_unsupported_natnet_version_is_refused_with_the_version_seen():
    with _stream(emu_cfg={"natnet_version": (3, 0, 0, 0)}, activate=False) as (_, drv):
        with pytest.raises(DriverError, match=r"NatNet 3\.0\.0\.0.*4\.1"):
            drv.activate()
        assert drv.state == "inactive"


def test_unknown_rigid_body_is_refused_naming_the_streamed_ones():
    with _stream(drv_cfg={"rigid_body": "gripper"}, activate=False) as (_, drv):
        with pytest.raises(DriverError, match=r"no rigid body 'gripper'.*'tool' \(id 1\)"):
            drv.activate()


def test_registry_builds_natnet_and_config_errors_name_the_key():
    from drivers import registry
    from dt_kernel.errors import ConfigError

    assert "natnet" in registry.known("camera") and not registry.needs_world("camera", "natnet")
    drv = registry.create("camera", "natnet", {"command_port": 1510, "rigid_body": "tool"})
    assert drv.state == "inactive"
    with pytest.raises(ConfigError, match="max_age"):
        registry.create("camera", "natnet", {"max_age": 0.1})


def test_multicast_mode_receives_frames_on_the_data_port():
    port = free_port()
    with _stream(emu_cfg={"multicast": True, "data_group": "127.0.0.1", "data_port": port},
                 drv_cfg={"multicast": True, "multicast_group": "127.0.0.1", "data_port": port,
                          "local_address": "127.0.0.1"}) as (emu, drv):
        r = drv.read()
        assert r.ok, r.refused
        assert drv.server_info.multicast and drv.server_info.data_port == port


# ----------------------------------------------------------------------------- faults
def test_dropped_frames_are_counted_as_lost_and_reported():
    with _stream(emu_cfg={"faults": {"drop_probability": 0.3, "seed": 4}}) as (emu, drv):
        rs = [drv.read() for _ in range(40)]
        assert all(r.ok for r in rs), [r.refused for r in rs if not r.ok][:3]  # losses are reported, not refused
        last = rs[-1].quality["frame_number"]
        dropped = [n for n in emu.stats.dropped if drv.first_frame < n < last]
        assert len(dropped) > 5
        assert rs[-1].quality["frames_lost"] == len(dropped)
        assert sum(r.quality["frames_lost_since_last_read"] for r in rs) == len(dropped)


def test_late_frames_are_refused_as_stale():
    # Every frame leaves the server 0.3 s after its mid-exposure: the transmit stamp says so.
    with _stream(emu_cfg={"faults": {"delay_probability": 1.0, "delay_s": 0.3}},
                 drv_cfg={"max_age_s": 0.1}) as (_, drv):
        rs = [drv.read() for _ in range(5)]
        assert all(not r.ok and "stale" in r.refused and "max_age_s" in r.refused for r in rs)
        assert all(r.quality["age_s"] >= 0.3 and np.isfinite(r.device_time) for r in rs)


def test_frames_overtaken_by_newer_ones_are_counted_late_not_lost():
    with _stream(emu_cfg={"faults": {"delay_probability": 0.3, "delay_s": 0.05, "seed": 2}}) as (emu, drv):
        frames = []
        for _ in range(40):
            r = drv.read()
            frames.append(r.quality["frame_number"])
        assert all(b > a for a, b in zip(frames, frames[1:]))
        assert wait_until(lambda: drv.stats["frames_late"] > 3, 10.0)
        # Every delayed frame arrives eventually: once the delays stop, nothing is counted lost.
        emu.set_faults(delay_probability=0.0)
        assert wait_until(lambda: drv.stats["frames_lost"] == 0, 10.0)
        assert emu.stats.frames_dropped == 0 and drv.stats["frames_late"] <= emu.stats.frames_delayed


def test_rigid_body_not_tracked_is_refused_naming_it():
    with _stream() as (emu, drv):
        assert drv.read().ok
        emu.set_faults(untracked_probability=1.0)
        assert wait_until(lambda: "not tracked" in (drv.read().refused or ""), 10.0)
        r = drv.read()
        assert "rigid body 'tool' (id 1) not tracked" in r.refused and r.quality["tracking_valid"] is False
        emu.set_faults(untracked_probability=0.0)
        assert wait_until(lambda: drv.read().ok, 10.0)


def test_too_few_markers_is_refused_and_occluded_markers_are_not_used():
    with _stream(emu_cfg={"faults": {"occluded_markers": (0, 3)}}, drv_cfg={"min_markers": 4}) as (_, drv):
        r = drv.read()
        assert not r.ok and "only 3 markers of rigid body 'tool' (id 1) seen (needs 4)" in r.refused
        assert r.quality["markers_seen"] == 3
    with _stream(emu_cfg={"faults": {"occluded_markers": (0, 3)}}) as (_, drv):
        r = drv.read()  # three markers still fit the cluster
        assert r.ok and r.quality["markers_used"] == 3


def test_cluster_residual_too_large_is_refused():
    with _stream(drv_cfg={"max_residual_m": 1e-6, "gate_sigma": 1e6}) as (_, drv):
        r = drv.read()
        assert not r.ok and "cluster fit residual" in r.refused and r.quality["residual_rms_m"] > 1e-6


def test_a_silent_server_gives_refusals_not_hangs():
    with _stream(drv_cfg={"read_timeout_s": 0.3}) as (emu, drv):
        assert drv.read().ok
        emu.close()
        r = drv.read()
        r = drv.read() if r.ok else r  # one frame may still be queued
        assert not r.ok and "no NatNet frame after" in r.refused


# ----------------------------------------------------------------------------- independent client
def _stop_sdk_client(client) -> None:
    """The sample's shutdown() closes its sockets and joins its threads, but closing a socket does
    not wake a thread blocked in recvfrom on Linux (its unicast data socket has no timeout): wake
    both with a harmless keep-alive datagram once the stop flag is set."""
    import socket

    client.stop_threads = True
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for sock in (client.data_socket, client.command_socket):
            port = sock.getsockname()[1]
            s.sendto(nn.pack_request(nn.NAT_KEEPALIVE), ("127.0.0.1", port))
    client.shutdown()


def test_optitrack_natnet_sdk_client_reads_our_emulator():
    """OptiTrack's own Python client (NatNetClient.py of the NatNet SDK, packaged as `natnetsdk`)
    connects to the emulator in unicast and decodes our frames: server info, rigid body pose,
    labelled markers, timestamps. Its frame and model decoders are private methods; they are
    called by their mangled names on our bytes, because its listeners expose only the rigid body."""
    sdk = pytest.importorskip("natnetsdk.NatNetClient", reason="natnetsdk (the test extra) is not installed")
    bodies, frames = [], []
    with _stream(drv_cfg={"marker_sigma_m": 70e-6}, seed=5) as (emu, drv):
        client = sdk.NatNetClient()
        client.set_client_address("127.0.0.1")
        client.set_server_address("127.0.0.1")
        client.set_use_multicast(False)
        client.command_port = emu.command_port
        client.multicast_address = "255.255.255.255"  # unicast: no multicast group to join
        client.set_print_level(0)
        client.rigid_body_listener = lambda i, pos, rot: bodies.append((i, pos, rot))
        client.new_frame_listener = frames.append
        assert client.run()
        try:
            assert wait_until(lambda: len(frames) > 20 and client.connected(), 20.0)
            assert client.get_application_name() == emu.cfg.app_name
            assert list(client.get_nat_net_version_server()) == [4, 1, 0, 0]
            assert list(client.get_server_version()) == [3, 1, 0, 0]
            numbers = [f["frame_number"] for f in frames[:20]]
            assert all(b > a for a, b in zip(numbers, numbers[1:]))
            assert all(f["labeled_marker_count"] == 5 and f["rigid_body_count"] == 1 for f in frames[:20])
            # Its rigid body position is the one our driver fits from the same markers.
            r = drv.read()
            i, pos, rot = bodies[-1]
            assert i == 1 and np.isclose(np.linalg.norm(rot), 1.0, atol=1e-5)
            assert np.linalg.norm(np.asarray(pos) - emu.last_truth[frames[len(bodies) - 1]["frame_number"]]) < 1e-3
            assert r.ok and np.linalg.norm(np.asarray(pos) - r.point) < 2e-3
        finally:
            _stop_sdk_client(client)
        # Its decoders on our bytes: every labelled marker, rigid body and stamp as we sent it.
        f = emu.make_frame(99, time.monotonic(), emu.cfg.faults)
        _, payload = nn.unpack_message(nn.pack_frame(f))
        _, md = client._NatNetClient__unpack_mocap_data(payload, len(payload), 4, 1)
        theirs = md.labeled_marker_data.labeled_marker_list
        assert [m.id_num for m in theirs] == [m.id for m in f.labeled_markers]
        assert np.allclose([m.pos for m in theirs], [m.pos for m in f.labeled_markers], atol=1e-6)
        rb = md.rigid_body_data.rigid_body_list[0]
        assert rb.id_num == 1 and rb.tracking_valid and np.allclose(rb.pos, f.rigid_bodies[0].pos, atol=1e-6)
        assert md.suffix_data.stamp_camera_mid_exposure == f.stamp_mid_exposure
        assert md.prefix_data.frame_number == 99
        _, model = nn.unpack_message(nn.pack_model_def(emu.descriptions()))
        descs = client._NatNetClient__unpack_data_descriptions(model, len(model), 4, 1)[1]
        rbd = descs.rigid_body_list[0]
        assert rbd.id_num == 1 and len(rbd.rb_marker_list) == 5
        assert np.allclose(rbd.rb_marker_list[2].pos, emu.source.markers[2], atol=1e-6)


# ----------------------------------------------------------------------------- who is listened to
def test_a_forged_frame_from_another_port_is_ignored_and_counted():
    """The black-box probe's datagram: frame 2,000,000,000 sent to the driver's socket from
    another port of the same address. It is not decoded, counted in `frames_foreign`, and the
    real stream goes on (before the fix every real frame was "late" from then on)."""
    import socket

    with _stream() as (emu, drv):
        assert drv.read().ok
        target = drv._cmd.getsockname()
        forged = nn.pack_frame(emu.make_frame(2_000_000_000, time.monotonic(), emu.cfg.faults))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as mallory:
            mallory.bind(("127.0.0.1", 0))
            for _ in range(5):
                mallory.sendto(forged, target)
            who = f"127.0.0.1:{mallory.getsockname()[1]}"
        assert wait_until(lambda: drv.counters()["frames_foreign"] == 5, 10.0)
        rs = [drv.read() for _ in range(10)]
        assert all(r.ok for r in rs), [r.refused for r in rs if not r.ok][:3]
        assert all(r.quality["frame_number"] < 1_000_000 for r in rs)
        c = drv.counters()
        assert c["frame_resets"] == 0 and c["frames_late"] == 0 and drv.last_foreign == who


def test_a_silent_server_refusal_names_the_foreign_sender():
    import socket

    with _stream(drv_cfg={"read_timeout_s": 0.3}) as (emu, drv):
        assert drv.read().ok
        emu.close()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as mallory:
            mallory.sendto(nn.pack_request(nn.NAT_KEEPALIVE), drv._cmd.getsockname())
            assert wait_until(lambda: drv.counters()["frames_foreign"] == 1, 10.0)
        r = drv.read()
        r = drv.read() if r.ok else r
        assert not r.ok and "1 datagrams from other senders ignored" in r.refused
        ports = "/".join(map(str, sorted((emu.command_port, emu.data_port))))
        assert f"frames are taken from 127.0.0.1:{ports} only" in r.refused


def test_the_emulator_holds_its_data_port():
    """A client trusts the server's data port: no other process may bind it and send from it."""
    import socket

    with _stream() as (emu, drv):
        assert drv.server_info.data_port == emu.data_port != 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s, pytest.raises(OSError):
            s.bind(("127.0.0.1", emu.data_port))


@pytest.mark.parametrize("start, number", [(1, 2_000_000_000), (600, 1)])
def test_a_frame_counter_that_jumps_or_restarts_is_a_new_reference(start, number):
    """The server itself renumbers its stream: far ahead (a take switched, or the forged number
    coming from the server's own address) or back to 1 from about 600 (a restart: within
    max_frame_jump, recognised because no newer frame came for max_age_s). The driver takes it
    as a new reference: readings keep flowing with the new numbers, nothing is counted lost or
    late for good."""
    with _stream(activate=False) as (emu, drv):
        emu.set_frame_number(start)
        drv.activate()
        before = [drv.read() for _ in range(5)]
        assert all(r.ok for r in before) and before[0].quality["frame_number"] >= start
        emu.set_frame_number(number)
        assert wait_until(lambda: drv.counters()["frame_resets"] >= 1, 10.0)
        after = [drv.read()]
        while not (after[-1].ok and after[-1].quality["frame_number"] < number + 1000) and len(after) < 40:
            after.append(drv.read())
        assert after[-1].ok, after[-1].refused
        more = [drv.read() for _ in range(10)]
        assert all(m.ok for m in more), [m.refused for m in more if not m.ok][:3]
        assert all(number <= m.quality["frame_number"] < number + 1000 for m in more)
        c = drv.counters()
        assert c["frame_resets"] == 1 and c["frames_lost"] == 0, c
        if number == 1:
            assert "the frame counter restarted" in drv.last_reset and 0 < c["frames_late"] < 600
        else:
            assert "the frame counter jumped ahead by" in drv.last_reset and c["frames_late"] == 0


def test_a_restarted_server_on_the_same_ports_is_read_again():
    """A real restart: the server process goes, a new one binds the same ports, counts from 1 on
    a clock that starts afresh. The keep-alive subscribes the client again and readings resume
    (the transit minimum is learnt again: the new clock is not the old one)."""
    from emulators.natnet import NatNetEmulator, SimRigMarkers

    with _stream(drv_cfg={"keepalive_s": 0.1}) as (emu, drv):
        rs = [drv.read() for _ in range(30)]
        assert all(r.ok for r in rs)
        ports = {"command_port": emu.command_port, "data_port": emu.data_port}
        emu.close()
        time.sleep(0.2)
        with NatNetEmulator(SimRigMarkers(_circle()), {**ports, "clock_offset_s": 5.0}):
            assert wait_until(lambda: drv.read().ok and drv.counters()["frame_resets"] >= 1, 15.0)
            more = [drv.read() for _ in range(10)]
            assert all(m.ok for m in more), [m.refused for m in more if not m.ok][:3]
            assert more[-1].quality["frame_number"] < 1000 and more[-1].quality["age_s"] < 0.5
