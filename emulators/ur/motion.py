"""The emulated controller's motion: a trapezoidal speed profile along a straight TCP path, sampled
at any wall-clock instant (the RTDE stream asks for the arm's state whenever it sends a package).

The plant (`sim.plant.SimulatedCobot`) settles at a target in one call; the emulator commits the
plant at the start of a move and this profile spreads the reported joints and pose over the time
the move takes, so the stream shows the arm moving (non-zero speed, program PLAYING) and then
standing at the target, as a real controller's does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def trapezoid_duration(dist: float, v: float, a: float) -> float:
    """Time to travel a distance from rest to rest with a trapezoidal (or triangular) speed profile.

    Parameters
    ----------
    dist : float
        m.
    v : float
        Cruise speed (m/s).
    a : float
        Acceleration (m/s^2).

    Returns
    -------
    float
        s.
    """
    if dist <= 0:
        return 0.0
    if dist >= v * v / a:  # reaches cruise speed
        return dist / v + v / a
    return 2.0 * math.sqrt(dist / a)  # triangular: accelerate half way, decelerate the rest


def trapezoid_at(t: float, dist: float, v: float, a: float) -> tuple[float, float]:
    """Distance travelled and speed at a time into the profile.

    Parameters
    ----------
    t : float
        s from the start.
    dist : float
        m.
    v : float
        m/s.
    a : float
        m/s^2.

    Returns
    -------
    s : float
        m.
    speed : float
        m/s.
    """
    total = trapezoid_duration(dist, v, a)
    if dist <= 0 or t >= total:
        return max(dist, 0.0), 0.0
    if t <= 0:
        return 0.0, 0.0
    vp = min(v, math.sqrt(dist * a))  # peak speed
    ta = vp / a  # time to accelerate
    if t < ta:
        return 0.5 * a * t * t, a * t
    if t < total - ta:
        return 0.5 * a * ta * ta + vp * (t - ta), vp
    r = total - t
    return dist - 0.5 * a * r * r, a * r


@dataclass
class Motion:
    """One move in progress: from (q0, p0) towards p_goal; the plant was committed to (q1, p1), which
    is p_goal itself or, for a protective stop, the point where the arm stops (`stop_at` along the
    path). Times are wall-clock seconds; `time_scale` stretches the profile (0.1 = ten times faster)."""

    q0: np.ndarray
    p0: np.ndarray  # (3,) m
    q1: np.ndarray
    p1: np.ndarray  # where the arm ends (m)
    p_goal: np.ndarray  # where it was sent (m)
    v: float
    a: float
    t_start: float
    time_scale: float = 1.0
    stop_at: float | None = None  # distance along the path of a protective stop (m)

    @property
    def dist(self) -> float:
        """The distance to the goal (m)."""
        return float(np.linalg.norm(self.p_goal - self.p0))

    def _profile_t(self, now: float) -> float:
        return (now - self.t_start) / self.time_scale

    @property
    def t_end(self) -> float:
        """Wall time at which the arm stands still (at p_goal, or at the protective stop)."""
        d, v, a = self.dist, self.v, self.a
        if self.stop_at is None:
            return self.t_start + trapezoid_duration(d, v, a) * self.time_scale
        # the first time the profile reaches stop_at (bisection on a monotonic function)
        lo, hi = 0.0, trapezoid_duration(d, v, a)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if trapezoid_at(mid, d, v, a)[0] < self.stop_at:
                lo = mid
            else:
                hi = mid
        return self.t_start + hi * self.time_scale

    def done(self, now: float) -> bool:
        """True once the arm stands still.

        Parameters
        ----------
        now : float
            s, wall clock.

        Returns
        -------
        bool
        """
        return now >= self.t_end

    def sample(self, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The arm's state at a wall time.

        Parameters
        ----------
        now : float
            s, wall clock.

        Returns
        -------
        q : ndarray
            rad.
        qd : ndarray
            rad/s.
        p : ndarray
            (3,) m, TCP.
        v : ndarray
            (3,) m/s, TCP.
        """
        if self.done(now):
            z = np.zeros(3)
            return self.q1.copy(), np.zeros_like(self.q1), self.p1.copy(), z
        d = self.dist
        s, sd = trapezoid_at(self._profile_t(now), d, self.v, self.a)
        u = (self.p_goal - self.p0) / d if d > 0 else np.zeros(3)
        end = self.stop_at if self.stop_at is not None else d
        f = s / end if end > 0 else 1.0  # fraction of the committed joint motion done
        q = self.q0 + f * (self.q1 - self.q0)
        qd = (self.q1 - self.q0) * (sd / end if end > 0 else 0.0)
        return q, qd, self.p0 + s * u, sd * u
