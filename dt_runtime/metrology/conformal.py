"""A stated U that holds on new positions by construction: split conformal calibration of the GUM
expanded uncertainty on held-out residuals (docs/cli.md, "Validity: every figure carries its own").

The nonconformity score of a held-out positioning i, per axis, is s_i = |r_i| / U_i: its residual
(by a map that never saw its target point) over the U the twin would have stated there. Rows of one
target point are not independent, so the exchangeable unit is the target point: each point g
contributes the fraction F_g(s) of its rows with a score <= s, and the factor is

    c = min { s : sum_g F_g(s) >= ceil((n + 1) (1 - alpha)) }     (n target points)

which is the ceil((n+1)(1-alpha))-th smallest score when every point has one row (split conformal,
Vovk et al. 2005; Lei et al. 2018). With replicates it is the pooled per-point coverage: for a new
target point exchangeable with the n held-out ones, a positioning drawn from it lies within c U
with probability >= 1 - alpha (the symmetric threshold over all n + 1 points is <= c, and its
expected coverage of the new point is >= 1 - alpha by exchangeability). The twin states
max(1, c) U: the GUM budget is the traceable statement and the calibration may only widen it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dt_kernel.errors import ModelError

ALPHA = 0.05  # 95 % expanded uncertainty
METHOD = "split conformal, grouped by target point"
NONE = "none"


def guarantee(alpha: float = ALPHA) -> str:
    """The statement a conformal scale carries, in words.

    Parameters
    ----------
    alpha : float
        Miscoverage (0.05 for 95 %).

    Returns
    -------
    str
    """
    return (f"marginal coverage >= {100 * (1 - alpha):g} % for exchangeable new positions (split conformal over "
            "held-out target points)")


def rank(n: int, alpha: float = ALPHA) -> int:
    """ceil((n + 1)(1 - alpha)): how many of n calibration points' coverage the factor must reach.

    Parameters
    ----------
    n : int
        Calibration points (exchangeable units).
    alpha : float
        Miscoverage (0.05 for 95 %).

    Returns
    -------
    int
        > n when n is too small for any finite factor to carry the guarantee (n < 1/alpha - 1).
    """
    return math.ceil((n + 1) * (1 - alpha) - 1e-12)


def grouped_quantile(scores: np.ndarray, groups: np.ndarray, alpha: float = ALPHA) -> tuple[float, int, bool]:
    """The split conformal factor of one axis' scores, grouped (see the module docstring).

    Parameters
    ----------
    scores : ndarray
        (m,) nonconformity scores, >= 0 (NaN rows are dropped).
    groups : ndarray
        (m,) the exchangeable unit of each row (the target point).
    alpha : float
        Miscoverage.

    Returns
    -------
    factor : float
        The smallest s whose pooled per-group coverage reaches `rank(n)`; when n is too small
        for that, the largest score (no guarantee).
    n : int
        Groups used.
    guaranteed : bool
        Whether n was large enough for the guarantee.
    """
    s = np.asarray(scores, dtype=float)
    g = np.asarray(groups)
    ok = np.isfinite(s)
    s, g = s[ok], g[ok]
    if len(s) == 0:
        return float("nan"), 0, False
    _, inv = np.unique(g, return_inverse=True)
    inv = inv.ravel()
    n = int(inv.max()) + 1
    w = 1.0 / np.bincount(inv)[inv]  # each group weighs 1 in total: its rows share it
    order = np.argsort(s, kind="stable")
    cum = np.cumsum(w[order])
    k = rank(n, alpha)
    if k > n:
        return float(s.max()), n, False
    j = int(np.searchsorted(cum, k - 1e-9))  # first sorted score where the pooled coverage reaches k
    return float(s[order[min(j, len(s) - 1)]]), n, True


@dataclass(frozen=True)
class ConformalScale:
    """The conformal factor the twin's U(TCP_c) is multiplied by, per GL axis.

    Attributes
    ----------
    factor : ndarray
        (3,) applied: max(1, c) per axis (1 for a twin without the calibration).
    raw : ndarray
        (3,) c per axis as calibrated (NaN for 'none').
    n : int
        Exchangeable calibration units (distinct held-out target points).
    rows : int
        Held-out positionings scored.
    method : str
        `METHOD`, or 'none' (an older twin: factor 1).
    guarantee : str
        What the factor guarantees, or why nothing is guaranteed.
    """

    factor: np.ndarray = field(default_factory=lambda: np.ones(3))
    raw: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    n: int = 0
    rows: int = 0
    method: str = NONE
    guarantee: str = "none: the GUM U as stated, not calibrated on held-out data"

    @property
    def applied(self) -> bool:
        """Whether it changes any U."""
        return bool(np.any(self.factor != 1.0))

    def to_dict(self) -> dict[str, Any]:
        """twin.json's `uncertainty_calibration` (also the summaries' key)."""
        return {"method": self.method, "n": self.n, "rows": self.rows, "alpha": ALPHA,
                "factor": [float(f) for f in self.factor],
                "raw_factor": [float(f) if np.isfinite(f) else None for f in self.raw],
                "applied": "U = max(1, c) x U_GUM per axis (never below the GUM budget)",
                "guarantee": self.guarantee}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> ConformalScale:
        """What `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            twin.json's `uncertainty_calibration`.
        where : str
            For the error message.

        Returns
        -------
        ConformalScale

        Raises
        ------
        ModelError
            A missing key, or a factor not finite and >= 1 per axis.
        """
        try:
            f = np.asarray(d["factor"], dtype=float)
            raw = np.asarray([np.nan if v is None else v for v in d.get("raw_factor", [None] * 3)], dtype=float)
            out = cls(f, raw, int(d["n"]), int(d.get("rows", 0)), str(d["method"]), str(d["guarantee"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{where}: uncertainty_calibration needs factor, n, method, guarantee ({exc!r})") from exc
        if f.shape != (3,) or not np.all(np.isfinite(f) & (f >= 1.0)):
            raise ModelError(f"{where}: uncertainty_calibration factor {f.tolist()}: expected 3 finite values >= 1")
        return out


def calibrate(r: np.ndarray, U: np.ndarray, groups: np.ndarray, alpha: float = ALPHA) -> ConformalScale:
    """The conformal scale from held-out residuals and the U each held-out row would have been stated.

    Parameters
    ----------
    r : ndarray
        (m, 3) m, held-out residuals (each row predicted by a map that never saw its target point).
    U : ndarray
        (m, 3) m, the GUM expanded uncertainty stated at each row.
    groups : ndarray
        (m,) target point id (the exchangeable unit).
    alpha : float
        Miscoverage (0.05: the 95 % U).

    Returns
    -------
    ConformalScale
        factor max(1, c) per axis; with fewer than 1/alpha - 1 points (19 at 95 %) the largest score
        and a guarantee that says none holds.
    """
    r, U = np.asarray(r, dtype=float), np.asarray(U, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(U > 0, np.abs(r) / U, np.where(r == 0, 0.0, np.inf))
    raw, ns, ok = [], [], []
    for k in range(3):
        c, n, g = grouped_quantile(s[:, k], groups, alpha)
        raw.append(c)
        ns.append(n)
        ok.append(g)
    raw_a = np.array(raw)
    n = int(min(ns))
    if not all(ok) or not np.all(np.isfinite(raw_a)):
        return ConformalScale(np.ones(3), raw_a, n, len(r), NONE,
                              f"none: {n} held-out target points, fewer than the {math.ceil(1 / alpha) - 1} a "
                              f"{100 * (1 - alpha):g} % split conformal factor needs; the GUM U as stated")
    return ConformalScale(np.maximum(raw_a, 1.0), raw_a, n, len(r), METHOD, guarantee(alpha))
