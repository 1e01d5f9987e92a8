"""Which effect parameters can the data determine? Rank, base parameters, aliased groups.

The one module that judges it, for a fitted model (`analyse`, `Identifiability`; base
parameters by `base_of`) and for the kinematic export (`aliasing`, `Aliasing`: at the end).
See docs/effects.md ("Which parameters the data determine").
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

RCOND = 1e-6  # singular values below this fraction of the largest are directions the data do not see
LOADING = 0.01  # squared loading on unseen directions above which a parameter is not identified
ZERO_COLUMN = 1e-9  # a column whose RMS is below this fraction of the largest one is round-off
COEF_TOL = 1e-6  # a regrouping coefficient (standardised columns) below this is round-off (FIGAROH's tol_beta)
TIE = 1e-6  # pivoting weight step: a tie between aliased columns goes to the parameter listed first


@dataclass
class Base:
    """The base parameters of a design with p parameters: `lead[k]` (ascending) is the leading
    parameter of the k-th, and beta = C theta with C (r, p) in physical units (C[k, lead[k]] = 1,
    the absorbed parameters' coefficients, zeros elsewhere)."""

    lead: list[int]
    C: np.ndarray

    @property
    def rank(self) -> int:
        """Number of base parameters."""
        return len(self.lead)

    def absorbed(self, k: int) -> list[int]:
        """The parameters the k-th base parameter stands for beside its leading one.

        Parameters
        ----------
        k : int
            The base parameter.

        Returns
        -------
        list of int
        """
        return [int(j) for j in np.flatnonzero(self.C[k]) if j != self.lead[k]]

    def state(self) -> list[dict]:
        """JSON-ready rows {lead, absorbs, coefficients} (what a saved model keeps).

        Returns
        -------
        list of dict
        """
        return [{"lead": int(i), "absorbs": (js := self.absorbed(k)), "coefficients": [float(self.C[k, j]) for j in js]}
                for k, i in enumerate(self.lead)]

    @classmethod
    def from_state(cls, rows: list[dict], p: int) -> Base:
        """The base parameters `state` wrote.

        Parameters
        ----------
        rows : list of dict
            From `state`.
        p : int
            Number of parameters.

        Returns
        -------
        Base
        """
        C = np.zeros((len(rows), p))
        for k, r in enumerate(rows):
            C[k, int(r["lead"])] = 1.0
            C[k, [int(j) for j in r["absorbs"]]] = r["coefficients"]
        return cls([int(r["lead"]) for r in rows], C)


@dataclass
class Identifiability:
    """What the data determine of a design's parameters: rank, condition number, which parameters are
    identified, the aliased groups, the base parameters and the columns that have no effect.
    """
    n_params: int
    rank: int
    condition: float  # largest / smallest singular value among the seen directions
    identified: np.ndarray  # (p,) bool
    groups: list[list[int]] = field(default_factory=list)  # aliased parameters, by index
    base: Base | None = None  # None for a model saved before base parameters were kept
    no_effect: list[int] = field(default_factory=list)  # columns zero to round-off

    def state(self) -> dict:
        """JSON-ready, by index (what a saved model keeps)."""
        return {"n_params": self.n_params, "rank": self.rank,
                "condition": float(self.condition) if np.isfinite(self.condition) else None,
                "identified": [bool(v) for v in self.identified], "groups": [list(map(int, g)) for g in self.groups],
                "no_effect": list(map(int, self.no_effect)),
                **({"base": self.base.state()} if self.base is not None else {})}

    @classmethod
    def from_state(cls, d: dict) -> Identifiability:
        """The judgement `state` wrote.

        Parameters
        ----------
        d : dict
            From `state`.

        Returns
        -------
        Identifiability
        """
        cond = d.get("condition")
        p = int(d["n_params"])
        return cls(p, int(d["rank"]), float("inf") if cond is None else float(cond),
                   np.asarray(d["identified"], bool), [list(map(int, g)) for g in d["groups"]],
                   Base.from_state(d["base"], p) if "base" in d else None, [int(i) for i in d.get("no_effect", [])])

    def to_dict(self, names: list[str] | None = None) -> dict:
        """The judgement for a report: rank, condition, the parameters not identified and the groups.

        Parameters
        ----------
        names : list of str, optional
            Parameter names; indices without them.

        Returns
        -------
        dict
        """
        name = (lambda i: names[i]) if names else (lambda i: i)
        return {"n_params": self.n_params, "rank": self.rank,
                "condition": float(self.condition) if np.isfinite(self.condition) else None,
                "not_identified": [name(i) for i in np.flatnonzero(~self.identified)],
                "groups": [[name(i) for i in g] for g in self.groups]}


def zero_columns(scale: np.ndarray) -> np.ndarray:
    """Columns whose RMS is round-off next to the largest (bool mask).

    Parameters
    ----------
    scale : ndarray
        (p,) each column's RMS.

    Returns
    -------
    ndarray
        (p,) bool.
    """
    scale = np.asarray(scale, dtype=float)
    if scale.size == 0:
        return np.zeros(0, bool)
    return scale <= ZERO_COLUMN * max(float(scale.max()), np.finfo(float).tiny)


def base_of(As: np.ndarray, scale: np.ndarray | None = None, zero: np.ndarray | None = None) -> Base:
    """The base parameters of the standardised design `As`.

    Base parameters (Khalil & Dombre's, as FIGAROH computes them: tools/qrdecomposition.py,
    `QR_pivoting`) are what the data do determine, r of them for rank r: a QR decomposition with
    column pivoting of the standardised design, As P = Q R, picks the r most independent columns
    (the pivots; the rank is the number of |R_ii| above `RCOND` x |R_11|, FIGAROH's tolerance on
    the diagonal of R made relative to the standardised columns), and every other column is a
    combination of them, As_d = As_b K with K = R_11^-1 R_12 (FIGAROH's regrouping coefficients
    `beta`). So A theta = A_b beta with beta_b = theta_b + K theta_d: each base parameter is named
    by its leading (pivot) parameter and stands for that combination, here in physical units
    (coefficient of theta_j: unit of the base parameter per unit of theta_j); coefficients below
    `COEF_TOL` are round-off and dropped (FIGAROH's tol_beta). beta is the same for every theta
    that predicts the same errors on these rows, so its value is a measurement, and its
    uncertainty follows from the parameters' covariance, u(beta) = sqrt(diag(C Sigma_theta C^T)).
    Columns equal to round-off decide the pivot by round-off: aliased columns (offset_q1 and
    frame1_rz on a vertical first axis) would lead by chance, so the pivoting sees column k
    weighted by 1 - `TIE` k and a tie goes to the parameter listed first (joint offsets before
    frame errors). See docs/effects.md ("Which parameters the data determine").

    Parameters
    ----------
    As : ndarray
        (rows, p) standardised design.
    scale : ndarray, optional
        Each column's standardisation (As = A / scale; default 1), which puts the coefficients in
        physical units.
    zero : ndarray, optional
        (p,) bool: columns known to be round-off (never a pivot).

    Returns
    -------
    Base
    """
    p = As.shape[1]
    scale = np.ones(p) if scale is None else np.asarray(scale, float)
    zero = np.zeros(p, bool) if zero is None else np.asarray(zero, bool)
    if p == 0 or As.shape[0] == 0:
        return Base([], np.zeros((0, p)))
    w = 1.0 - TIE * np.arange(p)
    W = As * w  # our copy: the decomposition may overwrite it
    W[:, zero] = 0.0
    R, piv = scipy.linalg.qr(W, mode="r", pivoting=True, overwrite_a=True, check_finite=False)
    d = np.abs(np.diag(R))
    r = int(np.sum(d > RCOND * d[0])) if d.size and d[0] > 0 else 0
    lead, dep = piv[:r], piv[r:]
    K = scipy.linalg.solve_triangular(R[:r, :r], R[:r, r:p]) if r else np.zeros((0, p))
    K[np.abs(K) < COEF_TOL] = 0.0
    # W theta_w = A theta with theta_w = theta * scale / w: back to physical units.
    f = scale / w
    C = np.zeros((r, p))
    C[np.arange(r), lead] = 1.0
    C[:, dep] = K * f[dep][None, :] / f[lead][:, None]
    order = np.argsort(lead)
    return Base([int(i) for i in lead[order]], C[order])


def analyse(As: np.ndarray, zero: np.ndarray | None = None, scale: np.ndarray | None = None) -> Identifiability:
    """Identifiability of the parameters of the standardised design `As`.

    A linear effect model e = A theta is identifiable in the directions the data excite. On
    standardised columns (each regressor scaled to unit RMS, so units do not matter) the rank r
    of the design comes from `base_of`, and the singular value decomposition As = U S V^T tells
    which directions the data do not see: those beyond the r largest singular values (the
    complete geometric set is rank deficient on purpose: a base rotation and a first-joint offset
    move the arm alike). A parameter is identified when the unseen directions leave it alone (its
    squared loading on them is below `LOADING`); the others are grouped by the unseen directions
    they share (offset_q1 with frame1_rz, say). A regressor column that is zero to round-off (a
    joint offset that cannot move a TCP lying on its axis) is unseen as a whole: its parameter is
    not identified and never divides by its round-off scale. The ridge estimate puts the unseen
    directions at zero, so a value of a non-identified parameter is an artefact of the penalty:
    reports and `dt fit --json` withhold it and list its group.

    Parameters
    ----------
    As : ndarray
        (rows, p) standardised design.
    zero : ndarray, optional
        (p,) bool: columns known to be round-off (not identified, each its own group).
    scale : ndarray, optional
        As for `base_of`.

    Returns
    -------
    Identifiability
    """
    p = As.shape[1]
    zero = np.zeros(p, bool) if zero is None else np.asarray(zero, bool)
    live = np.flatnonzero(~zero)
    identified = np.zeros(p, bool)
    groups: list[list[int]] = [[int(i)] for i in np.flatnonzero(zero)]
    no_effect = [int(i) for i in np.flatnonzero(zero)]
    base = base_of(As, scale, zero)
    if live.size == 0 or base.rank == 0:
        return Identifiability(p, 0, float("inf"), identified, groups, base, no_effect)
    # The SVD of the p x p normal matrix (rows may be millions, p is tens), for the directions
    # the data do not see: as many as the QR's rank leaves, so both tell one story.
    G = As[:, live].T @ As[:, live]
    w, V = np.linalg.eigh(G)
    s = np.sqrt(np.clip(w, 0.0, None))
    seen = np.zeros(live.size, bool)
    seen[np.argsort(s)[::-1][: base.rank]] = True
    rank = base.rank
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
    return Identifiability(p, rank, cond, identified, groups, base, no_effect)


def connected(n: int, links: Iterable[tuple[int, int]]) -> list[list[int]]:
    """The groups of 0..n-1 that `links` (pairs) connect, each sorted, in order of their smallest
    member (union-find): the aliased parameters here and in the kinematic export.

    Parameters
    ----------
    n : int
        Number of items.
    links : iterable of (int, int)
        Pairs.

    Returns
    -------
    list of list of int
    """
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


ALIAS_RTOL = 1e-5  # singular values below ALIAS_RTOL x the largest: directions the data cannot see
ALIAS_TOL = 0.05  # a column kept greedily must have >= 5 % of its norm outside the kept span
ALIAS_SHOWN = 1e-3  # aliases shown: scaled coefficients above this (all are applied)


# --------------------------------------------------------------------------- aliasing (the kinematic export)
@dataclass(frozen=True)
class Aliasing:
    """Which geometric parameters the design identifies (`aliasing`): `basis` (indices into names) spans
    every identifiable combination; `absorbed[j]` maps a non-basis parameter j to the basis
    parameters its column is a combination of, {i: d theta_i / d theta_j} (physical units),
    exactly (every coefficient: `combine` uses them); `aliases[j]` the same without the
    coefficients below ALIAS_SHOWN (scaled), which the report and `groups` show;
    `no_effect`: parameters whose column is zero over the data."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    rank: int
    basis: tuple[int, ...]
    absorbed: dict[int, dict[int, float]]
    aliases: dict[int, dict[int, float]]
    no_effect: tuple[int, ...]
    singular_values: tuple[float, ...]  # relative to the largest, scaled columns
    length_m: float  # the reach that scales angles to metres at the TCP
    rtol: float = ALIAS_RTOL

    def combine(self, theta: np.ndarray) -> np.ndarray:
        """The identifiable part of `theta`: every non-basis value moved onto the basis
        parameters its column aliases, non-basis parameters zero (same A theta on the data).

        Parameters
        ----------
        theta : ndarray
            (p,).

        Returns
        -------
        ndarray
            (p,).
        """
        out = np.zeros_like(theta)
        out[list(self.basis)] = theta[list(self.basis)]
        for j, coefs in self.absorbed.items():
            for i, c in coefs.items():
                out[i] += c * theta[j]
        return out

    def groups(self) -> list[list[str]]:
        """Parameters that alias one another (connected through `aliases`), each group sorted
        in parameter order, basis parameters included; no-effect parameters excluded."""
        links = [(i, j) for j, coefs in self.aliases.items() for i in coefs]
        out = []
        for g in connected(len(self.names), links):
            kept = [k for k in g if k not in self.no_effect]
            if any(j in self.aliases for j in g) and len(kept) > 1:
                out.append([self.names[k] for k in kept])
        return out


def _preferred_order(names: tuple[str, ...]) -> list[int]:
    def key(i: int) -> tuple[int, int, int]:
        n = names[i]
        if n.startswith("offset_q"):
            return (0, int(n[8:]), 0)
        if n.startswith("frame"):
            j, kind = n[5:].split("_")
            return (1, int(j), "dr".index(kind[0]) * 3 + "xyz".index(kind[1]))
        return (2, 0, i)

    return sorted(range(len(names)), key=key)


def aliasing(A: np.ndarray, names: tuple[str, ...], units: tuple[str, ...], length_m: float,
             rtol: float = ALIAS_RTOL) -> Aliasing:
    """Which parameters of the geometric block A (n, 3, p) the design identifies, for the
    kinematic export (analysis.export), whose values must be the parameters themselves.

    Angles are scaled to metres at the TCP by `length_m` (the arm's reach); the rank is the number
    of singular values above `rtol` times the largest; then a basis of that many parameters is
    chosen, first greedily in the order joint offsets, frames 1..n (translations, rotations), tool,
    keeping a column only if at least `ALIAS_TOL` of it lies outside the span of those kept, then
    by pivoted QR for what is left. Every other parameter's column is (numerically) a combination
    of the basis columns: its coefficients are `absorbed` (all) and `aliases` (those shown). A
    parameter whose column is zero has no effect on the TCP over these data.

    Parameters
    ----------
    A : ndarray, shape (n, 3, p)
        The geometric block's regressors at the training joint angles.
    names, units : tuple of str
        The p parameters' names and units ("rad" for an angle).
    length_m : float
        The reach that scales angles to metres at the TCP.
    rtol : float
        The relative singular-value tolerance of the rank.

    Returns
    -------
    Aliasing
        The basis, what every other parameter aliases, the no-effect parameters.
    """
    p = A.shape[2]
    s = np.array([length_m if u == "rad" else 1.0 for u in units])  # theta * s: metres at the TCP
    M = A.reshape(-1, p) / s / np.sqrt(A.shape[0])
    sv = np.linalg.svd(M, compute_uv=False)
    top = float(sv[0]) if sv.size and sv[0] > 0 else 1.0
    tol = rtol * top
    rank = int(np.sum(sv > tol))
    norms = np.linalg.norm(M, axis=0)
    basis: list[int] = []
    Q = np.zeros((M.shape[0], 0))
    for i in _preferred_order(names):
        if len(basis) == rank:
            break
        r = M[:, i] - Q @ (Q.T @ M[:, i])
        if norms[i] > tol and np.linalg.norm(r) >= max(ALIAS_TOL * norms[i], tol):
            basis.append(i)
            Q = np.column_stack([Q, r / np.linalg.norm(r)])
    rest = [i for i in range(p) if i not in basis]
    if len(basis) < rank and rest:  # the rest of the rank: the most independent columns left
        R = M[:, rest] - Q @ (Q.T @ M[:, rest])
        _, _, piv = scipy.linalg.qr(R, mode="economic", pivoting=True)
        basis += [rest[k] for k in piv[: rank - len(basis)]]
    basis.sort()
    others = [i for i in range(p) if i not in basis]
    absorbed: dict[int, dict[int, float]] = {}
    aliases: dict[int, dict[int, float]] = {}
    no_effect = []
    if others:
        C = np.linalg.lstsq(M[:, basis], M[:, others], rcond=None)[0] if basis else np.zeros((0, len(others)))
        for col, j in enumerate(others):
            if norms[j] <= tol:
                no_effect.append(j)
                continue
            # physical: theta_i += C_ij s_j / s_i theta_j
            absorbed[j] = {basis[k]: float(C[k, col] * s[j] / s[basis[k]]) for k in range(len(basis))}
            big = np.abs(C[:, col]) > ALIAS_SHOWN * max(1.0, float(np.max(np.abs(C[:, col]))))
            aliases[j] = {basis[k]: absorbed[j][basis[k]] for k in np.flatnonzero(big)}
    return Aliasing(tuple(names), tuple(units), rank, tuple(basis), absorbed, aliases, tuple(no_effect),
                           tuple(float(v / top) for v in sv), float(length_m), rtol)
