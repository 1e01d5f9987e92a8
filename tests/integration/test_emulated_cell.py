"""The emulated cell (`python -m emulators.emulated_cell`): one simulated plant behind RTDE, NatNet
and the serial laser tracker, on loopback. The three real drivers see the same arm: the
distances between the arm's stations measured by the NatNet rig and by the tracker agree (each
instrument's frame is its own; distances are not), and the UR received each move once. The
NatNet frame used is one exposed after the move's arrival (`read_exposed_after`): the cell runs
20 times faster than real time, so a frame from the last milliseconds of a move is millimetres off."""
from __future__ import annotations

import time

import numpy as np

from drivers import registry
from drivers.base import read_exposed_after
from tests.support.emulated_cell_process import cell_process

STATIONS = np.array([[0.9, 0.0, 0.55], [0.8, 0.15, 0.45], [1.05, -0.15, 0.65], [0.95, 0.1, 0.35]])


def _open(section: dict, kind: str):
    options = {k: v for k, v in section.items() if k != "kind"}
    d = registry.create(kind, section["kind"], options, source="<test>")
    if d.state == "unconfigured":
        d.configure({})
    d.activate()
    return d


def test_one_command_serves_the_three_protocols_over_one_plant():
    with cell_process("--time-scale", "0.05", "--seed", "3") as cell:
        assert {"rtde_port", "script_port", "natnet_command_port", "tracker_url", "control_port"} <= cell.ports.keys()
        robot = _open(cell.robot(move_timeout_s=30.0), "robot")
        camera = _open(cell.camera(max_age_s=0.5, read_timeout_s=5.0), "camera")
        tracker = _open(cell.tracker(timeout_s=2.0), "tracker")
        try:
            cam, trk = [], []
            for target in STATIONS:
                robot.move_linear(target, 0.25)
                arrived = time.monotonic()
                assert np.allclose(robot.read_commanded_tcp(), target, atol=2e-4)
                r, m = read_exposed_after(camera, arrived), tracker.measure()
                assert r.ok, r.refused
                assert m.ok
                cam.append(r.point)
                trk.append(m.point)
            stats = cell.control("stats")
        finally:
            for d in (robot, camera, tracker):
                d.close()
        assert stats["ur"]["movel"] == len(STATIONS) and stats["ur"]["moves_done"] == len(STATIONS)
        assert stats["natnet"]["frames_sent"] > 0 and stats["tracker"]["replies"] >= len(STATIONS)
        assert cell.control("bogus")["ok"] is False
    cam_d = np.linalg.norm(np.diff(cam, axis=0), axis=1)
    trk_d = np.linalg.norm(np.diff(trk, axis=0), axis=1)
    # the rig's scale error (configs/cameras.yaml) and noise: well under a millimetre over ~0.3 m
    assert np.all(np.abs(cam_d - trk_d) < 1e-3), (cam_d, trk_d)
    assert cell.proc.returncode == 0  # SIGTERM stops it cleanly
    assert cell.final is not None and cell.final["stopped"] and cell.final["ur"]["movel"] == len(STATIONS)
