"""How a model is held out: the fold schemes of the diagnosis, each the form in which deployment
brings new measurements (`points`, `regions`, `forward`, `sessions`).

`deployment` picks the scheme a step of the diagnosis is judged on. See docs/cli.md ("dt diagnose").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans2

from dt_runtime.analysis.crossval import folds_of

KINDS = ("points", "regions", "forward", "sessions")
MIN_GROUPS_PER_REGION = 3  # fewer distinct points than this per region: hold out points instead


@dataclass(frozen=True)
class Scheme:
    """One way of holding data out: `kind` (KINDS), its test masks, how many folds and, for a
    forecast, each fold's training masks (else a fold trains on every row it does not test).

    - `points`: whole target points held out (analysis.crossval.folds_of): the sensitive figure the
      significance tests use (many independent groups), but a held-out point has measured neighbours.
    - `regions`: regions of the workspace held out in turn (k-means on the points' commanded TCP):
      new poses in a part of the workspace the model has not seen, as a new program brings them.
    - `forward`: a forecast: the campaign cut into k blocks in time order, later blocks predicted by
      a model fitted on the blocks before them only, the form a time-dependent term is used in (a
      drift or a warm-up continues after the campaign). Never interleaved blocks: a middle block
      would be interpolated in time.
    - `sessions`: one session (a file of the campaign, its own set-up) held out at a time: the next
      campaign or task.
    """

    kind: str
    folds: tuple[np.ndarray, ...]
    train: tuple[np.ndarray, ...] | None = None

    def splits(self) -> list:
        """The folds as cross-validation takes them: test masks, or (train, test) pairs."""
        return list(self.folds) if self.train is None else list(zip(self.train, self.folds))

    @property
    def k(self) -> int:
        """Number of folds."""
        return len(self.folds)

    def to_dict(self) -> dict:
        """The scheme as a JSON-ready dict: kind, folds and rows per fold."""
        return {"kind": self.kind, "folds": self.k, "rows_per_fold": [int(f.sum()) for f in self.folds]}


def points(groups: np.ndarray, k: int, seed: int) -> Scheme:
    """Whole target points held out, k folds (seeded).

    Parameters
    ----------
    groups : ndarray
        (n,) target point of each row.
    k : int
        Number of folds.
    seed : int
        Seed of the assignment.

    Returns
    -------
    Scheme
    """
    return Scheme("points", tuple(folds_of(groups, k, seed)))


def regions(commanded: np.ndarray, groups: np.ndarray, k: int, seed: int) -> Scheme:
    """k regions of the workspace (k-means++ on each point's mean commanded TCP, seeded); every row
    of a point in its point's region. Falls back to points when there are too few points.

    Parameters
    ----------
    commanded : ndarray
        (n, 3), m.
    groups : ndarray
        (n,) target point of each row.
    k : int
        Number of regions.
    seed : int
        Seed of k-means++.

    Returns
    -------
    Scheme
    """
    ids, inv = np.unique(groups, return_inverse=True)
    inv = inv.ravel()
    if len(ids) < MIN_GROUPS_PER_REGION * k:
        return points(groups, k, seed)
    cnt = np.bincount(inv).astype(float)
    centres = np.stack([np.bincount(inv, weights=commanded[:, a]) for a in range(3)], 1) / cnt[:, None]
    scale = centres.std(axis=0)
    z = centres / np.where(scale > 0, scale, 1.0)
    _, label = kmeans2(z, k, seed=np.random.default_rng(seed), minit="++")
    # An empty cluster (k-means++ can leave one) is dropped rather than given an empty fold.
    folds = tuple(label[inv] == c for c in range(k) if np.any(label == c))
    return Scheme("regions", folds)


def forward(t: np.ndarray | None, n: int, k: int) -> Scheme:
    """A forecast in k blocks of the rows in time order (equal row counts): block j held out and
    predicted by a model fitted on blocks 0..j-1 only, for j from k // 2 on (every model fitted on
    at least 40 % of the campaign, as a deployed one is on all of it; a term fitted on its first
    fifth alone extrapolates from a sliver of the time range); the earlier blocks are never
    predicted.

    Parameters
    ----------
    t : ndarray or None
        (n,) time (None: the row order).
    n : int
        Number of rows.
    k : int
        Number of blocks.

    Returns
    -------
    Scheme
    """
    order = np.argsort(np.asarray(t, float), kind="stable") if t is not None else np.arange(n)
    k = max(k, 2)
    edges = np.linspace(0, n, k + 1).round().astype(int)
    tests, trains = [], []
    for a, b in list(zip(edges[:-1], edges[1:]))[k // 2:]:
        te, tr = np.zeros(n, bool), np.zeros(n, bool)
        te[order[a:b]] = True
        tr[order[:a]] = True
        tests.append(te)
        trains.append(tr)
    return Scheme("forward", tuple(tests), tuple(trains))


def sessions(session: np.ndarray) -> Scheme:
    """One session held out at a time.

    Parameters
    ----------
    session : ndarray
        (n,) session index of each row.

    Returns
    -------
    Scheme
    """
    return Scheme("sessions", tuple(session == s for s in np.unique(session)))


def session_of(extra: dict | None) -> np.ndarray | None:
    """The session index of every row (`Dataset.extra['session']`), or None for one session.

    Parameters
    ----------
    extra : dict or None
        The data's own columns.

    Returns
    -------
    ndarray or None
    """
    s = None if extra is None else extra.get("session")
    if s is None:
        return None
    s = np.asarray(s).astype(int)
    return s if len(np.unique(s)) > 1 else None


def deployment(commanded: np.ndarray, groups: np.ndarray, session: np.ndarray | None, k: int, seed: int,
               t: np.ndarray | None = None, time_dependent: bool = False) -> Scheme:
    """The scheme a step is judged on: held-out sessions when there are several; else a forecast
    (`forward`) for a time-dependent term, held-out regions for any other.

    Parameters
    ----------
    commanded : ndarray
        (n, 3), m.
    groups : ndarray
        (n,) target point of each row.
    session : ndarray or None
        (n,) session index.
    k : int
        Number of folds.
    seed : int
        Seed of the assignment.
    t : ndarray, optional
        (n,) time.
    time_dependent : bool, optional
        The term under test depends on time.

    Returns
    -------
    Scheme
    """
    if session is not None:
        return sessions(session)
    if time_dependent:
        return forward(t, len(groups), k)
    return regions(commanded, groups, k, seed)
