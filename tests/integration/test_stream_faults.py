"""Faults on a streamed path (issue 23, item 7): the streaming process stalled (SIGSTOP, as a
host that stops scheduling it) while the UR controller follows the stream. The controller's
watchdog stops the arm; when the process runs again its next set-point is refused, and the
stream's report says which set-point was the first not sent. Load-proof: every check is on the
emulator's cycle counts and the report, never on a wall-clock threshold."""
from __future__ import annotations

import functools
import os
import signal

import numpy as np
import pytest

from dt_runtime.service.stream import StreamProcess
from tests.support.loopback import wait_until
from tests.support.stream_fakes import offset_corrector, ur_stream_driver

RATE = 125.0
SCENARIO, CELL = "configs/scenarios/paper_default.yaml", "configs/cell.yaml"


@pytest.fixture
def emu():
    from drivers.simulated.devices import SimWorld
    from dt_runtime.common.paths import ROOT
    from emulators.ur import UrEmulator

    world = SimWorld(ROOT / SCENARIO, ROOT / CELL, seed=5)
    e = UrEmulator(world.cell.plant, "127.0.0.1", 0, 0)
    yield e
    e.stop()
    world.close()


def test_a_stalled_streaming_process_is_stopped_by_the_controllers_watchdog(emu):
    p0 = emu.plant.controller_tcp()
    n = 1000  # 8 s at 125 Hz: the stall comes long before the end
    t = np.arange(n) / RATE
    targets = p0 + np.outer(np.minimum(t, 2.0), [0.02, 0.0, 0.0])  # 20 mm/s for 2 s, then still
    proc = StreamProcess(offset_corrector, functools.partial(ur_stream_driver, emu.rtde_port, emu.script_port,
                                                             RATE, 25), t, targets, RATE, rt_priority=0)
    try:
        assert wait_until(lambda: proc.sent >= 50, 60.0), proc.sent
        os.kill(proc.pid, signal.SIGSTOP)
        try:  # the controller sees no new set-point for 25 cycles: stopj
            assert wait_until(lambda: emu.stats["watchdog_stops"] >= 1, 60.0), emu.stats
        finally:
            os.kill(proc.pid, signal.SIGCONT)
        rep = proc.result(timeout=60.0)
    finally:
        proc.kill()
    assert emu.stats["watchdog_stops"] == 1
    assert 50 <= rep.n_sent < n and "watchdog" in rep.stopped, rep.stopped
    assert rep.stopped.startswith(f"set-point {rep.n_sent + 1} of {n} refused")  # where to resume
