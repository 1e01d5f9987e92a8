"""Import mappings: read foreign measurement files into a `Dataset` without editing them.

A mapping (YAML, validated into the frozen `ImportMapping`) says how a foreign file is laid
out; a measurement in an instrument frame is registered to the robot (`RegistrationSpec`).
See docs/measurement-table.md ("Foreign files: import mappings").
"""
from __future__ import annotations

import calendar
import logging
import math
import time as _time_mod
from dataclasses import dataclass
from datetime import date, datetime
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from scipy.spatial.transform import Rotation

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import ConfigError, DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.common.paths import ROOT
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import Chain
from dt_runtime.frames.tool_fit import ToolFit, fit_tool
from dt_runtime.measurements.cells import (
    ColumnSpec,
    numeric_columns,
    parse_rows,
    read_header,
    sheet_hint,
    text_encoding,
)
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.measurements.joint_table import JointsSpec, KeyJoin, join_joints
from dt_runtime.measurements.registration_fit import RegistrationReport, fit_rigid_offset, read_transform
from dt_runtime.measurements.session_paths import companion
from dt_runtime.measurements.sheets import Cell, cell_text, check_sheet
from dt_runtime.metrology.stats import rms3
from dt_runtime.metrology.uncertainty import INF, coverage_factor

log = logging.getLogger(__name__)

LengthUnit = Literal["m", "mm"]
AngleUnit = Literal["rad", "deg"]
_LENGTH = {"m": 1.0, "mm": M_PER_MM}
_ANGLE = {"rad": 1.0, "deg": math.pi / 180.0}
_SPEED = {"m/s": 1.0, "mm/s": M_PER_MM}


# Quaternion orientation columns, by the order of the mapping's four columns (scalar first or last).
QUATERNIONS = ("quaternion_wxyz", "quaternion_xyzw")

class Columns(Frozen):
    """File column name for each contract field (None: the file lacks it). Without x, y, z the
    commanded TCP is the robot config's forward kinematics of the joint angles."""

    x: str | None = None
    y: str | None = None
    z: str | None = None
    joints: tuple[str, ...] = ()
    speed: str | None = None
    temperature: str | None = None
    payload: str | None = None
    point_id: str | None = None
    rep: str | None = None
    ex: str | None = None
    ey: str | None = None
    ez: str | None = None
    mx: str | None = None
    my: str | None = None
    mz: str | None = None
    ux: str | None = None
    uy: str | None = None
    uz: str | None = None
    # commanded flange orientation: three Euler angles, or four quaternion components (see
    # ImportMapping.orientation_convention)
    orientation: tuple[str, str, str] | tuple[str, str, str, str] | None = None


class Units(Frozen):
    """The unit of each field of a mapped file (positions, measurements, uncertainties, angles, speed)."""
    position: LengthUnit = "mm"      # commanded x, y, z
    measurement: LengthUnit = "mm"   # ex.. or mx..
    uncertainty: LengthUnit = "mm"   # ux..
    joints: AngleUnit = "rad"
    orientation: AngleUnit = "rad"
    speed: Literal["m/s", "mm/s"] = "mm/s"


class TimeSpec(Frozen):
    """Where `t` comes from.

    `seconds` (a numeric column), `timestamp` (a date-time text column, e.g. YYYYmmddHHMMSS,
    t = seconds from the earliest row), or `row_order` (t = row index 0, 1, 2 ...: only the order
    is known; e.g. a spreadsheet mangled the timestamps). A timestamp column that does not parse
    can fall back to row order (`fallback: row_order`), which the report's notes record.
    """
    source: Literal["seconds", "timestamp", "row_order"]
    column: str | None = None
    format: str = "%Y%m%d%H%M%S"     # strptime format for source: timestamp
    fallback: Literal["error", "row_order"] = "error"  # when a timestamp does not parse
    # time going backwards in the file: error, keep the file order, or sort rows by time
    order: Literal["error", "keep", "sort"] = "error"

    @model_validator(mode="after")
    def _column_needed(self):
        if self.source != "row_order" and not self.column:
            raise ValueError(f"time source '{self.source}' needs 'column'")
        return self


class UncertaintySpec(Frozen):
    """What the ux, uy, uz columns state. `standard` (the contract's): standard uncertainties.
    `expanded`: U = k u, with the coverage factor `k` stated (e.g. U95 with k = 2), or with the
    coverage probability `coverage` (e.g. 0.95) and the statement's effective degrees of freedom
    `dof` (k from Student's t; without dof, infinite: the normal distribution, k = 1.96 at 95 %).
    Imported as standard uncertainties u = U / k (GUM 6.2.1)."""

    kind: Literal["standard", "expanded"] = "standard"
    k: float | None = Field(None, ge=1)
    coverage: float | None = Field(None, gt=0, lt=1)
    dof: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _one_way(self):
        if self.kind == "standard":
            if any(v is not None for v in (self.k, self.coverage, self.dof)):
                raise ValueError("k, coverage and dof describe an expanded uncertainty: set kind: expanded "
                                 "(or leave them out for standard uncertainties)")
        elif (self.k is None) == (self.coverage is None):
            raise ValueError("kind: expanded needs one of k (the coverage factor, e.g. 2) or coverage (the "
                             "coverage probability, e.g. 0.95, with dof for Student's t), not both")
        elif self.dof is not None and self.coverage is None:
            raise ValueError("dof goes with coverage (k from Student's t); a stated k needs no dof")
        return self

    def factor(self) -> float:
        """The coverage factor k that divides the file's values into standard uncertainties (1 for standard)."""
        if self.kind == "standard":
            return 1.0
        if self.k is not None:
            return float(self.k)
        assert self.coverage is not None  # _one_way: expanded has k or coverage
        return float(coverage_factor(INF if self.dof is None else self.dof, self.coverage))

    def record(self) -> dict:
        """The import report's account of the conversion."""
        out: dict = {"stated": self.kind, "k": self.factor()}
        if self.kind == "expanded":
            out |= {"coverage": self.coverage, "dof": self.dof,
                    "k_from": "stated" if self.k is not None else
                    ("Student's t" if self.dof is not None else "normal distribution")}
        return out


class RegistrationSpec(Frozen):
    """How a measurement in an instrument frame (e.g. a laser tracker) is registered to the robot.

    With the commanded flange position p_f, its orientation R_f (when the mapping names
    orientation columns) and the measured point p_m, the import fits by least squares

        R p_m + t = p_f + R_f o                                   (one 3-vector equation per row)

    for the rigid transform instrument -> robot (R, t) and the probe/tool offset o in the flange
    frame (the paper's Eqs. 3-4, with the tool offset as extra unknowns). Start: Kabsch on the
    positions; then Levenberg-Marquardt (scipy least_squares). The commanded TCP is then
    p_f + R_f o, the measured TCP R p_m + t, and the error their difference (Eq. 8 sign). What is
    left is what a rigid registration cannot explain: the robot's own error plus noise. A given
    `transform` replaces the fit.
    """
    fit_offset: bool = True          # fit the probe/tool offset o on the flange (needs orientation)
    offset_init_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # start, or fixed if not fitted
    loss: Literal["linear", "soft_l1", "huber", "cauchy"] = "linear"
    f_scale_mm: float = Field(1.0, gt=0)  # residual scale of a robust loss
    # A given registration instead of a fit (the tracker's own set-up, measured separately): a
    # 4x4 matrix file per session, named by a template ({stem}, {name} of the data file) or a
    # table {data file name: matrix file}; relative to the data file, else to the mapping.
    transform: str | dict[str, str] | None = None
    transform_unit: LengthUnit = "mm"  # of the matrix's translation column
    transform_maps: Literal["instrument_to_robot", "robot_to_instrument"] = "instrument_to_robot"


class ImportMapping(Frozen):
    """An import mapping: how a foreign file is laid out (docs/measurement-table.md, "Mapping keys").

    Separator, decimal mark, which column holds each contract field, the unit of each field, the
    error sign, and whether the measurement is in an instrument frame that needs registration.
    The file is CSV text or a spreadsheet (.xlsx, .xls, .ods; `sheet:` picks the sheet): a
    spreadsheet's number cells are numbers (`decimal:` applies to its text cells only), its
    date-time cells are timestamps as they are, a number in a timestamp column reads as its digits.
    The file's numeric columns the mapping does not name are kept beside the rows (`Dataset.extra`).
    """
    format_version: Literal[1] = 1
    description: str = ""
    separator: str = Field(",", min_length=1, max_length=1)
    decimal: Literal[",", "."] = "."
    # The file's text encoding (a tracker's export is often latin-1 / cp1252); utf-8-sig reads
    # UTF-8 with or without a byte-order mark.
    encoding: str = "utf-8-sig"
    # a spreadsheet's sheet: its name, or its index (0 = the first); CSV files have none
    sheet: str | int = 0
    columns: Columns
    units: Units = Units()
    # what ux, uy, uz state: standard uncertainties, or expanded ones with their k (UncertaintySpec)
    uncertainty: UncertaintySpec = UncertaintySpec()
    # scipy Euler sequence: lowercase = extrinsic (fixed axes), uppercase = intrinsic
    orientation_convention: str = "xyz"
    error_sign: Literal["commanded_minus_measured", "measured_minus_commanded"] = "commanded_minus_measured"
    measured_frame: Literal["robot", "instrument"] = "robot"
    registration: RegistrationSpec = RegistrationSpec()
    time: Literal["none", "row_order"] | TimeSpec = "none"
    # contract field names (x, mx, ux, temperature, joints, orientation, ...) that a file may lack
    optional_columns: tuple[str, ...] = ()
    # number the distinct commanded positions (point_id, first appearance = 0) and their
    # repetitions (rep = 0, 1, ...), when the file has no such columns
    point_id_from_commanded: bool = False
    point_id_tolerance_mm: float = Field(0.001, gt=0)
    # a joint-angle table joined to the measurement file (joint_table.JointsSpec)
    joints: JointsSpec | None = None
    # robot config (path relative to the mapping, else to the working directory, else to the
    # project): its forward kinematics gives the commanded TCP when the file has no x, y, z
    robot: str | None = None

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, v: str) -> str:
        return text_encoding(v)

    @field_validator("sheet")
    @classmethod
    def _sheet(cls, v: str | int) -> str | int:
        return check_sheet(v)

    @field_validator("orientation_convention")
    @classmethod
    def _seq(cls, v: str) -> str:
        if v in QUATERNIONS:
            return v
        if len(v) != 3 or not (set(v) <= set("xyz") or set(v) <= set("XYZ")):
            raise ValueError("a scipy Euler sequence: three of x/y/z (extrinsic) or X/Y/Z (intrinsic), e.g. 'xyz'; "
                             f"or a quaternion, {' or '.join(QUATERNIONS)} (the order of the four columns)")
        return v

    @model_validator(mode="after")
    def _groups(self):
        c = self.columns
        has = {g: [getattr(c, a + g[1:]) is not None for a in "xyz"] for g in ("e", "m", "u")}
        grp = {"e": ["ex", "ey", "ez"], "m": ["mx", "my", "mz"], "u": ["ux", "uy", "uz"]}
        for g, flags in has.items():
            if any(flags) and not all(flags):
                raise ValueError(f"columns {grp[g]} must be given together")
        has_e = all(getattr(c, k) for k in grp["e"])
        has_m = all(getattr(c, k) for k in grp["m"])
        if has_e == has_m:
            raise ValueError("columns: give exactly one of ex/ey/ez (error) or mx/my/mz (measured)")
        if self.measured_frame == "instrument" and not has_m:
            raise ValueError("measured_frame 'instrument' needs measured columns mx/my/mz")
        xyz = [getattr(c, a) is not None for a in "xyz"]
        if any(xyz) and not all(xyz):
            raise ValueError("columns ['x', 'y', 'z'] must be given together (or none: commanded TCP from the joints)")
        if c.joints and self.joints is not None:
            raise ValueError("joint angles in columns.joints (this file) or in a joints: table, not both")
        if not any(xyz) and not (c.joints or self.joints is not None):
            raise ValueError("no commanded x/y/z: name the joint angles (columns.joints or a joints: table) "
                             "so the robot config's forward kinematics gives the commanded TCP")
        if self.registration.transform is not None and self.measured_frame != "instrument":
            raise ValueError("registration.transform (a given registration) needs measured_frame: instrument")
        if self.uncertainty.kind == "expanded" and not c.ux:
            raise ValueError("uncertainty: kind expanded describes the columns ux, uy, uz, which the mapping "
                             "does not name")
        return self



def flange_rotation(m: ImportMapping, o: np.ndarray, path: Path) -> np.ndarray:
    """The commanded flange orientations (n, 3, 3) of the orientation columns `o` (n, 3 or 4):
    Euler angles in the mapping's convention, or a quaternion (normalised; a row far from unit
    length is refused: a column mix-up or another unit).

    Parameters
    ----------
    m : ImportMapping
        The mapping (its orientation convention and columns).
    o : ndarray
        (n, 3) Euler angles or (n, 4) quaternions.
    path : Path
        The data file, for errors.

    Returns
    -------
    ndarray
        (n, 3, 3).
    """
    if m.orientation_convention not in QUATERNIONS:
        if o.shape[1] != 3:
            raise DataError(f"{path}: {o.shape[1]} orientation columns for the Euler sequence "
                            f"{m.orientation_convention!r}, which takes 3 (set orientation_convention to "
                            f"{' or '.join(QUATERNIONS)} for a quaternion)")
        return Rotation.from_euler(m.orientation_convention, o).as_matrix()
    if o.shape[1] != 4:
        raise DataError(f"{path}: {o.shape[1]} orientation columns for {m.orientation_convention}, which takes 4")
    xyzw = o if m.orientation_convention == "quaternion_xyzw" else o[:, [1, 2, 3, 0]]
    norm = np.linalg.norm(xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1) > 1e-3)
    if bad.size:
        raise DataError(f"{path}: the quaternion of data row {int(bad[0]) + 1} has length {norm[bad[0]]:.6g}, not 1 "
                        f"(columns {', '.join(m.columns.orientation or ())} in the order {m.orientation_convention})")
    return Rotation.from_quat(xyzw / norm[:, None]).as_matrix()

def load_mapping(path: str | Path) -> ImportMapping:
    """Validate a mapping YAML; a problem raises ConfigError(file, key, value, allowed).

    Parameters
    ----------
    path : str or Path
        The mapping YAML.

    Returns
    -------
    ImportMapping
    """
    return load_yaml(path, ImportMapping)


def mapping_robot(m: ImportMapping, mapping_path: Path | None) -> str | None:
    """The mapping's `robot:` as a robot reference (`frames.robots`: a catalogue name, or a config
    or URDF file beside the mapping, in the working directory or in the project), or None when
    the mapping names none.

    Parameters
    ----------
    m : ImportMapping
        The mapping.
    mapping_path : Path or None
        Where the mapping was read from.

    Returns
    -------
    str or None
    """
    if m.robot is None:
        return None
    bases = ([mapping_path.parent] if mapping_path is not None else []) + [Path.cwd(), ROOT]
    try:
        return robots.resolve(m.robot, bases).text
    except DataError as exc:
        raise ConfigError(mapping_path or "<mapping>", "robot", m.robot,
                          f"a catalogue arm, a robot config or a URDF file ({exc})") from exc


# --------------------------------------------------------------------------- import

def _timestamp(cell: Cell, fmt: str) -> float | None:
    """Zone-free seconds of a timestamp cell: a spreadsheet's date-time as it is, text (or a
    number's digits: 20210312101530) by the strptime format; None when it is no timestamp."""
    if isinstance(cell, date) and not isinstance(cell, datetime):
        return float(calendar.timegm(cell.timetuple()))
    if not isinstance(cell, datetime):
        if isinstance(cell, bool) or not isinstance(cell, (str, int, float)):
            return None  # a time of day or a duration alone is no point in time
        try:
            cell = datetime.strptime(cell_text(cell), fmt)
        except ValueError:
            return None
    return calendar.timegm(cell.timetuple()) + cell.microsecond * 1e-6


def _parse_timestamps(cells: list[Cell], fmt: str) -> np.ndarray | None:
    out = np.empty(len(cells))
    for i, s in enumerate(cells):
        v = _timestamp(s, fmt)
        if v is None:
            return None
        out[i] = v
    return out


def _chain(robot: Chain | str | Path | None, m: ImportMapping, mapping_path: Path | None, path: Path) -> Chain:
    """The robot whose forward kinematics gives the commanded TCP: the caller's (--robot) first,
    else the mapping's `robot:`."""
    if isinstance(robot, Chain):
        return robot
    if robot is not None:
        return robots.load(robot, [Path.cwd()])
    p = mapping_robot(m, mapping_path)
    if p is None:
        raise DataError(f"{path}: the mapping names no commanded x, y, z, so the commanded TCP is the forward "
                        "kinematics of the joint angles, which needs the robot: give --robot FILE (a robot config "
                        "or a URDF) or NAME (a catalogue arm such as ur5e), or `robot:` in the mapping")
    return robots.load(p)


def _extra_columns(path: Path, m: ImportMapping, header: list[str], used: set[str], lines: list[int],
                   notes: list[str]) -> dict[str, np.ndarray]:
    """The file's numeric columns the mapping does not name (humidity, pressure, ...), on the kept
    rows, by their names in the file; the non-numeric ones are said once (a warning and a note)."""
    names = [h for h in header if h and h not in used]
    cols, dropped = numeric_columns(path, names, lines, m.separator, m.decimal, m.encoding, m.sheet)
    if cols:
        notes.append(f"the file's own numeric column(s) kept beside the rows: {', '.join(cols)}")
    if dropped:
        log.warning("%s: non-numeric column(s) left out (not named by the mapping): %s", path, ", ".join(dropped))
        notes.append(f"non-numeric column(s) left out (not named by the mapping): {', '.join(dropped)}")
    return {k: np.asarray(v, dtype=float) for k, v in cols.items()}


@dataclass
class _Read:
    """What the file gave: parsed columns by field, their file lines, the rows skipped."""

    vals: dict
    lines: list[int]
    skipped: list
    joint_keys: list[str]

    def col3(self, keys) -> np.ndarray:
        return np.column_stack([self.vals[k] for k in keys]).astype(float)

    def arr(self, k: str) -> np.ndarray | None:
        return np.asarray(self.vals[k], float) if k in self.vals else None


@dataclass
class _Commanded:
    """The commanded TCP (n, 3) m before any probe offset, the flange orientations that carry one
    (from the file, or the nominal forward kinematics), and the chain when it came from the joints."""

    p: np.ndarray
    R_f: np.ndarray | None
    R_fk: np.ndarray | None
    chain: Chain | None


@dataclass
class _Registered:
    """The measurement in the robot frame: commanded (offset applied), measured, error, how."""

    commanded: np.ndarray
    measured: np.ndarray | None
    error: np.ndarray
    u: np.ndarray | None
    method: str
    R: np.ndarray
    t: np.ndarray
    offset: np.ndarray
    stds: tuple
    tool: ToolFit | None


def _specs(path: Path, m: ImportMapping, header: list[str]) -> list[ColumnSpec]:
    """Stage 1: the columns to read and how (unit scale, kind), each mapping field checked against
    the header (a missing optional one is left out)."""
    c, u = m.columns, m.units

    def present(field_name: str, names) -> bool:
        names = [names] if isinstance(names, str) else list(names)
        miss = [n for n in names if n not in header]
        if not miss:
            return True
        if field_name in m.optional_columns:
            return False
        raise DataError(f"{path}: line 1: mapping field '{field_name}' wants column(s) {miss}, "
                        f"not in the header {header}" + sheet_hint(path, m.encoding, m.sheet))

    specs = [ColumnSpec(a, getattr(c, a), scale=_LENGTH[u.position]) for a in "xyz"] if c.x is not None else []
    meas_keys = ("mx", "my", "mz") if c.mx else ("ex", "ey", "ez")
    specs += [ColumnSpec(k, getattr(c, k), scale=_LENGTH[u.measurement]) for k in meas_keys]
    if c.ux and present("ux", [c.ux, c.uy, c.uz]):
        specs += [ColumnSpec(k, getattr(c, k), required=False, scale=_LENGTH[u.uncertainty])
                  for k in ("ux", "uy", "uz")]
    if c.joints and present("joints", c.joints):
        specs += [ColumnSpec(f"q{i + 1}", name, scale=_ANGLE[u.joints]) for i, name in enumerate(c.joints)]
    if c.orientation and present("orientation", c.orientation):
        scale = 1.0 if m.orientation_convention in QUATERNIONS else _ANGLE[u.orientation]  # quaternions: no unit
        specs += [ColumnSpec(f"o{i}", name, scale=scale) for i, name in enumerate(c.orientation)]
    if c.speed and present("speed", c.speed):
        specs.append(ColumnSpec("speed", c.speed, required=False, scale=_SPEED[u.speed]))
    for k in ("temperature", "payload"):
        if getattr(c, k) and present(k, getattr(c, k)):
            specs.append(ColumnSpec(k, getattr(c, k), required=False))
    for k in ("point_id", "rep"):
        if getattr(c, k) and present(k, getattr(c, k)):
            specs.append(ColumnSpec(k, getattr(c, k), kind="int"))
    tspec = m.time
    if isinstance(tspec, TimeSpec) and tspec.source != "row_order":
        kind = "cell" if tspec.source == "timestamp" else "float"  # a sheet's date-time cell stays one
        assert tspec.column is not None  # TimeSpec._column_needed requires it for these sources
        specs.append(ColumnSpec("t", tspec.column, kind=kind))
    if m.joints is not None and isinstance(m.joints.join, KeyJoin):
        specs.append(ColumnSpec("join_key", m.joints.join.key, kind="str"))
    return specs


def _read(path: Path, m: ImportMapping, specs: list[ColumnSpec], skip_bad: bool, mapping_dir: Path | None,
          mfile: str, notes: list[str]) -> _Read:
    """Stage 2: the rows, and the joint-angle table joined to them (rows whose joints were skipped
    leave with them)."""
    vals, lines, skipped, _ = parse_rows(path, m.separator, m.decimal, specs, skip_bad, encoding=m.encoding,
                                         sheet=m.sheet)
    if m.joints is not None and lines:
        jj = join_joints(m.joints, path, lines, vals.get("join_key"), m.separator, m.encoding, mapping_dir,
                         skip_bad, mfile, data_sheet=m.sheet)
        if not jj.keep.all():
            vals = {k: [v for v, ok in zip(vs, jj.keep) if ok] for k, vs in vals.items()}
            lines = [ln for ln, ok in zip(lines, jj.keep) if ok]
            skipped = sorted(skipped + jj.skipped, key=lambda r: r.line)
        vals.update({f"q{i + 1}": list(jj.q[:, i]) for i in range(jj.q.shape[1])})
        how = "row order" if m.joints.join == "row" else f"key column '{m.joints.join.key}'"
        notes.append(f"joint angles joined from {jj.source} by {how}")
    if not lines:
        raise DataError(f"{path}: no usable data rows" + (f" ({len(skipped)} skipped)" if skipped else ""))
    c = m.columns
    n_joints = len(c.joints) if c.joints else (len(m.joints.columns) if m.joints is not None else 0)
    return _Read(vals, lines, skipped, [f"q{i + 1}" for i in range(n_joints)])


def _commanded(r: _Read, m: ImportMapping, robot, mapping_path: Path | None, path: Path,
               notes: list[str]) -> _Commanded:
    """Stage 3: the commanded TCP, from the file's x, y, z, else the robot's nominal forward
    kinematics of the joint angles (which also gives the flange orientation to carry a probe)."""
    R_fk, chain = None, None
    if m.columns.x is not None:
        p_cmd = r.col3("xyz")
    else:
        if "q1" not in r.vals:
            raise DataError(f"{path}: no commanded x, y, z and no joint angles to compute them from")
        chain = _chain(robot, m, mapping_path, path)
        q = r.col3(r.joint_keys)
        if q.shape[1] != chain.dof:
            raise DataError(f"{path}: {q.shape[1]} joint angle columns, the robot config {chain.name} has "
                            f"{chain.dof} joints: data of another robot? (give its config with --robot)")
        T = chain.frames(q)[2]
        # the nominal pose the controller commanded: position for the error, orientation to
        # carry a probe offset (registration.fit_offset) like a file's orientation columns
        p_cmd, R_fk = T[:, :3, 3].copy(), T[:, :3, :3].copy()
        notes.append(f"commanded TCP = nominal forward kinematics of the joint angles (robot config {chain.name})")
    c = m.columns
    R_f = flange_rotation(m, np.column_stack([r.vals[f"o{i}"] for i in range(len(c.orientation or ()))]), path) \
        if "o0" in r.vals else R_fk
    return _Commanded(p_cmd, R_f, R_fk, chain)


def _register(r: _Read, m: ImportMapping, cmd: _Commanded, path: Path, mapping_dir: Path | None, mfile: str,
              notes: list[str]) -> _Registered:
    """Stage 4: the measurement in the robot frame and the error e = commanded - measured (Eq. 8):
    the registration given (a 4x4 file) or fitted (rigid, with the probe offset on the flange), or
    none for data in the robot frame (a robot without a tool gets its offset fitted)."""
    n = len(r.lines)
    u_meas = r.col3(["ux", "uy", "uz"]) if "ux" in r.vals else None
    reg = m.registration
    o_init = np.asarray(reg.offset_init_mm, float) * M_PER_MM
    R_f = cmd.R_f
    if np.any(o_init) and R_f is None:
        raise DataError(f"{path}: registration.offset_init_mm is not zero but the mapping has no "
                        "orientation columns to carry the offset on the flange")
    method, R, t_vec, offset = "none", np.eye(3), np.zeros(3), (o_init if R_f is not None else np.zeros(3))
    stds: tuple = (None, None, None)
    tool: ToolFit | None = None
    if "mx" not in r.vals:
        commanded = cmd.p + (R_f @ offset if R_f is not None else 0.0)
        error = r.col3(["ex", "ey", "ez"])
        if m.error_sign == "measured_minus_commanded":
            error = -error
        return _Registered(commanded, None, error, u_meas, method, R, t_vec, offset, stds, tool)
    p_meas = r.col3(["mx", "my", "mz"])
    if (cmd.chain is not None and not cmd.chain.tool_given and cmd.R_fk is not None and m.measured_frame == "robot"
            and not np.any(o_init)):
        # the robot gives no tool offset: the TCP the tracker measured, on the flange (frames.tool_fit)
        tool = fit_tool(cmd.chain, r.col3(r.joint_keys), p_meas, "measured")
        offset, stds = tool.offset, (None, None, tool.u / M_PER_MM)
        notes.append(tool.line())
    if m.measured_frame == "instrument" and reg.transform is not None:
        # the session's registration as measured by the user: applied, not fitted
        tpath = companion(reg.transform, path, mapping_dir, "registration.transform", mfile)
        R, t_vec = read_transform(tpath, reg.transform_unit, reg.transform_maps)
        method = "given"
        notes.append(f"registration given by {tpath} ({reg.transform_maps}), not fitted")
    elif m.measured_frame == "instrument":
        if n < 3:
            raise DataError(f"{path}: registration needs at least 3 rows, got {n}")
        fit = fit_rigid_offset(p_meas, cmd.p, R_f, o_init, reg.fit_offset, reg.loss, reg.f_scale_mm * M_PER_MM)
        fitted_offset = fit.offset_dof > 0
        if reg.fit_offset and R_f is not None and fit.offset_dof < 3:
            notes.append(f"flange orientations vary in {fit.offset_dof} of 3 directions: only "
                         f"{fit.offset_dof} probe-offset component(s) fitted, the rest kept at offset_init_mm")
        if reg.fit_offset and R_f is None:
            notes.append("no orientation columns: probe offset not fitted (rigid registration only)")
        method = "rigid+offset" if fitted_offset else "rigid"
        R, t_vec, offset = fit.rotation, fit.translation, fit.offset
        stds = (fit.rotation_std, fit.translation_std / M_PER_MM,
                fit.offset_std / M_PER_MM if fitted_offset else None)
    if method != "none":
        p_meas = p_meas @ R.T + t_vec
        if u_meas is not None:
            # diagonal instrument-frame covariance rotated into the robot frame, per-axis std
            u_meas = np.sqrt((u_meas ** 2) @ (R ** 2).T)
    commanded = cmd.p + (R_f @ offset if R_f is not None else 0.0)
    if m.error_sign == "measured_minus_commanded":
        notes.append("error_sign ignored for measured columns: error is computed as commanded - measured")
    return _Registered(commanded, p_meas, commanded - p_meas, u_meas, method, R, t_vec, offset, stds, tool)


def _time(r: _Read, m: ImportMapping, path: Path, notes: list[str]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Stage 5: the time of each row (seconds, a timestamp, or the row order) and, when the file's
    time goes backwards and the mapping says so, the order that sorts it."""
    tspec, lines, n = m.time, r.lines, len(r.lines)
    if tspec == "row_order" or (isinstance(tspec, TimeSpec) and tspec.source == "row_order"):
        notes.append("t is the row index (time unknown, row order only)")
        return np.arange(n, dtype=float), None
    if not isinstance(tspec, TimeSpec):
        return None, None
    vals = r.vals
    if tspec.source == "seconds":
        t = np.asarray(vals["t"], float)
    else:
        parsed = _parse_timestamps(vals["t"], tspec.format)
        if parsed is None:
            bad = next(i for i, s in enumerate(vals["t"]) if _parse_timestamps([s], tspec.format) is None)
            if tspec.fallback == "error":
                raise DataError(f"{path}: line {lines[bad]}: column '{tspec.column}': value "
                                f"{cell_text(vals['t'][bad])!r}: not a timestamp of format {tspec.format!r}")
            parsed = np.arange(n, dtype=float)
            notes.append(f"column '{tspec.column}' does not parse as {tspec.format!r} (line {lines[bad]}: "
                         f"{cell_text(vals['t'][bad])!r}): t is the row index (row order only)")
        t = parsed
    order = None
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        where = f"{back.size} place(s), first at line {lines[back[0] + 1]}"
        if tspec.order == "error":
            raise DataError(f"{path}: line {lines[back[0] + 1]}: column '{tspec.column}': time goes "
                            f"backwards ({where}); set time.order to 'sort' or 'keep'")
        if tspec.order == "sort":
            order = np.argsort(t, kind="stable")
            notes.append(f"time goes backwards in the file ({where}): rows sorted by time")
        else:
            notes.append(f"time goes backwards in the file ({where}): file order kept")
    return t - t.min(), order


def _points(r: _Read, m: ImportMapping, p_cmd: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Stage 6: target point ids and repetitions, from the file or numbered from the commanded
    position (by first appearance, within the mapping's tolerance)."""
    point_id = np.asarray(r.vals["point_id"], np.int64) if "point_id" in r.vals else None
    rep = np.asarray(r.vals["rep"], np.int64) if "rep" in r.vals else None
    if m.point_id_from_commanded and point_id is None:
        key = np.round(p_cmd / (m.point_id_tolerance_mm * M_PER_MM)).astype(np.int64)
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inv = inv.ravel()
        rank = np.empty_like(first)
        rank[np.argsort(first)] = np.arange(first.size)  # number points by first appearance
        point_id = rank[inv]
        rep = np.zeros(len(point_id), np.int64)
        seen: dict[int, int] = {}
        for i, p in enumerate(point_id):
            rep[i] = seen.get(int(p), 0)
            seen[int(p)] = rep[i] + 1
    return point_id, rep


def _stated_uncertainty(u: np.ndarray | None, m: ImportMapping, notes: list[str]) -> tuple[np.ndarray | None,
                                                                                         dict | None]:
    """Stage 7: the stated uncertainties as standard ones (expanded ones divided by their k)."""
    if u is None:
        return None, None
    c = m.columns
    stated = m.uncertainty.record() | {"columns": [c.ux, c.uy, c.uz]}
    if m.uncertainty.kind == "expanded":
        u = u / m.uncertainty.factor()  # u = U / k (GUM 6.2.1); linear, so after the rotation too
        notes.append(f"ux, uy, uz ({', '.join(stated['columns'])}) are expanded uncertainties: divided by "
                     f"k = {stated['k']:.4g} ({stated['k_from']}) into standard uncertainties")
    return u, stated


def import_file(path: str | Path, mapping: ImportMapping | str | Path,
                skip_bad: bool = False, robot: Chain | str | Path | None = None) -> tuple[Dataset, RegistrationReport]:
    """Read a foreign file through `mapping` (a model or a YAML path) into an SI Dataset.

    Returns the dataset (commanded TCP, error = commanded - measured, measured in the robot
    frame, flange orientation when given) and a RegistrationReport (residual RMS, fitted or
    given transform and offset, notes, import time). Bad rows: DataError with file, line, column
    and value, or skipped and listed in `dataset.skipped` with skip_bad=True. `robot` (a Chain
    or a config path; default the mapping's `robot:`) is needed only when the file has no
    commanded x, y, z: the commanded TCP is then the forward kinematics of the joint angles.
    The stages: the columns to read, the rows (and the joint table), the commanded TCP, the
    registration and error, the time, the points, the stated uncertainty.

    Parameters
    ----------
    path : str or Path
        The foreign file.
    mapping : ImportMapping, str or Path
        The mapping or its YAML.
    skip_bad : bool, optional
        Skip bad rows instead of raising.
    robot : Chain, str or Path, optional
        The robot, for a file without commanded x, y, z.

    Returns
    -------
    dataset : Dataset
    report : RegistrationReport
    """
    started = _time_mod.perf_counter()
    path = Path(path)
    mapping_path = None if isinstance(mapping, ImportMapping) else Path(mapping)
    m = mapping if isinstance(mapping, ImportMapping) else load_mapping(mapping)
    mapping_dir = None if mapping_path is None else mapping_path.parent
    mfile = "<mapping>" if mapping_path is None else str(mapping_path)
    header = read_header(path, m.separator, m.encoding, m.sheet)
    notes: list[str] = []
    specs = _specs(path, m, header)
    r = _read(path, m, specs, skip_bad, mapping_dir, mfile, notes)
    cmd = _commanded(r, m, robot, mapping_path, path, notes)
    reg = _register(r, m, cmd, path, mapping_dir, mfile, notes)
    t, order = _time(r, m, path, notes)
    point_id, rep = _points(r, m, cmd.p)
    u, u_stated = _stated_uncertainty(reg.u, m, notes)
    extra = _extra_columns(path, m, header, {s.column for s in specs}, r.lines, notes)
    n = len(r.lines)
    ds = Dataset(commanded=reg.commanded, error=reg.error, measured=reg.measured, speed=r.arr("speed"),
                 joints=r.col3(r.joint_keys) if "q1" in r.vals else None,
                 temperature=r.arr("temperature"), payload=r.arr("payload"), t=t,
                 point_id=point_id, rep=rep, u=u, flange_rotation=cmd.R_f,
                 source=str(path), lines=np.asarray(r.lines, dtype=np.int64), skipped=r.skipped, extra=extra)
    if order is not None:
        ds = ds.select(order)
    res_mm = ds.error / M_PER_MM
    report = RegistrationReport(
        method=reg.method, n=n, rms_axis_mm=np.sqrt(np.mean(res_mm ** 2, axis=0)),
        rms_3d_mm=rms3(res_mm),
        rotation=reg.R, translation=reg.t, offset=np.asarray(reg.offset, float),
        rotation_std_rad=reg.stds[0], translation_std_mm=reg.stds[1], offset_std_mm=reg.stds[2],
        n_skipped=len(r.skipped), notes=notes, uncertainty=u_stated)
    if cmd.chain is not None and not cmd.chain.tool_given and cmd.R_fk is not None \
            and reg.method in ("none", "rigid+offset") and "mx" in r.vals \
            and (reg.tool is not None or reg.method == "rigid+offset"):
        # the offset stands for the robot's missing tool: the analysis appends it to the chain
        report.tool_offset = (reg.tool.to_dict() if reg.tool is not None else
                              {"xyz_mm": [float(v) / M_PER_MM for v in reg.offset],
                               "u_mm": [float(v) for v in np.ravel(reg.stds[2])], "residual_rms_mm": rms3(res_mm),
                               "n": n, "from": "measured (fitted with the registration)", "frame": "flange"})
    report.seconds = _time_mod.perf_counter() - started
    return ds, report
