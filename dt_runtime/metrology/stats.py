"""Summary statistics every table and report states: 3D RMS with its uncertainty, per-axis mean
and standard deviation, and a binomial proportion's interval. One definition each."""
from __future__ import annotations

import math

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.metrology.uncertainty import INF, coverage_factor

Z95 = 1.959964  # two-sided 95 % quantile of the normal distribution


def finite_rows(*arrs: np.ndarray) -> np.ndarray:
    """Rows where every array is finite (1D arrays per element, 2D arrays over each row).

    Parameters
    ----------
    *arrs : ndarray
        At least one array, all with the same number of rows.

    Returns
    -------
    ndarray
        (n,) bool.
    """
    ok: np.ndarray | None = None
    for a in arrs:
        m = np.isfinite(a) if a.ndim == 1 else np.all(np.isfinite(a), axis=1)
        ok = m if ok is None else ok & m
    assert ok is not None, "finite_rows needs at least one array"
    return ok


def rms3(e: np.ndarray) -> float:
    """3D RMS of (n, 3) vectors, in the unit of e: sqrt(mean |e|^2).

    Parameters
    ----------
    e : ndarray
        (n, 3).

    Returns
    -------
    float
    """
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


def t95(dof: float | None) -> float:
    """The 95 % coverage factor for `dof` degrees of freedom (normal when unknown or infinite).

    Parameters
    ----------
    dof : float or None
        Degrees of freedom.

    Returns
    -------
    float
    """
    return float(coverage_factor(dof if dof and np.isfinite(dof) and dof > 0 else INF))


def rms_with_U(e: np.ndarray) -> tuple[float, float, int]:
    """3D RMS and its expanded uncertainty by the delta method.

    Positionings are treated as independent: u(MS) = s(|e|^2)/sqrt(n), u(RMS) = u(MS)/(2 RMS),
    k = t_0.975(n-1). Non-finite rows are dropped.

    Parameters
    ----------
    e : ndarray
        (n, 3).

    Returns
    -------
    rms, U : float
        In the unit of e (NaN with fewer than 2 rows).
    n : int
        The rows used.
    """
    e = e[finite_rows(e)]
    n = len(e)
    if n < 2:
        return float("nan"), float("nan"), n
    sq = np.sum(e ** 2, axis=1)
    rms = math.sqrt(sq.mean())
    u = float(sq.std(ddof=1) / math.sqrt(n) / (2 * rms)) if rms > 0 else float("nan")
    return rms, t95(n - 1) * u, n


def mean_std_mm(e: np.ndarray) -> dict:
    """Per-axis mean and standard deviation (mm) of an (n, 3) array in metres (Tables 2-4).

    Parameters
    ----------
    e : ndarray
        (n, 3), m.

    Returns
    -------
    dict
        {axis: {"mean_mm", "std_mm"}, "n": n}.
    """
    return {ax: {"mean_mm": float(e[:, k].mean() * MM_PER_M), "std_mm": float(e[:, k].std(ddof=1) * MM_PER_M)}
            for k, ax in enumerate(AXES)} | {"n": int(len(e))}


def wilson_interval(k: float, n: float, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n.

    Used for the coverage of stated uncertainties; k and n may be effective counts, e.g. over
    distinct targets.

    Parameters
    ----------
    k, n : float
        Successes and trials.
    z : float, optional
        Normal quantile (95 % two-sided by default).

    Returns
    -------
    low, high : float
        NaN when n is 0.
    """
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, c - h), min(1.0, c + h)
