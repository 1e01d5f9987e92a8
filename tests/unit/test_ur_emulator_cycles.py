"""The UR emulator's control cycle sees the set-points that had arrived by its scheduled time, so
a cycle that runs late (the emulator not scheduled in time) moves the arm as an on-time one would."""
from __future__ import annotations

import numpy as np

from emulators.ur import UrEmulator


class _Plant:
    def joint_angles(self):
        return np.zeros(6)

    def controller_tcp(self):
        return np.array([0.9, 0.0, 0.5])


def test_a_late_cycle_sees_only_what_had_arrived_by_its_time():
    emu = UrEmulator(_Plant(), "127.0.0.1", 0, 0, autostart=False)
    try:
        reg = "input_int_register_24"
        for t, seq in ((1.000, 5), (1.004, 6), (1.010, 7)):
            emu._arrivals.append((t, {reg: seq}))
        emu._take_arrivals(1.005)  # the cycle due at 1.005, run whenever: set-points 5 and 6 had arrived
        assert emu._cycle_inputs[reg] == 6 and len(emu._arrivals) == 1
        emu._take_arrivals(1.009)
        assert emu._cycle_inputs[reg] == 6  # 7 arrived after this cycle's time
        emu._take_arrivals(1.013)
        assert emu._cycle_inputs[reg] == 7 and not emu._arrivals
        assert emu.stats["late_cycles"] == 0 and emu.stats["skipped_cycles"] == 0
    finally:
        emu.stop()
