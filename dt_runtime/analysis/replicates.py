"""The measurement noise floor from the data's own replicates (docs/cli.md, "The noise floor").

Repeated readings of one visit (`visit_groups`), else revisits under the same conditions
(`revisit_groups`); per axis the within-group variances are pooled with their degrees of freedom
(`pooled_floor`) and the floor is their 3D RMS, like the simulator's and the stated uncertainty's.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dt_kernel.units import M_PER_MM
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.models import effects as fx
from dt_runtime.models.effects.backlash import approach_signs
from dt_runtime.models.effects.base import approach

MIN_DOF = 10  # fewer degrees of freedom: the floor's own uncertainty (> 20 % of it) is too large to stop on
VISIT = "repeated readings of one visit"
REVISIT = "revisits with the same approach direction, speed, payload and temperature"
TO_MEASURE = ("repeat 10 poses, each twice in a row or revisited from the same direction at the same speed, "
              "payload and temperature")

# Revisit tolerances: what may differ between rows of one group. Each bounds the change of the
# effect that reads it well below a tracker's noise (~0.01-0.02 mm per axis):
POSE_GRID_M = 1e-5  # commanded TCP (rounded to this grid: two rows on one cell are one pose)
JOINT_GRID_RAD = 1e-5  # commanded joint angles (10 urad: 0.01 mm at 1 m reach)
SPEED_GRID_M_S = 1e-3  # commanded speed (1 mm/s)
PAYLOAD_GRID_KG = 1e-2  # carried mass (10 g)
TEMPERATURE_TOL_K = 0.5  # aluminium, 1.2 m reach: 23e-6 /K * 0.5 K * 1.2 m = 0.014 mm at the extreme
# Time between the first and the last row of a group. A drift changes between revisits whatever
# else is equal, and a structure lagging the air (thermal) too: 10 min keeps a joint-zero creep of
# 0.05 mrad/h below 0.01 mm at 1 m, and a 20-40 min thermal lag near where it was.
MAX_SPAN_S = 600.0
DIRECTION_TOL_DEG = 30.0  # the TCP's direction of travel into the pose (the dynamic lag lies along it)
OPEN_GROUPS = 20  # the recent groups of one pose a revisit may join (bounds the work on long files)


@dataclass(frozen=True)
class ReplicateFloor:
    """The noise floor from replicates: 3D RMS (m) of the pooled within-group scatter, its degrees of
    freedom, the number of groups (rows pooled together) and the definition used (`VISIT`, `REVISIT`)."""

    value_m: float
    dof: int
    cells: int
    definition: str = VISIT

    def source(self) -> str:
        """Where the floor came from, for `info['noise_floor']['source']` and the verdict."""
        return f"the scatter of replicates: {self.definition}; {self.dof} dof in {self.cells} groups"

    def to_dict(self) -> dict:
        """The floor as a JSON-ready dict (mm, dof, groups, definition)."""
        return {"mm": self.value_m / M_PER_MM, "dof": self.dof, "cells": self.cells, "groups": self.cells,
                "definition": self.definition,
                "pooled": "within-group variance per axis pooled with its degrees of freedom (rows minus "
                          "groups); 3D RMS = sqrt of their sum"}


def replicate_floor(ds: Dataset, min_dof: int = MIN_DOF) -> ReplicateFloor | None:
    """The measurement noise floor from the data's own replicates: repeated readings of one visit
    when they give `min_dof` degrees of freedom (the cleanest: only the instrument differs), else
    revisits under the same conditions (`revisit_groups`; their scatter also holds the arm's
    repeatability from one approach to the next, which no effect term can explain either). None
    when neither reaches `min_dof`.

    Parameters
    ----------
    ds : Dataset
        The data.
    min_dof : int, optional
        Least degrees of freedom.

    Returns
    -------
    ReplicateFloor or None
    """
    for definition, labels in ((VISIT, visit_groups(ds)), (REVISIT, revisit_groups(ds))):
        found = pooled_floor(ds.error, labels, min_dof)
        if found is not None:
            return ReplicateFloor(found[0], found[1], found[2], definition)
    return None


def pooled_floor(error: np.ndarray, labels: np.ndarray, min_dof: int = MIN_DOF) -> tuple[float, int, int] | None:
    """(3D RMS of the pooled within-group standard deviation (m), dof, groups) of the rows with a
    group label >= 0 in groups of two or more; None below `min_dof`. Per axis
    s^2 = sum (e - group mean)^2 / (rows - groups); the floor is sqrt(s_x^2 + s_y^2 + s_z^2).

    Parameters
    ----------
    error : ndarray
        (n, 3), m.
    labels : ndarray
        (n,) group label (-1: none).
    min_dof : int, optional
        Least degrees of freedom.

    Returns
    -------
    tuple or None
    """
    labels = np.asarray(labels, dtype=np.int64)
    mask = labels >= 0
    if not mask.any():
        return None
    _, cell = np.unique(labels[mask], return_inverse=True)
    cell = cell.ravel()
    error = np.asarray(error, float)[mask]
    counts = np.bincount(cell)
    rep = counts[cell] > 1
    n_cells = int(np.sum(counts > 1))
    dof = int(rep.sum()) - n_cells
    if dof < min_dof:
        return None
    e, c = error[rep], cell[rep]
    sums = np.stack([np.bincount(c, weights=e[:, a], minlength=len(counts)) for a in range(3)], 1)
    means = sums / np.maximum(counts, 1)[:, None]
    ss = np.sum((e - means[c]) ** 2, axis=0)
    return float(np.sqrt(np.sum(ss / dof))), dof, n_cells


def visit_groups(ds: Dataset) -> np.ndarray:
    """Per row, its visit: a run of consecutive rows of one target at the same speed, payload and
    joint angles (repeated readings; the arm has not moved, so no effect term tells them apart).

    Parameters
    ----------
    ds : Dataset
        The data, rows in time order.

    Returns
    -------
    ndarray
        (n,) labels.
    """
    from dt_runtime.analysis.crossval import groups_of

    if ds.n == 0:
        return np.zeros(0, np.int64)
    keys = [np.asarray(groups_of(ds), float)[:, None]]
    for col in (ds.speed, ds.payload, ds.joints):  # the same pose in another configuration is not a replicate
        if col is not None:
            keys.append(np.round(np.asarray(col, float), 9).reshape(ds.n, -1))
    K = np.hstack(keys)
    new_visit = np.r_[True, np.any(K[1:] != K[:-1], axis=1)]
    return np.cumsum(new_visit) - 1


def conditions(catalogue: fx.Catalogue | None = None) -> tuple[str, ...]:
    """What the effect terms of `catalogue` (default `effects.default()`) vary with beyond the pose
    (`Effect.drives`: 'direction', 'speed', 'payload', 'temperature', 'time' or a data column): the
    rows of a revisit group must agree in all of them.

    Parameters
    ----------
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    tuple of str
    """
    cat = catalogue if catalogue is not None else fx.default()
    return tuple(dict.fromkeys(c for name in cat.names() for c in cat.get(name).drives()))


def revisit_groups(ds: Dataset, drives: tuple[str, ...] | None = None) -> np.ndarray:
    """Per row, its group of revisits (-1: none): rows of one pose (point id, commanded TCP and joint
    angles on fine grids) that agree in every condition an effect term reads (`drives`, default
    `conditions()`), so that a difference between them is the measurement's (and the arm's
    repeatability), not an effect under test:

    - direction: the sign of every joint's motion into the pose (the backlash's `approach_signs`)
      and the TCP's direction of travel within DIRECTION_TOL_DEG (the dynamic lag's);
    - speed, payload, a data column a user's effect reads: the same value (on the grids above);
    - temperature within TEMPERATURE_TOL_K and time within MAX_SPAN_S, first to last row of a group.

    A condition whose column the data lack is not checked: no effect can read it. Rows in time
    order (the direction of approach is read from the previous row); the first row, whose approach
    is unknown, and rows with an empty cell in a checked column are in no group. Groups grow in
    row order: a row joins the latest of the recent groups (OPEN_GROUPS) whose every row it agrees with,
    else starts a new one.

    Parameters
    ----------
    ds : Dataset
        The data, rows in time order.
    drives : tuple of str, optional
        The conditions checked.

    Returns
    -------
    ndarray
        (n,) labels.
    """
    drives = conditions() if drives is None else drives
    n = ds.n
    keys, ok = _exact_keys(ds, drives)
    if n < 2 or not ok.any():
        return np.full(n, -1, np.int64)
    _, cls = np.unique(keys[ok], axis=0, return_inverse=True)
    label_of = np.full(n, -1, np.int64)
    label_of[ok] = cls.ravel()
    pairwise = _pairwise(ds, drives)
    out = np.full(n, -1, np.int64)
    group = -1
    for c in np.unique(label_of[ok]):
        open_groups: list[tuple[int, list[int]]] = []  # (label, rows), the latest last
        for i in map(int, np.flatnonzero(label_of == c)):
            home = next((g for g in reversed(open_groups[-OPEN_GROUPS:])
                         if all(fits(i, j) for fits in pairwise for j in g[1])), None)
            if home is None:
                group += 1
                home = (group, [])
                open_groups.append(home)
            home[1].append(i)
            out[i] = home[0]
    return out


def _exact_keys(ds: Dataset, drives: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The columns a group's rows share exactly (n, k), and which rows may join a group."""
    cols = [np.round(ds.commanded / POSE_GRID_M)]
    for ids in (ds.point_id, ds.extra.get("session")):  # another session: another set-up, registration
        if ids is not None:
            cols.append(np.asarray(ids, float)[:, None])
    if ds.joints is not None:
        cols.append(np.round(ds.joints / JOINT_GRID_RAD))
        if "direction" in drives:
            cols.append(approach_signs(ds.joints))
    grids = {"speed": SPEED_GRID_M_S, "payload": PAYLOAD_GRID_KG}
    for cond in drives:
        col = _column(ds, cond)
        if col is not None and cond not in ("direction", "temperature", "time"):
            cols.append(np.round(col / grids.get(cond, 1e-9))[:, None])
    keys = np.hstack(cols)
    ok = np.all(np.isfinite(keys), axis=1)
    for cond in ("temperature", "time"):
        col = _column(ds, cond) if cond in drives else None
        if col is not None:
            ok &= np.isfinite(col)
    ok[0] = False  # its approach is not in the data
    return keys, ok


def _column(ds: Dataset, cond: str) -> np.ndarray | None:
    """The data's column behind a condition ('time' -> t, a user's column -> `extra`), or None."""
    name = {"time": "t"}.get(cond, cond)
    col = getattr(ds, name, None) if name in ("t", "temperature", "speed", "payload") else ds.extra.get(name)
    return None if col is None else np.asarray(col, float)


def _pairwise(ds: Dataset, drives: tuple[str, ...]) -> list[Callable[[int, int], bool]]:
    """The checks two rows of one class must pass to share a group (functions of two row indices)."""
    checks = []
    for cond, tol in (("temperature", TEMPERATURE_TOL_K), ("time", MAX_SPAN_S)):
        col = _column(ds, cond) if cond in drives else None
        if col is not None:
            checks.append(_within(col, tol))
    if "direction" in drives:
        d = approach(ds.commanded)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        u = np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)
        cos_tol = np.cos(np.radians(DIRECTION_TOL_DEG))
        checks.append(lambda i, j: bool(u[i] @ u[j] >= cos_tol))
    return checks


def _within(col: np.ndarray, tol: float) -> Callable[[int, int], bool]:
    return lambda i, j: bool(abs(col[i] - col[j]) <= tol)
