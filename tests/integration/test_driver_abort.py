"""A move in flight against a device that stopped answering ends promptly when the host aborts
it (the daemon's SIGTERM path), instead of after (1 + retries) x move_timeout_s."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers import registry
from drivers.simulated.devices import SimWorld
from dt_kernel.errors import DriverError
from dt_runtime.common.paths import CONFIGS
from emulators.serial import ControllerEmulator


def test_abort_ends_a_move_to_a_silent_device_at_once():
    world = SimWorld(CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml")
    emu = ControllerEmulator(world.cell.plant)
    robot = registry.create("robot", "serial", {"url": emu.port, "timeout_s": 2.0, "move_timeout_s": 30.0,
                                                "retries": 3}, source="<test>")
    try:
        robot.activate()
        p0 = np.asarray(robot.read_commanded_tcp())
        emu.pause(600)  # deaf and mute: without abort the move would wait 4 x 30 s
        err: list[BaseException] = []

        def move():
            try:
                robot.move_linear(p0 + np.array([0.02, 0.0, 0.0]), 0.2)
            except BaseException as exc:  # noqa: BLE001 - collected for the assertion
                err.append(exc)

        th = threading.Thread(target=move)
        th.start()
        time.sleep(0.3)
        assert th.is_alive()  # the move is waiting on the silent device
        robot.abort("test stop")
        th.join(timeout=5.0)  # hang detection, not timing: it ends within one poll (20 ms)
        assert not th.is_alive()
        assert len(err) == 1 and isinstance(err[0], DriverError) and "aborted" in str(err[0])
    finally:
        robot.close()
        emu.stop()


def test_a_clear_abort_lets_the_next_move_through():
    world = SimWorld(CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml")
    robot = registry.create("robot", "sim", {}, world=world, source="<test>")
    robot.activate()
    p0 = np.asarray(robot.read_commanded_tcp())
    robot.abort()
    with pytest.raises(DriverError, match="aborted"):
        robot.move_linear(p0 + np.array([0.01, 0, 0]), 0.2)
    robot.clear_abort()
    robot.move_linear(p0 + np.array([0.01, 0, 0]), 0.2)
    robot.close()
