"""What the held-out residual follows beyond the catalogue: every numeric column of the data
tested against it (the check that names a factor nobody declared an effect for)."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

from dt_runtime.measurements.dataset import Dataset
from dt_runtime.models import effects as fx

ALPHA = 0.01


def factor_columns(ds: Dataset) -> dict[str, np.ndarray]:
    """Every numeric column of the data a residual could follow: the contract's (speed,
    temperature, payload, t, q1..qk) and the file's own (`Dataset.extra`), by name (speed m/s).

    Parameters
    ----------
    ds : Dataset
        The data.

    Returns
    -------
    dict of str to ndarray
    """
    cols: dict[str, np.ndarray] = {}
    for name in ("speed", "temperature", "payload", "t"):
        v = getattr(ds, name)
        if v is not None:
            cols[name] = np.asarray(v, dtype=float)
    if ds.joints is not None:
        cols.update({f"q{j + 1}": ds.joints[:, j] for j in range(ds.joints.shape[1])})
    cols.update(ds.extra)
    return cols


def column_check(residual: np.ndarray, groups: np.ndarray, columns: dict[str, np.ndarray],
                 alpha: float = ALPHA, catalogue: fx.Catalogue | None = None,
                 pose: np.ndarray | None = None) -> list[dict]:
    """Does the held-out residual follow a column? For each column: the per-point means of the
    residual (3 axes) regressed on the per-point mean of the column (a slope per axis; points,
    not rows, are the independent units), the fraction of the residual's variance it explains
    and the F-test p-value; significant below alpha / number of columns (Bonferroni). Best first.
    `catalogue`: the call's effects (default `effects.default()`), whose own effects reading a
    column are named in its `read_by`.

    Parameters
    ----------
    residual : ndarray
        (n, 3) held-out residual, m.
    groups : ndarray
        (n,) target point of each row.
    columns : dict of str to ndarray
        The columns (`factor_columns`).
    alpha : float, optional
        Family-wise significance level.
    catalogue : Catalogue, optional
        The call's effects.
    pose : ndarray, optional
        Pose coordinates per row.

    Returns
    -------
    list of dict
    """
    catalogue = catalogue if catalogue is not None else fx.default()
    ok = np.all(np.isfinite(residual), axis=1)
    out: list[dict] = []
    ids = np.unique(groups[ok])
    if len(ids) < 6:
        return out
    inv = np.searchsorted(ids, groups[ok])
    cnt = np.bincount(inv, minlength=len(ids)).astype(float)
    R = np.stack([np.bincount(inv, weights=residual[ok, a], minlength=len(ids)) for a in range(3)], 1) / cnt[:, None]
    R0 = R - R.mean(0)
    rss0 = float(np.sum(R0 ** 2))
    m = max(len(columns), 1)
    for name, col in columns.items():
        x = np.asarray(col, dtype=float)[ok]
        if not np.all(np.isfinite(x)):
            continue
        xg = np.bincount(inv, weights=x, minlength=len(ids)) / cnt
        xc = xg - xg.mean()
        sxx = float(xc @ xc)
        if sxx <= 1e-30 * max(1.0, float(np.abs(xg).max()) ** 2) or rss0 <= 0:
            continue
        slope = xc @ R0 / sxx
        rss1 = float(np.sum((R0 - np.outer(xc, slope)) ** 2))
        g = len(ids)
        dof = 3 * g - 6
        if dof <= 0:
            continue
        F = ((rss0 - rss1) / 3) / max(rss1 / dof, 1e-300)
        pval = float(stats.f.sf(F, 3, dof))
        out.append({"column": name, "explained_fraction": 1 - rss1 / rss0, "p_value": pval,
                    "significant": pval < alpha / m,
                    # the user's own effects that read it (they were candidates: their form did not fit)
                    "read_by": sorted(n for n, e in catalogue.user_effects().items() if name in e.columns)})
    out.sort(key=lambda r: (not r["significant"], -float(r["explained_fraction"])))
    if pose is not None:
        # A significant column that is itself a function of the pose (it rose as a scan went on)
        # cannot be told from the position the residual may follow instead (analysis.confounding).
        from dt_runtime.analysis.confounding import pose_r2

        for r in out:
            if r["significant"]:
                r["pose_r2"] = pose_r2(np.asarray(columns[r["column"]], float)[:, None], pose, groups)
    return out


def read_columns(effects: Sequence[str], gp_inputs: str, n_joints: int,
                 catalogue: fx.Catalogue | None = None) -> set[str]:
    """The columns a model with these effects and GP inputs reads (joints as q1..qk); the names
    refer to `catalogue` (default `effects.default()`).

    Parameters
    ----------
    effects : sequence of str
        The model's effects.
    gp_inputs : str
        The GP's inputs.
    n_joints : int
        Number of joints.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    set of str
    """
    catalogue = catalogue if catalogue is not None else fx.default()
    cols = {c for e in effects for c in catalogue.get(e).columns}
    cols |= {"tcp_speed": {"speed"}, "joints": {"joints"}}.get(gp_inputs, set())
    if "joints" in cols:
        cols = (cols - {"joints"}) | {f"q{j + 1}" for j in range(n_joints)}
    return cols
