"""A servo follower: how an arm's controller tracks a stream of set-points (URScript `servoj`).

UR's manual describes `servoj(q, a, v, t, lookahead_time, gain)` in two sentences: the gain "works
the same way as the P-term of a PID controller, where it adjusts the current position towards the
desired", and lookahead_time "is used to project the current position forward in time with the
current velocity. A low value gives fast reaction, a high value prevents overshoot" (ranges 0.03-0.2
s and 100-2000). Taken literally, per axis, with x the position, v its velocity and r the target::

    a = gain * (r - (x + lookahead_time * v))          i.e.  x'' + K T x' + K x = K r

a second-order follower with K = gain (1/s^2), natural frequency w = sqrt(K) and damping ratio
zeta = T sqrt(K) / 2. At constant target speed it trails the target by exactly T =
lookahead_time (the ramp's steady-state error), whatever the gain; a short look-ahead with a
high gain is under-damped and overshoots when the target stops (T = 0.03 s, gain 1200: zeta 0.52,
about 15 % of a step), a long one is damped (T = 0.1 s, gain 300: zeta 0.87). Users of the public
RTDE clients report ~34 ms from set-point to motion at lookahead 0.03 s on an e-Series
(servoj(q, 0, 0, 0.002, 0.03, 1200)), of which 4-6 ms is the communication round trip: the
model's 30 ms. It is a model of the documented behaviour, not UR's controller; the twin sees its
lag and overshoot as the plant's truth, the way it would see a real arm's.

Within a control cycle the target moves linearly from the last set-point to the new one (a
set-point is where the arm should be at the end of its cycle), integrated on sub-steps short
enough (w h <= 0.01) that a ramp's lag is the look-ahead time to 0.1 %; the
follower works in the TCP's position (m), one axis at a time (joint servoing through the
controller's IK moves the TCP the same way for small steps).
"""
from __future__ import annotations

import math

import numpy as np


class ServoFollower:
    """Per-axis servo tracking of set-points (see the module docstring)."""

    def __init__(self, position: np.ndarray, lookahead_s: float, gain: float):
        if not (lookahead_s > 0 and gain > 0):
            raise ValueError(f"servo follower needs lookahead_s > 0 and gain > 0, got {lookahead_s}, {gain}")
        self.lookahead_s, self.gain = float(lookahead_s), float(gain)
        self.x = np.array(position, dtype=float)
        self.v = np.zeros_like(self.x)
        self.r = self.x.copy()  # the last set-point

    @property
    def damping_ratio(self) -> float:
        return self.lookahead_s * math.sqrt(self.gain) / 2.0

    def step(self, target: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Track `target` (m) for `dt` seconds; returns (position m, velocity m/s) at the end."""
        r1 = np.asarray(target, dtype=float)
        k, c = self.gain, self.gain * self.lookahead_s
        n = max(1, math.ceil(dt * math.sqrt(k) / 0.01))
        h = dt / n
        x, v, r0 = self.x, self.v, self.r
        for j in range(n):
            r = r0 + (r1 - r0) * (j / n)  # the target at the sub-step's start, like x and v
            v_new = v + h * (k * (r - x) - c * v)
            x = x + h * 0.5 * (v + v_new)  # the mean velocity over the sub-step: no lag of its own
            v = v_new
        self.x, self.v, self.r = x, v, r1.copy()
        return x.copy(), v.copy()

    def stop(self) -> np.ndarray:
        """Stop where the arm is (stopj): velocity zero; returns the position (m)."""
        self.v = np.zeros_like(self.x)
        return self.x.copy()
