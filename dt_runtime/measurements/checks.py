"""Checks of measured data against physics, before anything is fitted: units and plausible ranges.

A wrong unit passes every format check (a number is a number) and then spoils the analysis
silently: joint angles in degrees hide a joint-space effect, positions in metres shrink every
error a thousandfold. `joints_vs_commanded` (with a robot config) and `plausible_ranges` catch
them and say which unit is likely wrong; `positions_in_mm` and `joints_in_radians` need no robot
config and run on every table, campaign file and program. See docs/cli.md (data checks).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import MM_PER_M
from dt_runtime.frames.kinematics import Chain

#: column -> (low, high in SI, unit as the file states it, factor from SI to that unit)
RANGES = {
    "speed": (0.0, 10.0, "mm/s", MM_PER_M),
    "payload": (0.0, 1000.0, "kg", 1.0),
    "temperature": (-50.0, 150.0, "deg C", 1.0),
}
MAX_REACH_M = 5.0
MAX_ERROR_M = 1.0  # a positioning "error" of a metre is a wrong file or unit, not an arm's error
MIN_SPAN_MM = 10.0  # a robot's positions span more than this: smaller ones are metres
# Radians: a joint angle beyond a turn and a bit (an arm's joints turn at most +-2 pi) is in degrees.
MAX_JOINT_RAD = 2 * np.pi + 0.01
DEGREES_HINT = "joint angles are in rad (|q| <= 2 pi); this looks like degrees"


def positions_in_mm(groups: dict[str, np.ndarray], where: str,
                    expected: str = "the file holds positions in mm") -> None:
    """DataError when a group of positions (SI, read from a file in mm) looks like metres: its
    largest |value| is below MIN_SPAN_MM. `groups`: the columns' names ("x, y, z") -> (n, 3) m.

    A robot's positions span more than MIN_SPAN_MM: a file whose largest |x|, |y|, |z| is
    smaller holds metres.

    Parameters
    ----------
    groups : dict of str to ndarray
        The columns' names -> (n, 3) positions, m.
    where : str
        What the error names.
    expected : str, optional
        What the message says the file should hold.

    Raises
    ------
    DataError
    """
    for name, P in groups.items():
        P = np.asarray(P, dtype=float)
        ok = P[np.all(np.isfinite(P), axis=1)]
        if len(ok) and np.max(np.abs(ok)) * MM_PER_M < MIN_SPAN_MM:
            raise DataError(f"{where}: columns {name}: largest |value| {np.max(np.abs(ok)) * MM_PER_M:.4g} mm; "
                            f"this looks like metres ({expected})")


def joints_in_radians(q: np.ndarray | None, where: str) -> None:
    """DataError naming the first joint column, row and value beyond MAX_JOINT_RAD (degrees).

    Parameters
    ----------
    q : ndarray or None
        (n, dof) joint angles, rad; None: nothing to check.
    where : str
        What the error names.

    Raises
    ------
    DataError
    """
    if q is None:
        return
    q = np.asarray(q, dtype=float)
    bad = np.argwhere(np.isfinite(q) & (np.abs(q) > MAX_JOINT_RAD))
    if bad.size:
        i, j = (int(k) for k in bad[0])
        raise DataError(f"{where}: column 'q{j + 1}', data row {i + 1}: {q[i, j]:g}: {DEGREES_HINT} "
                        f"({len(np.unique(bad[:, 0]))} rows beyond {MAX_JOINT_RAD:.4f} rad)")


@dataclass(frozen=True)
class JointCheck:
    """How well the joints' forward kinematics reproduces the commanded TCP."""

    median_mm: float
    p95_mm: float
    rows: int
    robot: str

    def to_dict(self) -> dict:
        """The check as a JSON-ready dict (mm rounded to 0.1 um)."""
        return {"median_mm": round(self.median_mm, 4), "p95_mm": round(self.p95_mm, 4), "rows": self.rows,
                "robot": self.robot}


def _mm(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x * MM_PER_M:.3f}" for x in v) + ")"


def _flange_mean(chain: Chain, q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The mean of the commanded TCP in the flange frame: R_f^T (p - p_f) averaged over the rows."""
    T = chain.frames(q)[2]
    return np.einsum("nba,nb->na", T[:, :3, :3], p - T[:, :3, 3]).mean(axis=0)


def _mismatch(chain: Chain, q: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.linalg.norm(chain.fk(q) - p, axis=1)


def _with_offset(chain: Chain, q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mismatch left when the best constant tool offset o (flange frame) and constant shift t
    (robot frame) are added to FK(q): (per-row distances, o, t), least squares."""
    T = chain.frames(q)[2]
    n = len(q)
    X = np.concatenate([T[:, :3, :3], np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    d = (p - T[:, :3, 3]).reshape(-1)
    beta = np.linalg.lstsq(X, d, rcond=1e-8)[0]
    return np.linalg.norm((d - X @ beta).reshape(n, 3), axis=1), beta[:3], beta[3:]


def joints_vs_commanded(q: np.ndarray | None, commanded: np.ndarray, chain: Chain, where: str,
                        refuse_m: float = 0.02, free_tool: bool = False) -> JointCheck | None:
    """The mismatch of FK(q) and the commanded TCP (both robot frame, SI); DataError naming the
    likely cause when its median exceeds `refuse_m`: units, a tool offset the config does not give,
    or another robot / joint order. None when there are no joint columns. `free_tool`: the chain
    ends at the flange and its tool is still to be fitted: the mismatch is measured after the best
    constant tool offset and shift (the nominal chain's check before any fit).

    The forward kinematics of the joint columns must reproduce the commanded TCP. A mismatch is
    reported (median over the rows); beyond `refuse_m` it is a DataError that names the likely
    cause, found by trying the usual mistakes: the joints in degrees, the positions in metres, a
    tool offset the config does not give (a constant offset explains it), the joints of another
    robot (count, or nothing fits).

    Parameters
    ----------
    q : ndarray or None
        (n, dof) joint angles, rad.
    commanded : ndarray
        (n, 3) commanded TCP, m.
    chain : Chain
        The robot config's chain.
    where : str
        What the error names.
    refuse_m : float, optional
        Largest median mismatch accepted, m.
    free_tool : bool, optional
        Measure the mismatch after the best constant tool offset and shift.

    Returns
    -------
    JointCheck or None
    """
    if q is None:
        return None
    q = np.asarray(q, dtype=float)
    p = np.asarray(commanded, dtype=float)
    if q.ndim != 2 or q.shape[1] == 0:
        return None
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
    if not ok.any():
        return None
    if q.shape[1] != chain.dof:
        raise DataError(f"{where}: {q.shape[1]} joint angle columns (q1..q{q.shape[1]}), the robot config "
                        f"{chain.name} has {chain.dof} joints: data of another robot? (give its config with --robot)")
    q, p = q[ok], p[ok]
    d = _with_offset(chain, q, p)[0] if free_tool else _mismatch(chain, q, p)
    check = JointCheck(float(np.median(d)) * MM_PER_M, float(np.percentile(d, 95)) * MM_PER_M, int(ok.sum()),
                       chain.name)
    if np.median(d) <= refuse_m:
        return check
    head = (f"{where}: the joint angles do not match the commanded TCP through the robot config {chain.name}"
            + (" with any tool offset" if free_tool else "") + f": they differ by {check.median_mm:.3f} mm "
            f"(median over {check.rows} rows)")
    if not free_tool:
        left = _with_offset(chain, q, p)[0]
        if np.median(left) <= refuse_m:
            raise DataError(
                f"{head}, but the forward kinematics plus one constant tool offset matches it within "
                f"{np.median(left) * MM_PER_M:.3f} mm: a tool offset the robot config does not give, or not the one "
                f"the data's TCP carries (the commanded TCP lies {_mm(_flange_mean(chain, q, p))} mm from the flange "
                "in the flange frame, on average): give tool_xyz_m in the robot config")
    # Which usual mistake explains the data? Each alternative is tried on the same rows.
    tries = {
        "the q columns look like degrees (in radians their forward kinematics matches the commanded TCP "
        "within {:.2f} mm): the table wants radians": lambda: _mismatch(chain, np.deg2rad(q), p),
        "the x, y, z columns look like metres (scaled by 1000 they match the joints' forward kinematics "
        "within {:.2f} mm): the table wants millimetres": lambda: _mismatch(chain, q, p * 1000.0),
        "the q columns look like degrees and x, y, z like metres (converted, they match within {:.2f} mm)":
            lambda: _mismatch(chain, np.deg2rad(q), p * 1000.0),
    }
    for text, f in tries.items():
        alt = float(np.median(f()))
        if alt <= refuse_m:
            raise DataError(f"{head}: " + text.format(alt * MM_PER_M))
    looks_deg = float(np.max(np.abs(q))) > 2.5 * np.pi
    raise DataError(f"{head[:-1]}, allowed {refuse_m * MM_PER_M:g} mm; no tool offset explains it): "
                    + ("the q columns exceed 2.5 pi, so they look like degrees; " if looks_deg else "")
                    + "data of another robot (give its config with --robot), or joints in another order or "
                    "zero convention")


def plausible_ranges(columns: dict[str, np.ndarray | None], commanded: np.ndarray, where: str) -> None:
    """DataError for the first implausible value: column, 1-based data row, value, allowed range.
    `columns`: SI arrays by column name (speed m/s, payload kg, temperature deg C).

    Speed > 0 and at most 10 m/s, payload in [0, 1000] kg, temperature in [-50, 150] deg C,
    commanded positions within 5 m of the base.

    Parameters
    ----------
    columns : dict of str to ndarray or None
        SI arrays by column name.
    commanded : ndarray
        (n, 3) commanded TCP, m.
    where : str
        What the error names.

    Raises
    ------
    DataError
    """
    for name, values in columns.items():
        if values is None or name not in RANGES:
            continue
        lo, hi, unit, k = RANGES[name]
        v = np.asarray(values, dtype=float)
        bad = np.flatnonzero(np.isfinite(v) & ((v < lo) | (v > hi) | ((v <= 0) if name == "speed" else False)))
        if bad.size:
            i = int(bad[0])
            low = f"> {lo * k:g}" if name == "speed" else f">= {lo * k:g}"
            raise DataError(f"{where}: column '{name}', data row {i + 1}: {v[i] * k:g} {unit} is not plausible "
                            f"(allowed {low} and <= {hi * k:g} {unit}; {bad.size} rows outside)")
    p = np.asarray(commanded, dtype=float)
    far = np.flatnonzero(np.isfinite(p).all(axis=1) & (np.abs(p) > MAX_REACH_M).any(axis=1))
    if far.size:
        i = int(far[0])
        raise DataError(f"{where}: columns x, y, z, data row {i + 1}: {np.round(p[i] * MM_PER_M, 1).tolist()} mm lies "
                        f"more than {MAX_REACH_M * MM_PER_M:g} mm from the base: positions in another unit "
                        "(micrometres?) or another frame")


def check_dataset(ds, chain: Chain | None, where: str | None = None, refuse_m: float = 0.02) -> dict:
    """The checks on a Dataset: ranges and units (positions in mm, joints in rad) always; joints
    against the commanded TCP with a robot config and joint columns (first: its message names the
    likely mistake more precisely). Returns the facts for the result's `source` block:
    {'joint_check': {...}} or {}.

    Parameters
    ----------
    ds : Dataset
        The data.
    chain : Chain or None
        The robot config's chain.
    where : str, optional
        What the error names (default the dataset's source).
    refuse_m : float, optional
        Largest median joint mismatch accepted, m.

    Returns
    -------
    dict
    """
    where = where or ds.source
    plausible_ranges({"speed": ds.speed, "payload": ds.payload, "temperature": ds.temperature}, ds.commanded, where)
    big = np.flatnonzero(np.abs(np.asarray(ds.error, dtype=float)).max(axis=1) > MAX_ERROR_M)
    if big.size:
        i = int(big[0])
        raise DataError(f"{where}: the error (ex, ey, ez or commanded - measured), data row {i + 1}: "
                        f"{np.asarray(ds.error[i]) * MM_PER_M} mm exceeds {MAX_ERROR_M * MM_PER_M:g} mm: not a "
                        f"positioning error (a wrong value, unit or frame; {big.size} rows)")
    jc = None if chain is None or ds.joints is None else joints_vs_commanded(ds.joints, ds.commanded, chain, where,
                                                                             refuse_m)
    positions_in_mm({"x, y, z": ds.commanded}, where, "the table holds positions in mm; a file in metres is read "
                    "through an import mapping with `units: {position: m}`")
    joints_in_radians(ds.joints, where)
    return {} if jc is None else {"joint_check": jc.to_dict()}
