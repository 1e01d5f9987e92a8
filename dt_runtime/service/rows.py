"""Typed rows of the store's high-rate tables: one small frozen dataclass per table.

The daemon loop builds one row per event and hands it to `Store.put`; the store's writer turns
it into SQL values (`values()`), so the loop never formats JSON nor touches SQLite. Field names
are the table's column names, in order. Units: SI (m, m/s); `t` is the caller's time stamp (s);
`data` is an optional JSON-ready mapping, stored as compact JSON (NaN becomes null).
"""
from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cache
from typing import Any, ClassVar

from dt_runtime.common.jsonsafe import compact


def _sql(v: Any) -> Any:
    """One column value as SQLite takes it: numbers as float, flags as 0/1, data as JSON."""
    if v is None:
        return None
    if isinstance(v, Mapping):
        return compact(dict(v)) if v else None
    if isinstance(v, bool):
        return int(v)
    return float(v)


class Row:
    """Base of the typed rows: the table it goes to and its column values."""

    __slots__ = ()
    TABLE: ClassVar[str]

    @classmethod
    @cache
    def columns(cls) -> tuple[str, ...]:
        """The table's column names: the row's fields, in order."""
        return tuple(f.name for f in fields(cls))  # type: ignore[arg-type]

    def values(self) -> tuple:
        """The column values as SQLite takes them: numbers as float, flags as 0/1, `data` as
        compact JSON (None when empty)."""
        return tuple(_sql(getattr(self, c)) for c in self.columns())

    @classmethod
    def from_mapping(cls, row: Mapping[str, Any]) -> Row:
        """A row from {column: value}; keys that are not columns go into `data`.

        Parameters
        ----------
        row : Mapping
            Column values (a missing optional column is None), and any extra keys.

        Returns
        -------
        Row
            An instance of the class it is called on.
        """
        cols = cls.columns()
        extra = {k: v for k, v in row.items() if k not in cols}
        data = dict(row.get("data") or {}) | extra
        return cls(**{c: row.get(c) for c in cols if c != "data"}, data=data or None)  # type: ignore[call-arg]


@dataclass(frozen=True, slots=True)
class CommandRow(Row):
    """Commanded TCP (m, robot frame) and speed (m/s)."""

    TABLE: ClassVar[str] = "commands"
    t: float
    x: float
    y: float
    z: float
    speed: float | None = None
    data: Mapping[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class CorrectionRow(Row):
    """Predicted error e_hat (m) applied to a command, and its standard uncertainty (m)."""

    TABLE: ClassVar[str] = "corrections"
    t: float
    dx: float
    dy: float
    dz: float
    ux: float | None = None
    uy: float | None = None
    uz: float | None = None
    data: Mapping[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class MeasurementRow(Row):
    """A measured TCP (m) and its difference from the prediction (m): the daemon stores the MVS
    point in the MVS frame and e_LT_hat - e_MVS in GL, what Eq. 17 tests (`dt status` names them)."""

    TABLE: ClassVar[str] = "measurements"
    t: float
    x: float
    y: float
    z: float
    ex: float | None = None
    ey: float | None = None
    ez: float | None = None
    data: Mapping[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class TTestRow(Row):
    """One in-service Eq. 17 t-test outcome (the worst axis' t, the smallest p)."""

    TABLE: ClassVar[str] = "t_stats"
    t: float
    t_value: float
    dof: float | None = None
    p_value: float | None = None
    passed: bool | None = None
    data: Mapping[str, Any] | None = None


def shown_time(t: float) -> str:
    """A row's time stamp as an operator reads it.

    Parameters
    ----------
    t : float
        s: epoch seconds (a daemon with `realtime: true`) or the simulated clock.

    Returns
    -------
    str
        Local time to a tenth of a second when `t` is a wall-clock time (after 2001-09-09), else
        "t = ... s (simulated clock)".
    """
    if t > 1e9:  # 2001-09-09 or later: the wall clock; a simulated clock never gets there
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) + f".{int(t % 1 * 10)}"
    return f"t = {t:.1f} s (simulated clock)"


ROW_TYPES: dict[str, type[Row]] = {c.TABLE: c for c in (CommandRow, CorrectionRow, MeasurementRow, TTestRow)}
