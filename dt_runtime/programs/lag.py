"""Lag compensation of a streamed path: a servo follower identified from one measured pass
(`estimate_lag`: w x'' + T x' + x = c(t - delta), the command c streamed and the positions x
measured) and removed by its exact inverse as a feed-forward (`compensate`: c(t) = D(t + delta),
D = d + T d' + w d''). The series e = a c' + b c'' (a = T + delta, b + a^2 = w + T delta +
delta^2 / 2) is the fit's starting point and what is reported. Units: SI (s, m).

The model, its derivation and measured results: docs/streaming.md, "The servo lag".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.metrology.stats import rms3
from dt_runtime.metrology.timing import TimedPath

SETTLE_S = 0.2  # s: a servo's transient after a step of the path's acceleration is over (1 / (zeta w) = 55 ms
# at look-ahead 0.03 s, gain 1200; a few of its time constants at the default look-ahead 0.1 s, gain 300)


@dataclass(frozen=True)
class LagEstimate:
    """A follower's lag learnt from one measured pass (`estimate_lag`).

    Attributes
    ----------
    tau_s : float
        a: the lag (s).
    u_tau_s : float
        Its standard uncertainty (s).
    accel_s2 : float
        b + a^2: the feed-forward's coefficient of the path's acceleration (s^2; 1/K for a servo).
    u_accel_s2 : float
        Its standard uncertainty (s^2).
    n : int
        Measured positions used (those on the moving part of the path).
    rms_before_m : float
        3D RMS of commanded - measured at the measured times (m).
    rms_after_m : float
        3D RMS of what the fitted model leaves (m).
    servo : tuple or None
        The identified follower w x'' + T x' + x = c(t - delta): (T s, w s^2 = 1/gain, delta s);
        None for an estimate of the series only (a stored one of an older version).
    """

    tau_s: float  # a: the lag (s)
    u_tau_s: float  # standard uncertainty of tau
    accel_s2: float  # b + a^2: the feed-forward's coefficient of the path's acceleration (s^2; 1/K for a servo)
    u_accel_s2: float
    n: int  # measured positions used (those on the moving part of the path)
    rms_before_m: float  # 3D RMS of commanded - measured at the measured times
    rms_after_m: float  # ... of what the identified model leaves
    servo: tuple[float, float, float] | None = None  # (T s, w s^2, delta s): the identified follower, or None

    @classmethod
    def from_dict(cls, d: dict) -> LagEstimate:
        """`to_dict`'s inverse (a stored estimate).

        Parameters
        ----------
        d : dict
            Keys tau_ms, u_tau_ms, accel_ms2, u_accel_ms2 (ms^2), n, rms_before_mm, rms_after_mm and,
            optionally, servo {T_ms, w_ms2, delay_ms}.

        Returns
        -------
        LagEstimate
        """
        sv = d.get("servo")
        servo = None if not sv else (1e-3 * sv["T_ms"], 1e-6 * sv["w_ms2"], 1e-3 * sv["delay_ms"])
        return cls(1e-3 * d["tau_ms"], 1e-3 * d["u_tau_ms"], 1e-6 * d["accel_ms2"], 1e-6 * d["u_accel_ms2"],
                   int(d["n"]), 1e-3 * d["rms_before_mm"], 1e-3 * d["rms_after_mm"], servo)

    def to_dict(self) -> dict:
        """JSON form in ms, ms^2 and mm (keys as `from_dict` reads them)."""
        d: dict[str, Any] = {
            "tau_ms": 1e3 * self.tau_s, "u_tau_ms": 1e3 * self.u_tau_s, "accel_ms2": 1e6 * self.accel_s2,
            "u_accel_ms2": 1e6 * self.u_accel_s2, "n": self.n,
            "rms_before_mm": 1e3 * self.rms_before_m, "rms_after_mm": 1e3 * self.rms_after_m}
        if self.servo is not None:
            T, w, delay = self.servo
            d["servo"] = {"T_ms": 1e3 * T, "w_ms2": 1e6 * w, "delay_ms": 1e3 * delay}
        return d


def _derivatives(path: TimedPath) -> tuple[np.ndarray, np.ndarray]:
    """The path's velocity and acceleration at its set-points (central differences)."""
    v = np.gradient(path.p, path.t, axis=0)
    return v, np.gradient(v, path.t, axis=0)


def estimate_lag(path: TimedPath, t: np.ndarray, measured: np.ndarray, max_lag_s: float = 0.5) -> LagEstimate:
    """The follower's lag and acceleration term behind `path` from positions `measured` (n, 3),
    m, at times `t` (n,), s, on the path's clock; times in the path's first `max_lag_s` are left
    out (the start-up transient).

    Parameters
    ----------
    path : TimedPath
        The commanded path (s, m).
    t : ndarray
        (n,) s, the measurement times on the path's clock.
    measured : ndarray
        (n, 3) m, the measured positions; non-finite rows are skipped.
    max_lag_s : float
        The start-up left out (s).

    Returns
    -------
    LagEstimate

    Raises
    ------
    DataError
        `t` and `measured` disagree in shape, fewer than 10 positions remain, or the path does not
        move or change speed or direction (the two terms cannot be told apart).
    """
    t, m = np.asarray(t, dtype=float), np.asarray(measured, dtype=float)
    if m.shape != (t.size, 3):
        raise DataError(f"estimate_lag needs n times and n x 3 positions, got {t.shape} and {m.shape}")
    keep = np.isfinite(t) & np.all(np.isfinite(m), axis=1) & (t >= path.t[0] + max_lag_s) & (t <= path.t[-1])
    if keep.sum() < 10:
        raise DataError(f"estimate_lag needs at least 10 measured positions on the path after its first"
                        f" {max_lag_s} s, got {int(keep.sum())}")
    t, m = t[keep], m[keep]
    v, acc = _derivatives(path)
    c = path.sample(path.p, t)
    e = (c - m).ravel()
    A = np.column_stack([path.sample(v, t).ravel(), path.sample(acc, t).ravel()])
    # a path at rest (|v| below 1 um/s) or with neither speed nor direction changing cannot tell them apart
    if np.sqrt(np.mean(A[:, 0] ** 2)) < 1e-6 or np.linalg.cond(A) > 1e8:
        raise DataError("estimate_lag needs a path that moves and changes speed or direction")
    coef, *_ = np.linalg.lstsq(A, e, rcond=None)
    r = e - A @ coef
    dof = max(1, e.size - 2)
    cov = np.linalg.inv(A.T @ A) * float(r @ r) / dof
    a, b = float(coef[0]), float(coef[1])
    series = (a, b + a * a)
    g = np.array([2 * a, 1.0])  # the feed-forward's coefficient b + a^2, first order in a and b
    u_series = (float(np.sqrt(cov[0, 0])), float(np.sqrt(g @ cov @ g)))
    fit = _identify(path, t, m, series)
    if fit is None or rms3(fit[3].reshape(-1, 3)) >= rms3(r.reshape(-1, 3)):
        # the series explains the pass as well (a follower that is no servo, noise): keep it
        return LagEstimate(a, u_series[0], series[1], u_series[1], int(t.size), rms3(c - m), rms3(r.reshape(-1, 3)))
    (T, w, delay), u_tau, u_accel, res = fit
    return LagEstimate(T + delay, u_tau, w + T * delay + 0.5 * delay ** 2, u_accel, int(t.size), rms3(c - m),
                       rms3(res.reshape(-1, 3)), (T, w, delay))


# Bounds of the identified follower (T s, w s^2, delta s): servoj's look-ahead 0.03-0.2 s and gain 100-2000
# (w 0.5-10 ms^2) lie well inside; w -> 0 is a first-order follower, delta a transport or hold delay.
_LOWER, _UPPER = np.array([1e-4, 1e-7, 0.0]), np.array([1.0, 0.1, 0.2])


def _follow(path: TimedPath, T: float, w: float, delay: float) -> np.ndarray:
    """The follower w x'' + T x' + x = c(t - delay) on the commanded path c (linear between its
    set-points, as a controller ramps to each within its cycle), from rest at c's first point:
    x at the path's set-point times, (n, 3). Exact discretisation (first-order hold, Franklin,
    Powell & Workman, Digital Control, 6.3) on the path's mean period."""
    from scipy.linalg import expm

    t = path.t
    h = float((t[-1] - t[0]) / max(t.size - 1, 1))
    c = path.sample(path.p, np.maximum(t - delay, t[0]))
    A = np.array([[0.0, 1.0], [-1.0 / w, -T / w]])
    M = np.zeros((4, 4))
    M[:2, :2], M[1, 2], M[2, 3] = A, 1.0 / w, 1.0
    E = expm(M * h)
    Ad, G1, G2 = E[:2, :2], E[:2, 2:3], E[:2, 3:4] / h
    z = np.vstack([c[0], np.zeros(3)])
    out = np.empty_like(c)
    out[0] = c[0]
    for k in range(1, t.size):
        z = Ad @ z + G1 * c[k - 1] + G2 * (c[k] - c[k - 1])
        out[k] = z[0]
    return out


def _identify(path: TimedPath, t: np.ndarray, m: np.ndarray, series: tuple[float, float]):
    """The follower (T, w, delta) whose response to the commanded path best matches the measured
    positions m at times t (nonlinear least squares, started from the series' a and b + a^2);
    with the standard uncertainties of tau = T + delta and of the series' b + a^2, and the
    residuals. None when the fit fails."""
    from scipy.optimize import least_squares

    a, k2 = series
    x0 = np.clip([a, k2, 0.0], _LOWER * 1.01, _UPPER * 0.99)
    scale = np.array([1e-3, 1e-6, 1e-3])  # ms, ms^2, ms: the parameters near 1

    def resid(q: np.ndarray) -> np.ndarray:
        T, w, delay = q * scale
        return (path.sample(_follow(path, T, w, delay), t) - m).ravel()

    try:
        sol = least_squares(resid, x0 / scale, bounds=(_LOWER / scale, _UPPER / scale), x_scale="jac")
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not sol.success:
        return None
    T, w, delay = sol.x * scale
    J = sol.jac / scale  # d resid / d (T, w, delta)
    dof = max(1, sol.fun.size - 3)
    # pinv: where the readings cannot tell T from delta (sparse, noisy) their sum is still known
    cov = np.linalg.pinv(J.T @ J, rcond=1e-12) * float(sol.fun @ sol.fun) / dof
    g_tau = np.array([1.0, 0.0, 1.0])
    g_k2 = np.array([delay, 1.0, T + delay])
    return ((float(T), float(w), float(delay)), float(np.sqrt(g_tau @ cov @ g_tau)),
            float(np.sqrt(g_k2 @ cov @ g_k2)), sol.fun)


def settled(path: TimedPath, settle_s: float = SETTLE_S, jump: float = 0.05) -> np.ndarray:
    """Per set-point (n,): True when the path's acceleration has not jumped within the last
    `settle_s` (a jump: a change between two set-points larger than `jump` x the path's largest
    acceleration). A trapezoidal profile's acceleration steps at every start, end of a ramp and
    change of curvature; a follower (and a feed-forward built on the path's second derivative,
    which steps there too) leaves a transient of a few time constants after each, where neither
    e = a c' + b c'' nor its inverse holds: a reading there tests the servo, not the twin.

    Parameters
    ----------
    path : TimedPath
        The commanded path (s, m).
    settle_s : float
        How long a transient lasts after a jump (s).
    jump : float
        A jump's threshold, as a fraction of the path's largest acceleration.

    Returns
    -------
    ndarray
        (n,) bool, one per set-point of `path`; all True for a path at rest.
    """
    _, acc = _derivatives(path)
    da = np.linalg.norm(np.diff(acc, axis=0), axis=1)
    peak = float(np.max(np.linalg.norm(acc, axis=1))) if len(acc) else 0.0
    ok = np.ones(path.t.size, dtype=bool)
    if peak < 1e-6:  # m/s^2: a path at rest (its differences' rounding is not an acceleration)
        return ok
    for k in np.flatnonzero(da > jump * peak):
        ok[(path.t >= path.t[k]) & (path.t < path.t[k + 1] + settle_s)] = False
    return ok


def compensate(path: TimedPath, lag: LagEstimate | float) -> TimedPath:
    """The path to stream so that the follower is on `path` on time: with an estimate, the
    identified follower's inverse (D = d + T d' + w d'' sent delta early; an estimate without
    the model: the series d + a d' + (b + a^2) d''); with a number (s), the path shifted by it.

    Parameters
    ----------
    path : TimedPath
        The desired path (s, m).
    lag : LagEstimate or float
        An estimate (`estimate_lag`), or a lag in s.

    Returns
    -------
    TimedPath
        The path to stream.

    Raises
    ------
    DataError
        A lag given as a number that is not finite and >= 0.
    """
    if not isinstance(lag, LagEstimate):
        tau = float(lag)
        if not (np.isfinite(tau) and tau >= 0):
            raise DataError(f"a lag must be a finite time >= 0, got {tau}")
        return path.shifted(tau)
    v, acc = _derivatives(path)
    if lag.servo is None:
        return TimedPath(path.t, path.p + lag.tau_s * v + lag.accel_s2 * acc)
    T, w, delay = lag.servo
    ahead = TimedPath(path.t, path.p + T * v + w * acc)  # D = d + T d' + w d'': the follower's inverse
    return TimedPath(path.t, ahead.sample(ahead.p, np.minimum(path.t + delay, path.t[-1])))  # sent delta early
