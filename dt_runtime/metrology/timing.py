"""A moving arm measured at a time: the commanded path at the reading's mid-exposure, and the
uncertainty the timing adds.

A camera reading of a moving TCP is compared with the commanded path at its mid-exposure time
(interpolated between the timed set-points the arm was sent), not with the last command
(`compare_at`). See docs/streaming.md. Units: SI (m, s, m/s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError


@dataclass(frozen=True)
class TimedPath:
    """Timed set-points of a commanded path: t (n,) strictly increasing, s; p (n, 3), m."""

    t: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        t, p = np.asarray(self.t, dtype=float), np.asarray(self.p, dtype=float)
        if t.ndim != 1 or p.shape != (t.size, 3) or t.size < 2:
            raise DataError(f"a timed path needs n >= 2 times and n x 3 positions, got {t.shape} and {p.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise DataError("a timed path holds a non-finite time or position")
        if np.any(np.diff(t) <= 0):
            i = int(np.argmax(np.diff(t) <= 0))
            raise DataError(f"a timed path's times must increase: set-point {i + 1} at {t[i + 1]} s"
                            f" follows {t[i]} s")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "p", p)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The commanded position and velocity at time `t`.

        Linear between set-points; the velocity is that of the segment.

        Parameters
        ----------
        t : float
            Time, s, within [t_0, t_n].

        Returns
        -------
        position, velocity : ndarray
            Each (3,), m and m/s.

        Raises
        ------
        DataError
            Outside [t_0, t_n].
        """
        if not self.t[0] <= t <= self.t[-1]:
            raise DataError(f"time {t:.6f} s is outside the path ({self.t[0]:.6f} .. {self.t[-1]:.6f} s)")
        k = int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2))
        dt = self.t[k + 1] - self.t[k]
        v = (self.p[k + 1] - self.p[k]) / dt
        return self.p[k] + v * (t - self.t[k]), v

    def shifted(self, tau_s: float) -> TimedPath:
        """The same times, each sent the position the path has `tau_s` later (the last one held).

        A feed-forward that makes a follower lagging by tau_s arrive on time (programs.lag).

        Parameters
        ----------
        tau_s : float
            The lag, s.

        Returns
        -------
        TimedPath
        """
        return TimedPath(self.t, self.sample(self.p, np.clip(self.t + tau_s, self.t[0], self.t[-1])))

    def sample(self, values: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Values given at the set-points, linear between them, held beyond the ends.

        Parameters
        ----------
        values : ndarray
            (n, k) at the set-points (the positions, or their derivatives).
        t : ndarray
            (m,) times, s.

        Returns
        -------
        ndarray
            (m, k).
        """
        return np.column_stack([np.interp(t, self.t, values[:, j]) for j in range(values.shape[1])])


@dataclass(frozen=True)
class MovingComparison:
    """A reading of the moving arm set against the path at its mid-exposure time."""

    commanded: np.ndarray  # (3,) the path at the reading's time, m
    velocity: np.ndarray  # (3,) m/s
    u_timing: np.ndarray  # (3,) |v| u_t, m
    u_total: np.ndarray  # (3,) sqrt(u_reading^2 + u_timing^2), m: what Eq. 17 uses for the reading
    refused: str | None  # why the reading is not tested, or None

    @property
    def ok(self) -> bool:
        """True when the reading is tested (not refused)."""
        return self.refused is None


def compare_at(path: TimedPath, t_mid: float, u_time_s: float, u_reading, max_timing_ratio: float = 1.0
               ) -> MovingComparison:
    """Set a reading of the moving arm against the path at its mid-exposure time.

    An error u_t in the reading's time moves the compared point by v u_t, v the path's velocity
    there, so timing adds a Type B component u_timing = |v| u_t per axis (GUM 5.1.3: sensitivity
    coefficient v of the time), root-sum-squared with the reading's own uncertainty before Eq. 17.
    Where the timing term dominates the reading says more about the clock than about the arm: it
    is refused, with the reason. At rest (v = 0) nothing is added and nothing refused.

    Parameters
    ----------
    path : TimedPath
        The commanded path's timed set-points.
    t_mid : float
        The reading's mid-exposure time, s, on the path's clock.
    u_time_s : float
        Standard uncertainty of that time, s.
    u_reading : float or array-like
        The reading's standard uncertainty per axis, m.
    max_timing_ratio : float, optional
        Refuse when u_timing exceeds this times u_reading on an axis.

    Returns
    -------
    MovingComparison
        Refused (with the reason) outside the path's time span or where timing dominates.

    Raises
    ------
    DataError
        When `u_time_s` is not a finite time >= 0.
    """
    if not (np.isfinite(u_time_s) and u_time_s >= 0):
        raise DataError(f"u_time_s must be a finite time >= 0, got {u_time_s}")
    u_r = np.abs(np.asarray(u_reading, dtype=float)) * np.ones(3)
    nan3 = np.full(3, np.nan)
    try:
        c, v = path.at(t_mid)
    except DataError as exc:
        return MovingComparison(nan3, nan3, nan3, u_r, f"reading at {t_mid:.6f} s: {exc}")
    u_t = np.abs(v) * u_time_s
    refused = None
    worst = int(np.argmax(u_t - max_timing_ratio * u_r))
    if u_t[worst] > max_timing_ratio * u_r[worst]:
        axis = "xyz"[worst]
        refused = (f"timing dominates: at {1e3 * np.linalg.norm(v):.0f} mm/s a time uncertainty of"
                   f" {1e3 * u_time_s:.2f} ms adds {1e6 * u_t[worst]:.1f} um on {axis}, more than"
                   f" {max_timing_ratio:g} x the reading's {1e6 * u_r[worst]:.1f} um")
    return MovingComparison(c, v, u_t, np.sqrt(u_r ** 2 + u_t ** 2), refused)
