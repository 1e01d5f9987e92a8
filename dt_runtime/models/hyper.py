"""The effect terms' nonlinear parameters (`Effect.hyper`, e.g. the structure's thermal time
constant), estimated by profile likelihood (`profile`; the method: its docstring).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models import effects as fx


@dataclass(frozen=True)
class Estimate:
    """A nonlinear parameter's estimate: the value used, its standard uncertainty (None when not
    identified), its profile interval and unit.
    """
    value: float  # what the model uses
    u: float | None  # standard uncertainty (None: not identified)
    lo: float  # profile interval (-log L within 1/2 of its minimum)
    hi: float
    identified: bool
    unit: str

    def to_dict(self) -> dict:
        """The estimate as a JSON-ready dict."""
        return {"value": self.value, "u": self.u, "lo": self.lo, "hi": self.hi, "identified": self.identified,
                "unit": self.unit}

    @classmethod
    def from_dict(cls, d: dict) -> Estimate:
        """The estimate `to_dict` wrote.

        Parameters
        ----------
        d : dict
            A dict from `to_dict`.

        Returns
        -------
        Estimate
        """
        return cls(float(d["value"]), None if d.get("u") is None else float(d["u"]), float(d["lo"]),
                   float(d["hi"]), bool(d["identified"]), str(d["unit"]))


def rss_of(A: np.ndarray, y: np.ndarray, ridge: float) -> float:
    """Residual sum of squares of the ridge least squares y ~ A theta on standardised columns
    (the effect fit's ordinary step, `HybridModel.fit`).

    Parameters
    ----------
    A : ndarray
        (N, p) regressors.
    y : ndarray
        (N,) target.
    ridge : float
        The penalty.

    Returns
    -------
    float
    """
    scale = np.sqrt(np.mean(A ** 2, axis=0))
    keep = scale > 1e-300
    As = A[:, keep] / scale[keep]
    p = As.shape[1]
    if not p:
        return float(y @ y)
    lam = ridge * len(y) * 1e-3 / 3
    theta = np.linalg.solve(As.T @ As + lam * np.eye(p), As.T @ y)
    r = y - As @ theta
    return float(r @ r)


class FixedPart:
    """`rss_of` for regressors [B, a] where only a changes (the profiled effect's block between
    grid values): B's standardised columns, their Gram matrix B'B and B'y are computed once, so
    a grid value costs O(N p) (the cross products with a and the residual) instead of the
    O(N p^2) Gram of the whole design. Same numbers as rss_of on the concatenation."""

    def __init__(self, B: np.ndarray, y: np.ndarray, ridge: float):
        scale = np.sqrt(np.mean(B ** 2, axis=0))
        keep = scale > 1e-300
        self.Bs = B[:, keep] / scale[keep]
        self.G = self.Bs.T @ self.Bs
        self.By = self.Bs.T @ y
        self.y = y
        self.lam = ridge * len(y) * 1e-3 / 3

    def rss(self, a: np.ndarray) -> float:
        """RSS of the ridge fit of y on [B, a] (a: (N, q) the changing columns).

        Parameters
        ----------
        a : ndarray
            (N, q) the changing columns.

        Returns
        -------
        float
        """
        scale = np.sqrt(np.mean(a ** 2, axis=0))
        keep = scale > 1e-300
        As = a[:, keep] / scale[keep]
        pb, q = self.Bs.shape[1], As.shape[1]
        if not pb + q:
            return float(self.y @ self.y)
        H = np.empty((pb + q, pb + q))
        H[:pb, :pb], H[pb:, pb:] = self.G, As.T @ As
        H[:pb, pb:] = self.Bs.T @ As
        H[pb:, :pb] = H[:pb, pb:].T
        H[np.diag_indices(pb + q)] += self.lam
        theta = np.linalg.solve(H, np.concatenate([self.By, As.T @ self.y]))
        r = self.y - self.Bs @ theta[:pb] - As @ theta[pb:]
        return float(r @ r)


def profile(effects: tuple[str, ...], inp: fx.Inputs, error: np.ndarray, chain: Chain | None,
            ridge: float, catalogue: fx.Catalogue | None = None) -> dict[str, dict[str, Estimate]]:
    """The nonlinear parameters of `effects` (each at its profile-likelihood estimate: an effect's
    parameters one after the other, each with the ones before it at their estimates and the others'
    at their defaults), {effect: {parameter: Estimate}}. Effects whose
    parameters the inputs cannot inform (the thermal lag without a time column) are left out
    (their defaults apply).

    Parameters
    ----------
    effects : tuple of str
        The model's effects.
    inp : Inputs
        The data's columns.
    error : ndarray
        (n, 3), m.
    chain : Chain or None
        The robot's kinematic chain.
    ridge : float
        The effect fit's penalty.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    dict

    Notes
    -----
    For each value on the effect's grid, the linear parameters of every effect are fitted by least
    squares and the residual sum of squares kept; the estimate minimises it (refined between grid
    neighbours), and its standard uncertainty is half the width of the interval where the profile
    log-likelihood is within 1/2 of its maximum (Gaussian errors: -log L = N/2 log RSS + const, N
    the number of scalar residuals; rows that repeat a point are not independent, so the interval
    is a lower bound on the uncertainty).

    A value whose interval reaches the end of the grid is not identified: the data do not bound it
    (`Estimate.identified` False; e.g. a temperature that hardly changed, or a lag longer than the
    data). The model then uses the grid's first value (0 s: the air temperature as logged).
    """
    out: dict[str, dict[str, Estimate]] = {}
    cat = catalogue if catalogue is not None else fx.default()
    wanted = [e for e in effects if cat.get(e).hyper and inp.has(*cat.get(e).hyper_columns)]
    if not wanted:
        return out
    y = np.asarray(error, dtype=float).ravel()
    fixed = [cat.build(e, inp, chain).A for e in effects if e not in wanted]
    for name in wanted:
        eff = cat.get(name)
        others = [cat.build(e, inp, chain).A for e in wanted if e != name]
        base = np.concatenate(fixed + others, axis=2) if fixed or others else np.zeros((inp.n, 3, 0))
        # Only the profiled effect's block changes between grid values: the rest once (FixedPart).
        part = FixedPart(base.reshape(len(y), -1), y, ridge)
        out[name] = {}
        chosen: dict[str, float] = {}  # the effect's parameters estimated so far (in the grid's order)
        for param, grid in eff.hyper.items():
            def rss(v: float, param: str = param, eff: fx.Effect = eff, part: FixedPart = part,
                    before: tuple = tuple(chosen.items())) -> float:
                return part.rss(eff.build(inp, chain, dict(before) | {param: v}).A.reshape(len(y), -1))

            choices = eff.hyper_choices.get(param)
            out[name][param] = (_choice(rss, np.asarray(grid, float), len(y)) if choices else
                                _estimate(rss, np.asarray(grid, float), len(y), eff.hyper_units.get(param, "")))
            chosen[param] = out[name][param].value
    return out


def _choice(rss: Callable[[float], float], grid: np.ndarray, n: int) -> Estimate:
    """A choice between alternatives (grid values): the one of least RSS. Identified when every
    other alternative is worse by more than 1/2 in -log L (the profile interval holds it alone)."""
    values = np.array([rss(v) for v in grid])
    k = int(np.argmin(values))
    nll = 0.5 * n * np.log(np.maximum(values, 1e-300) / max(float(values[k]), 1e-300))
    others = np.delete(nll, k)
    best = float(grid[k])
    return Estimate(best, None, best, best, bool(len(others) == 0 or others.min() > 0.5), "")


def _estimate(rss: Callable[[float], float], grid: np.ndarray, n: int, unit: str) -> Estimate:
    values = np.array([rss(v) for v in grid])
    k = int(np.argmin(values))
    best, best_rss = float(grid[k]), float(values[k])
    if 0 < k < len(grid) - 1 and grid[k - 1] > 0:  # refine on log scale between the neighbours
        res = optimize.minimize_scalar(lambda u: rss(float(np.exp(u))), method="bounded",
                                       bounds=(np.log(grid[k - 1]), np.log(grid[k + 1])),
                                       options={"xatol": 1e-3})
        if res.fun < best_rss:
            best, best_rss = float(np.exp(res.x)), float(res.fun)
    nll = 0.5 * n * np.log(np.maximum(values, 1e-300) / max(best_rss, 1e-300))
    inside = grid[nll <= 0.5]
    lo = float(min(inside.min(), best)) if len(inside) else best
    hi = float(max(inside.max(), best)) if len(inside) else best
    # Bounded when the interval stays off the grid's far end (and the profile is not flat).
    identified = bool(nll[-1] > 0.5 and len(inside) < len(grid))
    if not identified:
        return Estimate(float(grid[0]), None, lo, hi, False, unit)
    # The interval's ends between grid values: interpolate where -log L crosses 1/2.
    lo, hi = _crossing(grid, nll, best, -1), _crossing(grid, nll, best, +1)
    return Estimate(best, (hi - lo) / 2, lo, hi, True, unit)


def _crossing(grid: np.ndarray, nll: np.ndarray, best: float, side: int) -> float:
    """Where the profile's -log L rises through 1/2 on `side` of best (linear between grid values)."""
    idx = np.arange(len(grid))
    order = idx[grid > best] if side > 0 else idx[grid < best][::-1]
    prev_v, prev_n = best, 0.0
    for i in order:
        if nll[i] > 0.5:
            f = (0.5 - prev_n) / max(nll[i] - prev_n, 1e-300)
            return float(prev_v + f * (grid[i] - prev_v))
        prev_v, prev_n = float(grid[i]), float(nll[i])
    return float(grid[order[-1]]) if len(order) else best
