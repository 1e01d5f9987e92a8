"""The measurement table (docs/measurement-table.md, **contract**) in memory and on disk.

`Dataset` holds one row per measured positioning as SI numpy arrays (metres, rad, s, kg, m/s;
temperature in deg C); `read_table` / `write_table` read and write the contract CSV (mm, mm/s).
Error sign (paper Eq. 8): `error = commanded - measured`. Foreign files go through
`dt_runtime.measurements.importer`, which reuses the row parser (`cells`), so a bad cell is
reported the same way.
"""
from __future__ import annotations

import csv
import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.common.safe_json import read_json
from dt_runtime.measurements.cells import (
    ColumnSpec,
    SkippedRow,
    cell_error,
    numeric_columns,
    parse_rows,
    read_header,
    refuse_near_misses,
)

log = logging.getLogger(__name__)


XYZ = ("x", "y", "z")
ERROR_COLS = ("ex", "ey", "ez")
MEASURED_COLS = ("mx", "my", "mz")
U_COLS = ("ux", "uy", "uz")
SCALAR_COLS = ("speed", "temperature", "payload", "t")
ID_COLS = ("point_id", "rep")
_JOINT_RE = re.compile(r"^q([1-9][0-9]*)$")

# ex and mx given together must agree to this (mm): files may be written with rounded values.
CONSISTENCY_TOL_MM = 1e-3


def _vec(a, name: str, n: int | None, width: int | None = None, dtype=float) -> np.ndarray | None:
    if a is None:
        return None
    a = np.asarray(a, dtype=dtype)
    if width is None:
        ok = a.ndim == 1 and (n is None or a.shape[0] == n)
    else:
        ok = a.ndim == 2 and a.shape[1] == width and (n is None or a.shape[0] == n)
    if not ok:
        want = f"({n if n is not None else 'n'},{'' if width is None else ' ' + str(width)})"
        raise DataError(f"Dataset.{name}: expected shape {want}, got {a.shape}")
    return a


@dataclass
class Dataset:
    """Measurement rows as SI arrays; `n` rows, every array's first axis is `n`.

    commanded (n,3) m   commanded TCP in the robot frame (required)
    error     (n,3) m   commanded - measured (required; computed when only `measured` is known)
    measured  (n,3) m   measured TCP in the robot frame, if known
    speed (n,) m/s, joints (n,k) rad, temperature (n,) degC, payload (n,) kg, t (n,) s,
    point_id, rep (n,) int, u (n,3) m standard uncertainty of the measurement,
    flange_rotation (n,3,3) commanded flange orientation in the robot frame (not part of the
    contract CSV: kept in memory only, e.g. for registration or orientation-dependent models).
    Optional float columns may hold NaN where a cell was empty.
    source: where the rows came from; lines: the source file line of each row (traceability);
    skipped: rows dropped by skip_bad=True.
    """

    commanded: np.ndarray
    error: np.ndarray
    measured: np.ndarray | None = None
    speed: np.ndarray | None = None
    joints: np.ndarray | None = None
    temperature: np.ndarray | None = None
    payload: np.ndarray | None = None
    t: np.ndarray | None = None
    point_id: np.ndarray | None = None
    rep: np.ndarray | None = None
    u: np.ndarray | None = None
    flange_rotation: np.ndarray | None = None
    source: str = "<memory>"
    lines: np.ndarray | None = None
    skipped: list[SkippedRow] = field(default_factory=list)
    # Numeric columns outside the contract (a fixture's temperature, humidity, a tool id), kept so
    # that the diagnosis can test the residual against them: name -> (n,) float (NaN where empty).
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.commanded = _vec(self.commanded, "commanded", None, 3)
        n = self.commanded.shape[0]
        self.error = _vec(self.error, "error", n, 3)
        self.measured = _vec(self.measured, "measured", n, 3)
        self.u = _vec(self.u, "u", n, 3)
        for name in SCALAR_COLS:
            setattr(self, name, _vec(getattr(self, name), name, n))
        for name in ID_COLS:
            setattr(self, name, _vec(getattr(self, name), name, n, dtype=np.int64))
        self.lines = _vec(self.lines, "lines", n, dtype=np.int64)
        if self.joints is not None:
            self.joints = _vec(self.joints, "joints", n, np.asarray(self.joints).shape[-1])
        if self.flange_rotation is not None:
            R = np.asarray(self.flange_rotation, dtype=float)
            if R.shape != (n, 3, 3):
                raise DataError(f"Dataset.flange_rotation: expected shape ({n}, 3, 3), got {R.shape}")
            self.flange_rotation = R
        if not (np.all(np.isfinite(self.commanded)) and np.all(np.isfinite(self.error))):
            raise DataError(f"{self.source}: commanded positions and errors must be finite")
        self.extra = {str(k): _vec(v, f"extra column {k}", n) for k, v in (self.extra or {}).items()}

    @classmethod
    def from_measured(cls, commanded, measured, **kw) -> Dataset:
        """Rows from commanded and measured TCP (m); error = commanded - measured (Eq. 8).

        Parameters
        ----------
        commanded, measured : ndarray
            (n, 3), m.
        **kw
            Other Dataset fields.

        Returns
        -------
        Dataset
        """
        commanded, measured = np.asarray(commanded, float), np.asarray(measured, float)
        return cls(commanded=commanded, error=commanded - measured, measured=measured, **kw)

    def __len__(self) -> int:
        return int(self.commanded.shape[0])

    @property
    def n(self) -> int:
        """Number of rows."""
        return len(self)

    @property
    def actual(self) -> np.ndarray:
        """Measured TCP: given, or commanded - error."""
        return self.measured if self.measured is not None else self.commanded - self.error

    def select(self, index) -> Dataset:
        """Rows picked by a boolean mask or an index array (skipped rows are carried over).

        Parameters
        ----------
        index : array-like
            Boolean mask or row indices.

        Returns
        -------
        Dataset
        """
        idx = np.asarray(index)
        kw: dict[str, Any] = {}
        for f in ("commanded", "error", "measured", "speed", "joints", "temperature", "payload",
                  "t", "point_id", "rep", "u", "flange_rotation", "lines"):
            a = getattr(self, f)
            kw[f] = None if a is None else a[idx]
        return replace(self, **kw, skipped=list(self.skipped), extra={k: v[idx] for k, v in self.extra.items()})

    def columns(self) -> list[str]:
        """The contract columns `write_table` writes for this dataset, in order."""
        cols = list(XYZ)
        if self.speed is not None:
            cols.append("speed")
        if self.joints is not None:
            cols += [f"q{i + 1}" for i in range(self.joints.shape[1])]
        cols += [c for c in ("temperature", "payload", "t", "point_id", "rep") if getattr(self, c) is not None]
        cols += list(ERROR_COLS)
        if self.measured is not None:
            cols += list(MEASURED_COLS)
        if self.u is not None:
            cols += list(U_COLS)
        return cols


# --------------------------------------------------------------------------- contract table

def read_table(path: str | Path, skip_bad: bool = False) -> Dataset:
    """Read a contract measurement table (mm in the file, SI in the Dataset).

    Needs x, y, z and either ex, ey, ez or mx, my, mz (both: they must agree to 1 um and
    the error is taken from ex..ez). Columns outside the contract are kept in `extra` if numeric
    (ignored with a warning if not), but one that misspells a contract column the file lacks
    ('sped', 'Temperature', 'point id') is a DataError naming the contract name. `t` must not
    decrease; a row where it does is a bad row.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    skip_bad : bool, optional
        Skip bad rows (listed in `skipped`) instead of raising.

    Returns
    -------
    Dataset
    """
    path = Path(path)
    header = read_header(path, ",")
    contract = [*XYZ, *ERROR_COLS, *MEASURED_COLS, *U_COLS, *SCALAR_COLS, *ID_COLS]
    joints_given = [c for c in header if _JOINT_RE.match(c)]
    refuse_near_misses(path, [c for c in header if c not in contract and c not in joints_given],
                       [c for c in [*contract, *(f"q{i}" for i in range(1, 8))] if c not in header],
                       "docs/measurement-table.md")
    specs = [ColumnSpec(c, c, scale=M_PER_MM) for c in XYZ]
    has_e = all(c in header for c in ERROR_COLS)
    has_m = all(c in header for c in MEASURED_COLS)
    for group in (ERROR_COLS, MEASURED_COLS, U_COLS):
        present = [c for c in group if c in header]
        if present and len(present) != 3:
            raise DataError(f"{path}: line 1: column group {group} is incomplete, found only {present}")
    if not (has_e or has_m):
        raise DataError(f"{path}: line 1: needs columns ex, ey, ez or mx, my, mz; header has {header}")
    if has_e:
        specs += [ColumnSpec(c, c, scale=M_PER_MM) for c in ERROR_COLS]
    if has_m:
        specs += [ColumnSpec(c, c, scale=M_PER_MM) for c in MEASURED_COLS]
    if all(c in header for c in U_COLS):
        specs += [ColumnSpec(c, c, required=False, scale=M_PER_MM) for c in U_COLS]
    if "speed" in header:
        specs.append(ColumnSpec("speed", "speed", required=False, scale=M_PER_MM))
    for c in ("temperature", "payload"):
        if c in header:
            specs.append(ColumnSpec(c, c, required=False))
    if "t" in header:
        specs.append(ColumnSpec("t", "t"))
    for c in ID_COLS:
        if c in header:
            specs.append(ColumnSpec(c, c, kind="int"))
    joint_idx = sorted(int(m.group(1)) for c in header if (m := _JOINT_RE.match(c)))
    if joint_idx and joint_idx != list(range(1, len(joint_idx) + 1)):
        raise DataError(f"{path}: line 1: joint columns must be q1..qk without gaps, found "
                        f"{[f'q{i}' for i in joint_idx]}")
    specs += [ColumnSpec(f"q{i}", f"q{i}") for i in joint_idx]
    known = {s.column for s in specs}
    unknown = [c for c in header if c not in known]

    state = {"t_max": -math.inf}

    def check(row: dict) -> None:
        if has_e and has_m:
            for i, ax in enumerate(XYZ):
                e_m = (row[ax] - row[MEASURED_COLS[i]]) / M_PER_MM
                if abs(e_m - row[ERROR_COLS[i]] / M_PER_MM) > CONSISTENCY_TOL_MM:
                    raise cell_error(ERROR_COLS[i], f"disagrees with {ax} - {MEASURED_COLS[i]} = {e_m:.6g} mm")
        if "t" in row:
            if row["t"] < state["t_max"]:
                raise cell_error("t", f"time decreases (previous row had t = {state['t_max']:g} s)")
            state["t_max"] = row["t"]

    vals, lines, skipped, _ = parse_rows(path, ",", ".", specs, skip_bad, check)
    if not lines:
        raise DataError(f"{path}: no usable data rows" + (f" ({len(skipped)} skipped)" if skipped else ""))

    def col3(cols):
        return np.column_stack([vals[c] for c in cols]).astype(float)

    commanded = col3(XYZ)
    measured = col3(MEASURED_COLS) if has_m else None
    error = col3(ERROR_COLS) if has_e else commanded - measured
    arr = lambda k: np.asarray(vals[k], dtype=float) if k in vals else None  # noqa: E731
    return Dataset(
        commanded=commanded, error=error, measured=measured,
        speed=arr("speed"),
        joints=col3([f"q{i}" for i in joint_idx]) if joint_idx else None,
        temperature=arr("temperature"), payload=arr("payload"), t=arr("t"),
        point_id=np.asarray(vals["point_id"], dtype=np.int64) if "point_id" in vals else None,
        rep=np.asarray(vals["rep"], dtype=np.int64) if "rep" in vals else None,
        u=col3(U_COLS) if "ux" in vals else None,
        source=str(path), lines=np.asarray(lines, dtype=np.int64), skipped=skipped,
        extra=_extra_columns(path, unknown, lines),
    )


def _extra_columns(path: Path, names: list[str], lines) -> dict[str, np.ndarray]:
    """The numeric columns outside the contract, on the kept rows (NaN where a cell is empty);
    a column with any text cell is ignored with a warning naming it."""
    cols, bad = numeric_columns(path, names, lines)
    if bad:
        log.warning("%s: ignoring non-numeric column(s) outside the measurement table contract: %s", path, bad)
    return {c: np.asarray(v, dtype=float) for c, v in cols.items()}


def _fmt(v: float) -> str:
    # repr is the shortest string that reads back to the same float: exact round trips.
    return "" if not math.isfinite(v) else repr(float(v))


def write_table(dataset: Dataset, path: str | Path) -> Path:
    """Write the contract CSV (mm, mm/s). `flange_rotation`, `lines`, `skipped` are not written.

    Parameters
    ----------
    dataset : Dataset
        The data (SI).
    path : str or Path
        The CSV file.

    Returns
    -------
    Path
    """
    path = Path(path)
    ds = dataset
    if ds.t is not None and ds.n > 1 and np.any(np.diff(ds.t) < 0):
        i = int(np.argmax(np.diff(ds.t) < 0)) + 1
        raise DataError(f"{path}: cannot write: column 't' decreases at row {i} "
                        f"({ds.t[i - 1]:g} -> {ds.t[i]:g} s); the contract wants monotonic time")
    cols = ds.columns()
    blocks: list[np.ndarray] = [ds.commanded / M_PER_MM]
    if ds.speed is not None:
        blocks.append(ds.speed[:, None] / M_PER_MM)
    if ds.joints is not None:
        blocks.append(ds.joints)
    for c in ("temperature", "payload", "t"):
        if getattr(ds, c) is not None:
            blocks.append(getattr(ds, c)[:, None])
    n_float_before_ids = sum(b.shape[1] for b in blocks)
    tail: list[np.ndarray] = [ds.error / M_PER_MM]
    if ds.measured is not None:
        tail.append(ds.measured / M_PER_MM)
    if ds.u is not None:
        tail.append(ds.u / M_PER_MM)
    head = np.hstack(blocks)
    tail_a = np.hstack(tail)
    ids = [getattr(ds, c) for c in ID_COLS if getattr(ds, c) is not None]
    assert len(cols) == n_float_before_ids + len(ids) + tail_a.shape[1]
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with path.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(cols)
            for i in range(ds.n):
                w.writerow([_fmt(v) for v in head[i]] + [str(int(a[i])) for a in ids]
                           + [_fmt(v) for v in tail_a[i]])
    except OSError as exc:
        raise DataError(f"{path}: cannot write ({exc.strerror})") from exc
    return path


def concat(datasets: Iterable[Dataset]) -> Dataset:
    """Rows of several datasets one after the other (a column survives only if all have it).

    Parameters
    ----------
    datasets : iterable of Dataset
        In order.

    Returns
    -------
    Dataset
    """
    ds = list(datasets)
    if not ds:
        raise DataError("concat: no datasets")
    kw: dict[str, Any] = {}
    for f in ("commanded", "error", "measured", "speed", "joints", "temperature", "payload",
              "t", "point_id", "rep", "u", "flange_rotation", "lines"):
        parts = [getattr(d, f) for d in ds]
        kw[f] = None if any(p is None for p in parts) else np.concatenate(parts)
    return Dataset(**kw, source="+".join(d.source for d in ds),
                   skipped=[s for d in ds for s in d.skipped])


def sessions(datasets: Sequence[Dataset]) -> Dataset:
    """Several files of one campaign as one dataset, each a *session*: rows in file order, each
    session's time shifted to start 1 s after the previous one ends (so time stays monotonic),
    point ids offset so no two sessions share one (a point re-measured in another session, with
    its own tracker set-up, is another group), the session's index in the `session` column
    (`Dataset.extra`; `dt diagnose --group-by session` holds one out at a time). Columns survive
    only if every session has them. The command line names each session by its file
    (`session_paths.session_names`, in `Data.info['session_files']`).

    Parameters
    ----------
    datasets : sequence of Dataset
        One per session, in order.

    Returns
    -------
    Dataset
    """
    ds = list(datasets)
    if not ds:
        raise DataError("sessions: no datasets")
    parts, offset_t, offset_id = [], 0.0, 0
    common = set.intersection(*(set(d.extra) for d in ds))
    for i, d in enumerate(ds):
        kw: dict[str, Any] = {"extra": {k: d.extra[k] for k in common} | {"session": np.full(d.n, float(i))}}
        if d.t is not None and d.n:
            kw["t"] = d.t - d.t[0] + offset_t
            offset_t = float(kw["t"][-1]) + 1.0
        if d.point_id is not None:
            kw["point_id"] = d.point_id - d.point_id.min() + offset_id
            offset_id = int(kw["point_id"].max()) + 1
        parts.append(replace(d, **kw, skipped=list(d.skipped)))
    out = concat(parts)
    out.extra = {k: np.concatenate([p.extra[k] for p in parts]) for k in parts[0].extra}
    return out


def meta_path(data: str | Path) -> Path:
    """The sidecar of a data file, `<file>.meta.json` (`dt simulate` writes its scenario, seed,
    registration residual and noise floor there).

    Parameters
    ----------
    data : str or Path
        The data file.

    Returns
    -------
    Path
    """
    data = Path(data)
    return data.with_name(data.name + ".meta.json")


def read_meta_sidecar(data: str | Path) -> dict | None:
    """The simulation sidecar (`meta_path`) of a data file, if there is one.

    Parameters
    ----------
    data : str or Path
        The data file.

    Returns
    -------
    dict or None
        The sidecar's JSON object; None without a sidecar.

    Raises
    ------
    DataError
        When the sidecar is unreadable or not a JSON object.
    """
    p = meta_path(data)
    if not p.is_file():
        return None
    try:
        meta = read_json(p, "simulation sidecar")  # bounded: size, depth, finite numbers
    except DataError as exc:
        raise DataError(f"{p}: unreadable sidecar of {data} ({exc}); remove it or write it again") from exc
    if not isinstance(meta, dict):
        raise DataError(f"{p}: the sidecar of {data} is not a JSON object; remove it or write it again")
    return meta
