"""A servo follower: how an arm's controller tracks a stream of set-points (URScript `servoj`).

UR's manual, taken literally per axis, is a second-order follower: a = gain (r - (x +
lookahead_time v)), i.e. x'' + K T x' + K x = K r with K = gain (1/s^2) and T = lookahead_time,
damping ratio T sqrt(K) / 2; at constant target speed it trails by exactly T. It is a model of
the documented behaviour, not UR's controller. Look-ahead, gain and the lag they give:
docs/drivers.md ("Streaming set-points")."""
from __future__ import annotations

import math

import numpy as np


class ServoFollower:
    """Per-axis servo tracking of set-points, in the TCP's position (m).

    Within a control cycle the target moves linearly from the last set-point to the new one (a
    set-point is where the arm should be at the end of its cycle), integrated on sub-steps short
    enough (w h <= 0.01, w = sqrt(gain)) that a ramp's lag is the look-ahead time to 0.1 %.

    Parameters
    ----------
    position : ndarray
        (3,) m, where the arm starts (at rest).
    lookahead_s : float
        s, > 0.
    gain : float
        1/s^2, > 0.

    Raises
    ------
    ValueError
        When ``lookahead_s`` or ``gain`` is not positive.
    """

    def __init__(self, position: np.ndarray, lookahead_s: float, gain: float):
        if not (lookahead_s > 0 and gain > 0):
            raise ValueError(f"servo follower needs lookahead_s > 0 and gain > 0, got {lookahead_s}, {gain}")
        self.lookahead_s, self.gain = float(lookahead_s), float(gain)
        self.x = np.array(position, dtype=float)
        self.v = np.zeros_like(self.x)
        self.r = self.x.copy()  # the last set-point

    @property
    def damping_ratio(self) -> float:
        """The follower's damping ratio, lookahead_s sqrt(gain) / 2."""
        return self.lookahead_s * math.sqrt(self.gain) / 2.0

    def step(self, target: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Track ``target`` for ``dt`` seconds.

        Parameters
        ----------
        target : ndarray
            (3,) m, the new set-point.
        dt : float
            s, the control cycle.

        Returns
        -------
        position : ndarray
            (3,) m, at the end.
        velocity : ndarray
            (3,) m/s, at the end.
        """
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
