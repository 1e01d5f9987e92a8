"""Lag compensation of a streamed path (issue 23, item 5).

A servo follower (a UR's servoj with its look-ahead time and gain) reaches a streamed set-point
late: along a path at velocity v the arm stands about v tau behind the command, a systematic
error of 0.1-2 mm at 100-500 mm/s for tau of a few milliseconds that the static error map does not
contain. It is learnt from one measured pass of the path and removed by feed-forward:

- `estimate_lag`: tau minimising sum_i |c(t_i - tau) - m_i|^2 over the measured positions m_i
  at times t_i (c the commanded path, linear between set-points), on [0, max_lag_s] (a bounded
  scalar search, then the standard uncertainty of tau from the curvature of that sum: the
  residual variance over sum |v|^2, as for a linear fit of e = v tau);
- `compensate`: the path each set-point time sends the position the path has tau later
  (`TimedPath.shifted`), so the arm, tau late, is where the path should be.

A pure time shift models a first-order lag; what a second-order follower adds on curves (the
corner cutting of its overshoot) stays in the residual, which is reported with tau.
Units: SI (s, m).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from dt_kernel.errors import DataError
from dt_runtime.metrology.stats import rms3
from dt_runtime.metrology.timing import TimedPath


@dataclass(frozen=True)
class LagEstimate:
    tau_s: float
    u_tau_s: float  # standard uncertainty of tau
    n: int  # measured positions used (those on the moving part of the path)
    rms_before_m: float  # 3D RMS of commanded - measured at the measured times
    rms_after_m: float  # ... of the commanded path delayed by tau - measured

    def to_dict(self) -> dict:
        return {"tau_ms": 1e3 * self.tau_s, "u_tau_ms": 1e3 * self.u_tau_s, "n": self.n,
                "rms_before_mm": 1e3 * self.rms_before_m, "rms_after_mm": 1e3 * self.rms_after_m}


def _delayed(path: TimedPath, t: np.ndarray, tau: float) -> np.ndarray:
    tq = np.clip(t - tau, path.t[0], path.t[-1])
    return np.column_stack([np.interp(tq, path.t, path.p[:, j]) for j in range(3)])


def estimate_lag(path: TimedPath, t: np.ndarray, measured: np.ndarray, max_lag_s: float = 0.5) -> LagEstimate:
    """The follower's lag behind `path` from positions `measured` (n, 3), m, at times `t` (n,),
    s, on the path's clock; only times at least `max_lag_s` after the path's start are used (the
    start-up transient)."""
    t, m = np.asarray(t, dtype=float), np.asarray(measured, dtype=float)
    if m.shape != (t.size, 3):
        raise DataError(f"estimate_lag needs n times and n x 3 positions, got {t.shape} and {m.shape}")
    keep = np.isfinite(t) & np.all(np.isfinite(m), axis=1) & (t >= path.t[0] + max_lag_s) & (t <= path.t[-1])
    if keep.sum() < 10:
        raise DataError(f"estimate_lag needs at least 10 measured positions on the path after its first"
                        f" {max_lag_s} s, got {int(keep.sum())}")
    t, m = t[keep], m[keep]

    def cost(tau: float) -> float:
        return float(np.sum((_delayed(path, t, tau) - m) ** 2))

    tau = float(minimize_scalar(cost, bounds=(0.0, max_lag_s), method="bounded",
                                options={"xatol": 1e-7}).x)
    r = _delayed(path, t, tau) - m
    # velocity of the path at the measured times: the sensitivity of the fit to tau
    dt = max(1e-4, float(np.median(np.diff(path.t))))
    v = (_delayed(path, t, tau - dt / 2) - _delayed(path, t, tau + dt / 2)) / dt
    sv2 = float(np.sum(v ** 2))
    dof = max(1, r.size - 1)
    u = float(np.sqrt(np.sum(r ** 2) / dof / sv2)) if sv2 > 0 else float("inf")
    return LagEstimate(tau, u, int(t.size), rms3(_delayed(path, t, 0.0) - m), rms3(r))


def compensate(path: TimedPath, lag: LagEstimate | float) -> TimedPath:
    """The path to stream so that a follower `lag` behind it is on the path on time."""
    tau = lag.tau_s if isinstance(lag, LagEstimate) else float(lag)
    if not (np.isfinite(tau) and tau >= 0):
        raise DataError(f"a lag must be a finite time >= 0, got {tau}")
    return path.shifted(tau)
