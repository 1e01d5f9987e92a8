"""Can the campaign separate a candidate effect at all? Checked before the effect is tested (`check`).

An effect is testable only where its driving factor varies independently of the pose: a GP on
the pose takes up whatever the factor does when the factor is itself a function of the pose
(the classic case is a scan, where time is position). See docs/effects.md ("How a diagnosis reads").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from dt_runtime.models import effects as fx
from dt_runtime.models.effects.base import approach

# Time is separable from the pose only when poses are measured again later: at least MIN_REVISITS
# points whose rows span at least REVISIT_GAP of the campaign's time (a scan has none).
MIN_REVISITS = 5
REVISIT_GAP = 0.1
R2_MAX = 0.9  # above this share of a factor's variance predicted by the pose (or another factor): confounded
NEIGHBOURS = 5
CONTRACT = {"time": "t", "temperature": "temperature", "speed": "speed", "payload": "payload"}


@dataclass(frozen=True)
class Finding:
    """A candidate's factor against what it is confounded with: `against` is 'pose' (R^2 of the
    nearest-neighbour prediction), 'scan' (time: no pose measured again later; `revisited` of
    `points` poses were), 'constant' (it does not vary) or another factor ('time')."""

    candidate: str
    factor: str
    against: str
    r2: float | None
    testable: bool
    revisited: int | None = None
    points: int | None = None

    def to_dict(self) -> dict:
        """The finding as a JSON-ready dict."""
        out = {"candidate": self.candidate, "factor": self.factor, "against": self.against,
               "r2": None if self.r2 is None else float(self.r2), "testable": self.testable}
        if self.revisited is not None:
            out |= {"revisited": self.revisited, "points": self.points, "min_gap": REVISIT_GAP}
        return out


def factor_values(factor: str, inp: fx.Inputs) -> np.ndarray | None:
    """The values of a factor on every row, (n, k): the direction of approach as the sign of each
    joint's last move (the Cartesian unit direction without joints).

    Parameters
    ----------
    factor : str
        The factor's name.
    inp : Inputs
        The data's columns.

    Returns
    -------
    ndarray or None
    """
    if factor == "direction":
        if inp.joints is not None:
            return np.sign(approach(inp.joints, per_column=True))
        d = approach(inp.commanded)
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    v = inp.get(CONTRACT.get(factor, factor))
    return None if v is None else np.asarray(v, float).reshape(len(inp.commanded), -1)


def varies(v: np.ndarray) -> bool:
    """More than one value in some column (beyond round-off).

    Parameters
    ----------
    v : ndarray
        (n,) or (n, k).

    Returns
    -------
    bool
    """
    span = np.ptp(v, axis=0)
    return bool(np.any(span > 1e-9 * np.maximum(1.0, np.abs(v).max(axis=0))))


def pose_r2(values: np.ndarray, pose: np.ndarray, groups: np.ndarray, k: int = NEIGHBOURS) -> float:
    """Share of the variance of `values` (n, c) that the mean over the k nearest rows of *other*
    points (standardised `pose` coordinates) predicts: 1 when the factor is a function of the pose,
    ~0 when the same poses were measured at other values of it.

    Parameters
    ----------
    values : ndarray
        (n, c) the factor.
    pose : ndarray
        (n, d) pose coordinates.
    groups : ndarray
        (n,) target point of each row.
    k : int, optional
        Neighbours.

    Returns
    -------
    float
    """
    v = np.asarray(values, float)
    ss_tot = float(np.sum((v - v.mean(axis=0)) ** 2))
    if ss_tot <= 0 or len(v) < k + 2:
        return 0.0
    scale = pose.std(axis=0)
    z = pose / np.where(scale > 0, scale, 1.0)
    _, counts = np.unique(groups, return_counts=True)
    extra = int(min(counts.max(), 200))
    m = min(len(v), k + extra)
    _, idx = cKDTree(z).query(z, k=m)
    idx = idx.reshape(len(v), -1)
    other = groups[idx] != groups[:, None]
    # the first k neighbours from other points (fewer where the query returned fewer)
    rank = np.cumsum(other, axis=1)
    use = other & (rank <= k)
    n_use = np.maximum(use.sum(axis=1), 1)
    pred = np.einsum("nm,nmc->nc", use.astype(float), v[idx]) / n_use[:, None]
    ss_res = float(np.sum((v - pred) ** 2))
    return float(max(0.0, 1.0 - ss_res / ss_tot))


def linear_r2(a: np.ndarray, b: np.ndarray) -> float:
    """R^2 of a (n, c) regressed linearly on b (n, d) with an intercept.

    Parameters
    ----------
    a : ndarray
        (n, c).
    b : ndarray
        (n, d).

    Returns
    -------
    float
    """
    X = np.column_stack([np.ones(len(b)), b])
    coef, *_ = np.linalg.lstsq(X, a, rcond=None)
    ss_tot = float(np.sum((a - a.mean(axis=0)) ** 2))
    return 0.0 if ss_tot <= 0 else float(max(0.0, 1.0 - np.sum((a - X @ coef) ** 2) / ss_tot))


def check(candidates: list[str], inp: fx.Inputs, groups: np.ndarray,
          catalogue: fx.Catalogue | None = None) -> list[Finding]:
    """The confounding findings of every candidate factor (not the pose itself); a candidate with a
    finding whose `testable` is False is not tested. The names refer to `catalogue` (default
    `effects.default()`).

    A term fitted to a factor that is a function of the pose wins on held-out points of the same
    campaign and fails on the next one: in a scan every pose is measured once, in order, so time
    *is* position, and a drift term (linear in time) is a second, stiffer map of the position.

    A factor is *confounded with the pose* when the poses measured near a row (in other points, k
    nearest in joint space, else TCP) predict its value there: R^2 of that leave-the-point-out
    nearest-neighbour prediction above R2_MAX (`pose_r2`). A factor that does not vary (one speed,
    one payload) cannot be tested either. Two factors are confounded with each other (temperature
    and time) when one is a linear function of the other (R^2 above R2_MAX): their effects then
    compete for the same residual (the diagnosis tests them head to head). Each finding carries a
    code the report turns into words and the measurement that would make the effect testable.

    Parameters
    ----------
    candidates : list of str
        Effect names.
    inp : Inputs
        The data's columns.
    groups : ndarray
        (n,) target point of each row.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    list of Finding
    """
    catalogue = catalogue if catalogue is not None else fx.default()
    pose = inp.joints if inp.joints is not None else inp.commanded
    cache: dict[str, Finding] = {}
    out: list[Finding] = []
    for name in candidates:
        for factor in catalogue.get(name).drives():
            if factor not in cache:
                cache[factor] = _factor(factor, inp, pose, groups)
            f = cache[factor]
            out.append(Finding(name, f.factor, f.against, f.r2, f.testable, f.revisited, f.points))
    return out


def _factor(factor: str, inp: fx.Inputs, pose: np.ndarray, groups: np.ndarray) -> Finding:
    v = factor_values(factor, inp)
    if v is None:
        return Finding("", factor, "missing", None, False)
    if not varies(v):
        return Finding("", factor, "constant", None, False)
    if factor == "time":
        revisited, n_points = revisits(v[:, 0], groups)
        if revisited < MIN_REVISITS:
            return Finding("", factor, "scan", None, False, revisited, n_points)
    r2 = pose_r2(v, pose, groups)
    return Finding("", factor, "pose", r2, r2 <= R2_MAX)


def revisits(t: np.ndarray, groups: np.ndarray) -> tuple[int, int]:
    """How many points (groups) were measured again at least REVISIT_GAP of the campaign's time
    after they were first measured, and how many points there are. Repeated readings in one visit
    are not revisits: they say nothing of what time does at a pose.

    Parameters
    ----------
    t : ndarray
        (n,) time, s.
    groups : ndarray
        (n,) target point of each row.

    Returns
    -------
    revisited, points : int
    """
    t = np.asarray(t, float)
    span = float(np.ptp(t)) if len(t) else 0.0
    ids, inv = np.unique(groups, return_inverse=True)
    inv = inv.ravel()
    lo = np.full(len(ids), np.inf)
    hi = np.full(len(ids), -np.inf)
    np.minimum.at(lo, inv, t)
    np.maximum.at(hi, inv, t)
    return int(np.sum(hi - lo >= REVISIT_GAP * span)) if span > 0 else 0, int(len(ids))


def competing(a: str, b: str, inp: fx.Inputs, catalogue: fx.Catalogue | None = None) -> str | None:
    """The factor two candidates share, or the pair of factors that follow each other (temperature
    and time, R^2 above R2_MAX): they explain the same residual and are tested head to head. The
    names refer to `catalogue` (default `effects.default()`).

    Parameters
    ----------
    a, b : str
        Effect names.
    inp : Inputs
        The data's columns.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    str or None
    """
    catalogue = catalogue if catalogue is not None else fx.default()
    fa, fb = set(catalogue.get(a).drives()), set(catalogue.get(b).drives())
    shared = sorted(fa & fb)
    if shared:
        return shared[0]
    pair = {"temperature", "time"}
    if pair <= (fa | fb) and not pair <= fa and not pair <= fb:
        T, t = factor_values("temperature", inp), factor_values("time", inp)
        if T is not None and t is not None and varies(T) and varies(t) and linear_r2(T, t) > R2_MAX:
            return "temperature and time"
    return None
