"""Which effect parameters can the data determine? Rank, condition and aliased groups.

A linear effect model e = A theta is identifiable in the directions the data excite. On
standardised columns (each regressor scaled to unit RMS, so units do not matter) the singular
value decomposition As = U S V^T tells: singular values below `RCOND` x the largest are
directions the data do not see (the complete geometric set is rank deficient on purpose: a base
rotation and a first-joint offset move the arm alike). A parameter is *identified* when the
unseen directions leave it alone (its squared loading on them is below `LOADING`); the others
are grouped by the unseen directions they share (offset_q1 with frame1_rz, say), and for such a
group only the combinations along the seen directions are determined. A regressor column that
is zero to round-off (a joint offset that cannot move a TCP lying on its axis) is unseen as a
whole: its parameter is not identified and never divides by its round-off scale.

The ridge estimate puts the unseen directions at zero, so a value of a non-identified parameter
is an artefact of the penalty, not a measurement: reports and `dt fit --json` mark it
(`identified: false`, value withheld) and list its group.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

RCOND = 1e-6  # singular values below this fraction of the largest are directions the data do not see
LOADING = 0.01  # squared loading on unseen directions above which a parameter is not identified
ZERO_COLUMN = 1e-9  # a column whose RMS is below this fraction of the largest one is round-off


@dataclass
class Identifiability:
    n_params: int
    rank: int
    condition: float  # largest / smallest singular value among the seen directions
    identified: np.ndarray  # (p,) bool
    groups: list[list[int]] = field(default_factory=list)  # aliased parameters, by index

    def state(self) -> dict:
        """JSON-ready, by index (what a saved model keeps)."""
        return {"n_params": self.n_params, "rank": self.rank,
                "condition": float(self.condition) if np.isfinite(self.condition) else None,
                "identified": [bool(v) for v in self.identified], "groups": [list(map(int, g)) for g in self.groups]}

    @classmethod
    def from_state(cls, d: dict) -> Identifiability:
        cond = d.get("condition")
        return cls(int(d["n_params"]), int(d["rank"]), float("inf") if cond is None else float(cond),
                   np.asarray(d["identified"], bool), [list(map(int, g)) for g in d["groups"]])

    def to_dict(self, names: list[str] | None = None) -> dict:
        name = (lambda i: names[i]) if names else (lambda i: i)
        return {"n_params": self.n_params, "rank": self.rank,
                "condition": float(self.condition) if np.isfinite(self.condition) else None,
                "not_identified": [name(i) for i in np.flatnonzero(~self.identified)],
                "groups": [[name(i) for i in g] for g in self.groups]}


def zero_columns(scale: np.ndarray) -> np.ndarray:
    """Columns whose RMS is round-off next to the largest (bool mask)."""
    scale = np.asarray(scale, dtype=float)
    if scale.size == 0:
        return np.zeros(0, bool)
    return scale <= ZERO_COLUMN * max(float(scale.max()), np.finfo(float).tiny)


def analyse(As: np.ndarray, zero: np.ndarray | None = None) -> Identifiability:
    """Identifiability of the parameters of the standardised design `As` (rows x p); `zero`:
    columns known to be round-off (not identified, each its own group)."""
    p = As.shape[1]
    zero = np.zeros(p, bool) if zero is None else np.asarray(zero, bool)
    live = np.flatnonzero(~zero)
    identified = np.zeros(p, bool)
    groups: list[list[int]] = [[int(i)] for i in np.flatnonzero(zero)]
    if live.size == 0:
        return Identifiability(p, 0, float("inf"), identified, groups)
    # The SVD of the p x p normal matrix: rows may be millions, p is tens.
    G = As[:, live].T @ As[:, live]
    w, V = np.linalg.eigh(G)
    s = np.sqrt(np.clip(w, 0.0, None))
    seen = s > RCOND * s.max()
    rank = int(seen.sum())
    cond = float(s[seen].max() / s[seen].min()) if rank else float("inf")
    Vn = V[:, ~seen]  # unseen directions, in the live parameters
    load = np.sum(Vn ** 2, axis=1)
    identified[live] = load < LOADING
    # Group the non-identified live parameters that share unseen directions.
    bad = np.flatnonzero(load >= LOADING)
    if bad.size:
        couple = np.abs(Vn[bad] @ Vn[bad].T) >= LOADING
        links = [(i, j) for i in range(bad.size) for j in range(i + 1, bad.size) if couple[i, j]]
        groups.extend(sorted([int(live[bad[i]]) for i in g] for g in connected(bad.size, links)))
    return Identifiability(p, rank, cond, identified, groups)


def connected(n: int, links: Iterable[tuple[int, int]]) -> list[list[int]]:
    """The groups of 0..n-1 that `links` (pairs) connect, each sorted, in order of their smallest
    member (union-find): the aliased parameters here and in the kinematic export."""
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in links:
        parent[root(i)] = root(j)
    members: dict[int, list[int]] = {}
    for i in range(n):
        members.setdefault(root(i), []).append(i)
    return sorted(members.values())
