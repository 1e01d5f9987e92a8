"""A joint-angle table joined to a measurement file (the import mapping's `joints:` section).

A tracker exports points; the robot's joint angles come from the controller, often as a
spreadsheet-exported CSV. The two are paired by row order or by a key column (`join_joints`).
See docs/campaigns.md ("`joints:`, a joint-angle table joined to the measurement file").
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from dt_kernel.config import Frozen
from dt_kernel.errors import DataError
from dt_runtime.measurements.cells import ColumnSpec, SkippedRow, data_row_lines, parse_rows, text_encoding
from dt_runtime.measurements.session_paths import companion
from dt_runtime.measurements.sheets import check_sheet

_ANGLE = {"rad": 1.0, "deg": math.pi / 180.0}


class KeyJoin(Frozen):
    """Join a joint table to the measurement file by a key column (instead of by row order)."""
    key: str                       # the key column of the measurement file
    joints_key: str | None = None  # its name in the joint table (default: the same)


class JointsSpec(Frozen):
    """The `joints:` section of an import mapping.

    The two files are paired either by row order (`join: row`: row i of one is row i of the other,
    so both must have the same number of data rows) or by a key column present in both
    (`join: {key: Punkt}`): a point measured twice takes the same joint row, but a key the joint
    table lists twice is ambiguous and a key it lacks has no joints, both refused with the keys
    named. The table is CSV (`separator`, `decimal`, `encoding`) or a spreadsheet as the
    controller's software saved it (.xlsx, .xls, .ods; `sheet` picks the sheet).
    """

    # file name (placeholders {stem}, {name} of the data file) or {data file name: joint table}
    path: str | dict[str, str]
    separator: str = Field(",", min_length=1, max_length=1)
    decimal: Literal[",", "."] = "."
    encoding: str = "utf-8-sig"
    sheet: str | int = 0  # a spreadsheet's sheet: name, or index (0 = the first)
    columns: tuple[str, ...] = Field(min_length=1)
    unit: Literal["rad", "deg"] = "rad"
    join: Literal["row"] | KeyJoin = "row"

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, v: str) -> str:
        return text_encoding(v)

    @field_validator("sheet")
    @classmethod
    def _sheet(cls, v: str | int) -> str | int:
        return check_sheet(v)


@dataclass
class JoinedJoints:
    """The joint angles joined to a measurement file's rows."""
    q: np.ndarray            # (kept rows, k) rad, one row per kept measurement row
    keep: np.ndarray         # (measurement rows,) bool: False where the joint row was skipped (skip_bad)
    source: Path             # the joint table read
    skipped: list[SkippedRow] = field(default_factory=list)  # measurement rows dropped by the join


def _norm_key(text: str) -> str:
    """'7', '7.0', '7,0' and ' 7 ' are one key; anything else compares as its stripped text."""
    s = text.strip()
    try:
        v = float(s.replace(",", "."))
    except ValueError:
        return s
    return str(int(v)) if math.isfinite(v) and v == int(v) else s


def join_joints(spec: JointsSpec, data: Path, data_lines: Sequence[int], data_keys: Sequence[str] | None,
                data_separator: str, data_encoding: str, mapping_dir: Path | None, skip_bad: bool = False,
                mapping_file: str = "<mapping>", data_sheet: str | int = 0) -> JoinedJoints:
    """The joint angles (rad) of each kept measurement row (`data_lines`: their file lines;
    `data_keys`: their key cells for a key join; `data_sheet`: the measurement file's sheet, if
    it is a spreadsheet).

    Parameters
    ----------
    spec : JointsSpec
        The mapping's `joints:` section.
    data : Path
        The measurement file.
    data_lines : sequence of int
        The kept rows' file lines.
    data_keys : sequence of str or None
        Their key cells, for a key join.
    data_separator, data_encoding : str
        The measurement file's separator and encoding.
    mapping_dir : Path or None
        Where the mapping is (relative joint-table paths).
    skip_bad : bool, optional
        Drop rows whose joints are bad instead of raising.
    mapping_file : str, optional
        The mapping's name, for messages.
    data_sheet : str or int, optional
        The measurement file's sheet.

    Returns
    -------
    JoinedJoints
    """
    path = companion(spec.path, data, mapping_dir, "joints.path", mapping_file)
    specs = [ColumnSpec(f"q{i + 1}", c, scale=_ANGLE[spec.unit]) for i, c in enumerate(spec.columns)]
    if isinstance(spec.join, KeyJoin):
        specs.append(ColumnSpec("key", spec.join.joints_key or spec.join.key, kind="str"))
    vals, jlines, _, _ = parse_rows(path, spec.separator, spec.decimal, specs, skip_bad, encoding=spec.encoding,
                                    sheet=spec.sheet)
    q_all = np.column_stack([vals[s.key] for s in specs if s.key != "key"]).astype(float).reshape(len(jlines), -1)
    n = len(data_lines)
    keep = np.ones(n, bool)
    pick = np.zeros(n, np.int64)
    dropped: list[SkippedRow] = []
    if spec.join == "row":
        all_m = data_row_lines(data, data_separator, data_encoding, data_sheet)
        all_j = data_row_lines(path, spec.separator, spec.encoding, spec.sheet)
        if len(all_m) != len(all_j):
            raise DataError(f"{data}: {len(all_m)} data rows, but its joint table {path} has {len(all_j)}: "
                            "`join: row` pairs row i of one with row i of the other, so the counts must match "
                            "(a missing or extra row?; or join by a key column: `join: {key: COLUMN}`)")
        pos_m = {line: i for i, line in enumerate(all_m)}
        row_of_j = {line: k for k, line in enumerate(jlines)}
        for i, line in enumerate(data_lines):
            jl = all_j[pos_m[line]]
            if jl in row_of_j:
                pick[i] = row_of_j[jl]
            else:  # the joint row was bad and skipped (skip_bad): its measurement has no joints
                keep[i] = False
                dropped.append(SkippedRow(line, "<joints>", "",
                                          f"its joint row (line {jl} of {path.name}) was skipped"))
    else:
        assert data_keys is not None  # the importer reads the key column for a key join
        keys = [_norm_key(k) for k in vals["key"]]
        first: dict[str, int] = {}
        dup: dict[str, list[int]] = {}
        for k, key in enumerate(keys):
            if key in first:
                dup.setdefault(key, [jlines[first[key]]]).append(jlines[k])
            else:
                first[key] = k
        if dup:
            shown = "; ".join(f"{k!r} at lines {v}" for k, v in list(dup.items())[:5])
            raise DataError(f"{path}: key column '{spec.join.joints_key or spec.join.key}': {len(dup)} duplicate "
                            f"key(s) ({shown}): each key must name one joint configuration")
        missing = [(line, raw) for line, raw in zip(data_lines, data_keys) if _norm_key(raw) not in first]
        if missing and not skip_bad:
            shown = ", ".join(repr(raw) for _, raw in missing[:5])
            raise DataError(f"{data}: line {missing[0][0]}: column '{spec.join.key}': value {missing[0][1]!r}: "
                            f"no row of the joint table {path} has this key ({len(missing)} row(s) miss one: "
                            f"{shown}{' ...' if len(missing) > 5 else ''})")
        for i, raw in enumerate(data_keys):
            key = _norm_key(raw)
            if key in first:
                pick[i] = first[key]
            else:
                keep[i] = False
                dropped.append(SkippedRow(data_lines[i], spec.join.key, raw, f"no row of {path.name} has this key"))
    return JoinedJoints(q_all[pick[keep]], keep, path, dropped)
