"""A plant for the serial controller emulator without a simulation: a joint vector that follows
the TCP (tests of the serial drivers, the registry and the conformance suite)."""
from __future__ import annotations

import time

import numpy as np

from dt_kernel.errors import UnreachableError

HOME = np.array([0.9, 0.0, 0.7])


class FakePlant:
    """The plant interface the controller emulator expects, with a joint vector that follows the TCP."""

    def __init__(self, move_delay_s: float = 0.0):
        self.tcp = HOME.copy()
        self.moves: list[tuple[np.ndarray, float]] = []
        self.move_delay_s = move_delay_s
        self.bad_joint: float | None = None

    def move_linear(self, target, speed):
        if np.linalg.norm(target) > 1.5:
            raise UnreachableError(f"target {target} out of reach")
        time.sleep(self.move_delay_s)
        self.tcp = np.array(target, dtype=float)
        self.moves.append((self.tcp.copy(), float(speed)))

    def joint_angles(self):
        q = np.concatenate([self.tcp, -self.tcp])
        if self.bad_joint is not None:
            q[2] = self.bad_joint
        return q

    def controller_tcp(self):
        return self.tcp.copy()
