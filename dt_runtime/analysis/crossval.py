"""Grouped cross-validation, the one implementation: groups (the target point), fold assignment,
the held-out loop, and the hybrid model's held-out residuals. Every row of a group is on the
same side of a split, so a model cannot win by remembering a point.

    groups = groups_of(dataset)
    folds = folds_of(groups, 5, seed=0)
    cv = cross_validate(HybridModel(("geometric",), robot=chain), dataset, dataset.error, groups, folds)
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dt_runtime.common.threads import blas_limited
from dt_runtime.models.effects import as_inputs

if TYPE_CHECKING:  # only a type here: the twin's calibration imports this module without the hybrid model
    from dt_runtime.models.hybrid import HybridModel


@dataclass
class CvResult:
    """One cross-validation: held-out residuals, the per-group mean squares, the fold models' stated
    uncertainties and the GP hyperparameters used.
    """
    residual: np.ndarray  # (n,3) held-out residuals (NaN for rows in no fold)
    group_mse: np.ndarray  # (g,) per-group mean squared 3D residual, groups in np.unique order
    std: np.ndarray | None  # (n,3) the fold models' stated standard uncertainty (return_std)
    # The GP hyperparameters fitted on all rows, per axis in input/output units (`log_hypers_`):
    # the warm start of a model that extends this one (diagnose). None without that fit.
    log_hypers: list[np.ndarray] | None = None
    # The GP hyperparameters the folds used (fitted on all rows, or given), per axis: the same
    # configuration cross-validated on another scheme reuses them.
    thetas: list[np.ndarray] | None = None


def groups_of(ds) -> np.ndarray:
    """Cross-validation groups of a Dataset: the target point; rows of unknown point get a group
    each only if their commanded positions differ (a model must not win by remembering a point).

    Parameters
    ----------
    ds : Dataset
        The data.

    Returns
    -------
    ndarray
        (n,).
    """
    if ds.point_id is not None:
        return ds.point_id
    _, inv = np.unique(np.round(ds.commanded / 1e-6).astype(np.int64), axis=0, return_inverse=True)
    return inv.ravel()


def folds_of(groups: np.ndarray, k: int, seed: int) -> list[np.ndarray]:
    """k boolean test masks (at most one per group), each holding whole groups.

    Parameters
    ----------
    groups : ndarray
        (n,) group of each row.
    k : int
        Number of folds.
    seed : int
        Seed of the assignment.

    Returns
    -------
    list of ndarray

    Notes
    -----
    The distinct group ids, shuffled with `default_rng(seed)`; fold f = ids[f::k].
    """
    ids = np.unique(groups)
    rng = np.random.default_rng(seed)
    rng.shuffle(ids)
    k = min(k, len(ids))
    return [np.isin(groups, ids[f::k]) for f in range(k)]


def heldout(Y: np.ndarray, folds: list[np.ndarray], predict_fold: Callable, return_std: bool = False):
    """Held-out residuals Y - prediction, each test mask predicted by `predict_fold(train, test)`
    (boolean masks; it returns the prediction, or (prediction, std) with return_std). A fold is a
    test mask (trained on the other rows) or a (train, test) pair (a forecast trains on the earlier
    rows only). Rows in no fold stay NaN. Returns (residual, std or None).

    Parameters
    ----------
    Y : ndarray
        (n, k) target.
    folds : list
        Test masks or (train, test) pairs.
    predict_fold : callable
        predict_fold(train, test) -> prediction (or (prediction, std)).
    return_std : bool, optional
        Also collect the std.

    Returns
    -------
    residual : ndarray
    std : ndarray or None
    """
    resid = np.full_like(Y, np.nan, dtype=float)
    std = np.zeros_like(Y, dtype=float) if return_std else None
    for fold in folds:
        tr, te = fold if isinstance(fold, tuple) else (~fold, fold)
        out = predict_fold(tr, te)
        if std is not None:
            out, std[te] = out
        resid[te] = Y[te] - out
    return resid, std


def grouped_residuals(X: np.ndarray, Y: np.ndarray, groups: np.ndarray, folds: int, seed: int,
                      fit_predict: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """Held-out residuals r = Y - Y_hat of any regressor, each group predicted by
    `fit_predict(X_train, Y_train, X_test)` fitted without it (`folds` folds, `folds_of`).

    Parameters
    ----------
    X, Y : ndarray
        Inputs and targets.
    groups : ndarray
        (n,) group of each row.
    folds : int
        Number of folds.
    seed : int
        Seed of the assignment.
    fit_predict : callable
        fit_predict(X_train, Y_train, X_test) -> Y_hat.

    Returns
    -------
    ndarray
    """
    X, Y = np.asarray(X), np.asarray(Y, dtype=float)
    return heldout(Y, folds_of(groups, folds, seed),
                   lambda tr, te: fit_predict(X[tr], Y[tr], X[te]))[0]


def group_mse(residual: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Mean squared 3D residual per group (np.unique order), over the group's held-out rows (NaN
    for a group a forecast never predicts).

    Parameters
    ----------
    residual : ndarray
        (n, 3), m.
    groups : ndarray
        (n,) group of each row.

    Returns
    -------
    ndarray
    """
    sq = np.sum(residual ** 2, axis=1)
    out = np.full(len(np.unique(groups)), np.nan)
    for i, g in enumerate(np.unique(groups)):
        v = sq[groups == g]
        v = v[np.isfinite(v)]
        if len(v):
            out[i] = v.mean()
    return out


@blas_limited
def fit_hypers(model: HybridModel, X, y: np.ndarray, starts=None, design=None):
    """The GP hyperparameters `cross_validate` keeps fixed in its folds: `model`'s configuration
    fitted on all rows (warm-started from `starts`). Returns (thetas, log_hypers) per axis, or
    (None, None) for a model without a GP.

    Parameters
    ----------
    model : HybridModel
        The configuration.
    X : Dataset, Inputs or ndarray
        The rows.
    y : ndarray
        (n, 3) error, m.
    starts : list, optional
        Warm starts.
    design : Design, optional
        `model.design_matrix(X, y)`, when already built.

    Returns
    -------
    tuple
    """
    if model.gp_inputs == "none":
        return None, None
    inp = as_inputs(X)
    y = np.asarray(y, dtype=float)
    design = model.design_matrix(inp, y) if design is None else design
    full = model.unfitted().fit(inp, y, design=design, starts=starts)
    assert full.gp_ is not None  # gp_inputs != "none"
    return full.gp_.thetas_, full.gp_.log_hypers_


@blas_limited  # one BLAS thread for the whole loop (common.threads), the caller's setting restored
def cross_validate(model: HybridModel, X, y: np.ndarray, groups: np.ndarray, folds: list[np.ndarray], *,
                   thetas=None, return_std: bool = False, hyper_per_fold: bool = False,
                   starts=None) -> CvResult:
    """Held-out residuals of `model`'s configuration (its parameters; a fitted model's learned
    state is not used), each row predicted by a clone fitted on the other folds (rows in no fold
    stay NaN). `thetas`: GP hyperparameters to keep fixed (e.g. a saved model's); default:
    fitted once on all rows (below), or with hyper_per_fold inside every fold (strict, slower).
    return_std: also the fold models' stated standard uncertainty of each prediction (its
    variance costs more than the mean). starts: warm starts of the hyperparameter fit on all rows
    (`CvResult.log_hypers` of a nearby model; ignored when the GP inputs differ).

    Parameters
    ----------
    model : HybridModel
        The configuration.
    X : Dataset, Inputs or ndarray
        The rows.
    y : ndarray
        (n, 3) error, m.
    groups : ndarray
        (n,) target point of each row.
    folds : list
        Test masks or (train, test) pairs.
    thetas : list, optional
        Fixed GP hyperparameters.
    return_std : bool, optional
        Also the stated standard uncertainty.
    hyper_per_fold : bool, optional
        Fit the GP hyperparameters inside every fold.
    starts : list, optional
        Warm starts.

    Returns
    -------
    CvResult
    """
    inp = as_inputs(X)
    y = np.asarray(y, dtype=float)
    # Regressors that look at the previous row (approach direction) are built on the full,
    # time-ordered data and then split, so held-out rows keep their true history.
    design = model.design_matrix(inp, y)
    # GP hyperparameters are fitted once per candidate model on all rows and kept fixed in
    # the folds (the fold models refit the effect parameters and the GP posterior): a few
    # smoothness/noise numbers leak, no point's error does, and the loop runs 5x faster.
    log_hypers = None
    if thetas is None and not hyper_per_fold:
        thetas, log_hypers = fit_hypers(model, inp, y, starts, design)

    def predict_fold(tr, te):
        m = model.unfitted().fit(inp.subset(tr), y[tr], design=design.rows(tr), thetas=thetas)
        return m.predict(inp.subset(te), return_std=return_std, design=design.rows(te))

    resid, std = heldout(y, folds, predict_fold, return_std)
    return CvResult(resid, group_mse(resid, groups), std, log_hypers, thetas)
