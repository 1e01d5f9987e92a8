"""A calibration campaign's phase files: what `dt demo` writes from its simulated campaign and
`dt calibrate` reads.

One CSV per phase (UTF-8, comma, header row, one row per positioning, in time order); the
columns, units and plausibility checks are described in docs/campaign-files.md. `check_robot`
catches files of another robot than the robot config.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import AXES, M_PER_MM, MM_PER_M
from dt_runtime.frames.kinematics import Chain
from dt_runtime.measurements.cells import CellError, ColumnSpec, parse_rows, read_header, refuse_near_misses
from dt_runtime.measurements.checks import DEGREES_HINT, MAX_JOINT_RAD, joints_vs_commanded, positions_in_mm
from dt_runtime.measurements.phase import PhaseData

MAX_ROWS = 2_000_000

_XYZ = ("x", "y", "z")
_QCOL = re.compile(r"q(\d+)")


def _cols(prefix: str) -> list[str]:
    return [f"{prefix}{a}" for a in AXES]


def _fmt(v: float) -> str:
    return "" if not np.isfinite(v) else repr(float(v))


def write_phase(path: str | Path, data: PhaseData) -> Path:
    """Write one phase (positions in mm), atomically: a crash leaves no half-written file.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    data : PhaseData
        The phase (SI).

    Returns
    -------
    Path
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    nq = data.q.shape[1] if np.ndim(data.q) == 2 else 0
    header = (["point_id", "rep", "axis", "distance", *_cols("t"), *_XYZ, "speed", *[f"q{j + 1}" for j in range(nq)],
               "temperature", "payload", "t", *_cols("lt_"), *_cols("mvs_")]
              + (_cols("truth_lt_") if data.truth_lt is not None else []))
    axis = data.axis if data.axis is not None else np.full(data.n, None, dtype=object)
    dist = data.distance if data.distance is not None else np.full(data.n, np.nan)
    tmp = path.with_suffix(path.suffix + ".part")
    try:
        with tmp.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(header)
            for i in range(data.n):
                row = [str(data.point_id[i]), str(data.rep[i]), axis[i] if axis[i] in AXES else "",
                       _fmt(dist[i] * MM_PER_M)]
                row += [_fmt(v * MM_PER_M) for v in data.target[i]] + [_fmt(v * MM_PER_M) for v in data.p_rdk[i]]
                row += [_fmt(data.speed[i] * MM_PER_M)] + [_fmt(v) for v in (data.q[i] if nq else [])]
                row += [_fmt(data.temperature[i]), _fmt(data.payload[i]), _fmt(data.t[i])]
                row += [_fmt(v * MM_PER_M) for v in data.p_lt[i]] + [_fmt(v * MM_PER_M) for v in data.p_mvs[i]]
                if data.truth_lt is not None:
                    row += [_fmt(v * MM_PER_M) for v in data.truth_lt[i]]
                w.writerow(row)
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise DataError(f"{path}: cannot write the campaign file ({exc.strerror})") from exc
    return path


def read_phase(path: str | Path, phase: str, registration: bool = False) -> PhaseData:
    """Read one phase file (SI inside); DataError naming file, line, column and value.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    phase : str
        The phase's name.
    registration : bool, optional
        A registration phase (needs `axis` and `distance`).

    Returns
    -------
    PhaseData
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such campaign file")
    header = read_header(path, ",")
    names = ["point_id", "rep", "axis", "distance", *_cols("t"), *_XYZ, "speed", "temperature", "payload", "t",
             *(c for p in ("lt_", "mvs_", "truth_lt_") for c in _cols(p)), *(f"q{j}" for j in range(1, 8))]
    refuse_near_misses(path, [c for c in header if c not in names and not _QCOL.fullmatch(c)],
                       [c for c in names if c not in header], "docs/campaign-files.md")
    mm = M_PER_MM
    specs = [ColumnSpec(a, a, scale=mm) for a in _XYZ] + [ColumnSpec("speed", "speed", scale=mm)]
    specs += [ColumnSpec(c, c, scale=mm, required=False) for c in _cols("lt_")]
    present = set(header)
    optional_xyz = [c for p in ("t", "mvs_", "truth_lt_") for c in _cols(p) if c in present]
    specs += [ColumnSpec(c, c, scale=mm, required=False) for c in optional_xyz]
    qnums = sorted(int(m.group(1)) for c in header if (m := _QCOL.fullmatch(c)))
    if qnums != list(range(1, len(qnums) + 1)):
        raise DataError(f"{path}: line 1: joint angle columns {[f'q{j}' for j in qnums]}; expected q1 to qN "
                        "without a gap (the controller's joints in order)")
    qcols = [f"q{j}" for j in qnums]
    scalars = [c for c in ("temperature", "payload", "t") if c in present]
    specs += [ColumnSpec(c, c, required=False) for c in qcols + scalars]
    if "point_id" in present:
        specs.append(ColumnSpec("point_id", "point_id", kind="str"))
    if "rep" in present:
        specs.append(ColumnSpec("rep", "rep", kind="int"))
    if registration:
        missing = [c for c in ("axis", "distance") if c not in present]
        if missing:
            raise DataError(f"{path}: line 1: a registration file needs the column(s) {missing} (three-line "
                            f"method: the line x, y or z and the distance along it in mm); header has {header}")
        specs += [ColumnSpec("axis", "axis", kind="str"), ColumnSpec("distance", "distance", scale=mm)]

    def fail(column: str, why: str) -> None:
        err = CellError(why)
        err.column = column  # type: ignore[attr-defined]
        raise err

    def check(row: dict) -> None:
        if not row["speed"] > 0:
            fail("speed", "speed must be > 0 mm/s")
        if "payload" in row and row["payload"] < 0:
            fail("payload", "payload must be >= 0 kg")
        if registration and row["axis"] not in AXES:
            fail("axis", f"registration axis must be one of {', '.join(AXES)}")
        for q in qcols:
            if abs(row[q]) > MAX_JOINT_RAD:
                fail(q, DEGREES_HINT)

    vals, lines, _, _ = parse_rows(path, ",", ".", specs, row_check=check)
    n = len(lines)
    if n == 0:
        raise DataError(f"{path}: no rows")
    if n > MAX_ROWS:
        raise DataError(f"{path}: {n} rows, more than the {MAX_ROWS} a campaign file may hold")

    def xyz(prefix: str) -> np.ndarray:
        cols = _XYZ if prefix == "" else _cols(prefix)
        if cols[0] not in vals:
            return np.full((n, 3), np.nan)
        return np.column_stack([np.asarray(vals[c], dtype=float) for c in cols])

    def scalar(c: str) -> np.ndarray:
        return np.asarray(vals[c], dtype=float) if c in vals else np.full(n, np.nan)

    p_rdk = xyz("")
    target = xyz("t") if "tx" in vals else p_rdk.copy()
    positions_in_mm({"x, y, z": p_rdk, "tx, ty, tz": target, "lt_x, lt_y, lt_z": xyz("lt_"),
                     "mvs_x, mvs_y, mvs_z": xyz("mvs_")}, str(path), "campaign files hold positions in mm")
    return PhaseData(
        phase=phase,
        point_id=_ids(vals["point_id"]) if "point_id" in vals else np.arange(1, n + 1),
        rep=np.asarray(vals["rep"]) if "rep" in vals else np.zeros(n, dtype=int),
        target=target, speed=np.asarray(vals["speed"], dtype=float), p_rdk=p_rdk, p_lt=xyz("lt_"),
        p_mvs=xyz("mvs_"), t=scalar("t"),
        q=np.column_stack([np.asarray(vals[q], dtype=float) for q in qcols]) if qcols else np.full((n, 0), np.nan),
        temperature=scalar("temperature"), payload=scalar("payload"),
        truth_lt=xyz("truth_lt_") if "truth_lt_x" in vals else None,
        axis=np.array(vals["axis"], dtype=object) if registration else None,
        distance=np.asarray(vals["distance"], dtype=float) if registration else None)


def _ids(cells: list[str]) -> np.ndarray:
    """Point ids: integers when every id is one (as the campaign runner numbers them: grouping and
    the seeded cross-validation folds then see the same ids, in the same order, as in memory),
    else the text."""
    try:
        return np.array([int(c) for c in cells], dtype=np.int64)
    except (ValueError, OverflowError):  # OverflowError: beyond int64
        return np.array(cells)


def check_robot(data: PhaseData, chain: Chain, where: str, tol_m: float = 1e-3) -> None:
    """The joint angles' forward kinematics (robot config `chain`) must reproduce the commanded
    TCP: DataError naming the likely cause if the median distance exceeds tol_m (joints in
    degrees, positions in metres, files of another robot: `measurements.checks`).

    Parameters
    ----------
    data : PhaseData
        The phase.
    chain : Chain
        The robot config's chain.
    where : str
        What the error names.
    tol_m : float, optional
        Largest median distance accepted, m.
    """
    joints_vs_commanded(data.q, data.p_rdk, chain, where, refuse_m=tol_m)
