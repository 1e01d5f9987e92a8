"""The residual of every row, per model, as a table beside the compare report (`residuals.csv`).

What the report's residual maps aggregate, for a reader that explores them (the dashboard's
metrologist's view, a spreadsheet); millimetres, as every file the project writes. The columns:
`write_residuals`.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis.points import approach

NAME = "residuals.csv"


def columns(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    """Column name -> values, in the order written.

    Parameters
    ----------
    arrays : dict
        The SI arrays `compare` returned.

    Returns
    -------
    dict of str to ndarray
        Lengths in mm, speed in mm/s.
    """
    n = len(arrays["commanded"])
    out: dict[str, np.ndarray] = {}
    for key in ("lines", "point_id", "session"):
        v = arrays.get(key)
        if v is not None:
            out["line" if key == "lines" else key] = np.asarray(v)
    P = np.asarray(arrays["commanded"], float) * MM_PER_M
    for k, ax in enumerate(AXES):
        out[ax] = P[:, k]
    if arrays.get("speed") is not None:
        out["speed"] = np.asarray(arrays["speed"], float) * MM_PER_M
    q = arrays.get("joints")
    if q is not None and len(q) > 1:
        d = approach(q)
        for j in range(d.shape[1]):
            out[f"approach_q{j + 1}"] = d[:, j].astype(int)
    for m in arrays.get("models") or []:
        r = np.asarray(m["residual"], float) * MM_PER_M
        for k, ax in enumerate(AXES):
            out[f"r_{ax}:{m['name']}"] = r[:, k]
        fail = m.get("fail")
        out[f"fails:{m['name']}"] = (np.full(n, "", dtype=object) if fail is None
                                     else np.asarray(fail).any(axis=1).astype(int))
    return out


def write_residuals(arrays: dict[str, Any], out_dir: str | Path) -> Path:
    """Write `residuals.csv` into `out_dir`: the residual of every row, per model.

    Columns: `line` (the data file's line of the row), `point_id` and `session` where the data
    have them, the commanded TCP `x, y, z` (mm, robot frame), `speed` (mm/s) where given,
    `approach_q1` ... (the direction from which each joint approached the row: -1, 0 still, +1;
    analysis.points) where the joints are given, then for each model in the order compared ('as
    is' first) `r_x:<name>`, `r_y:<name>`, `r_z:<name>` (r = e - e_hat, mm) and `fails:<name>`
    (1 when the row fails the Eq. 17 t-test in any axis, 0 when it passes, empty without a t-test).

    Parameters
    ----------
    arrays : dict
        The SI arrays `compare` returned.
    out_dir : str or Path
        The directory.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(out_dir) / NAME
    cols = columns(arrays)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(list(cols))
        for row in zip(*cols.values()):
            w.writerow([_cell(v) for v in row])
    return path


def _cell(v: Any) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    return str(v.item() if hasattr(v, "item") else v)


MAX_BYTES = 64 * 1024 * 1024  # a million rows of a dozen models is far more than a campaign


def read_residuals(path: str | Path) -> dict[str, list[str]]:
    """The table as column name -> text per row; DataError naming the file for one that is too
    big, has no header or rows of another width.

    Parameters
    ----------
    path : str or Path
        A residuals.csv.

    Returns
    -------
    dict of str to list of str
    """
    path = Path(path)
    try:
        if path.stat().st_size > MAX_BYTES:
            raise DataError(f"{path}: larger than {MAX_BYTES // 2**20} MB; not a residuals table of dt compare")
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"{path}: cannot be read ({exc})") from exc
    if not rows or not {"x", "y", "z"} <= set(rows[0]):
        raise DataError(f"{path}: no header with x, y, z: not a residuals table of dt compare")
    head = rows[0]
    bad = next((i for i, r in enumerate(rows[1:], start=2) if len(r) != len(head)), None)
    if bad is not None:
        raise DataError(f"{path}: line {bad} has {len(rows[bad - 1])} cells, the header {len(head)}")
    return {h: [r[i] for r in rows[1:]] for i, h in enumerate(head)}
