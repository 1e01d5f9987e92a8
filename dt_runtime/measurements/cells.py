"""Cells and rows of a measurement file: the one row parser behind the contract table
(`dataset.read_table`) and the import mappings (`importer`). Each column spec turns one cell into
a number; a failure names file, line, column and value (`DataError`), or with skip_bad becomes a
`SkippedRow`.
"""
from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dt_kernel.errors import DataError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SkippedRow:
    """A row left out by `skip_bad=True`: where it was and why."""

    line: int
    column: str
    value: str
    reason: str

    def __str__(self) -> str:
        return f"line {self.line}: column '{self.column}': value {self.value!r}: {self.reason}"



class CellError(ValueError):
    """One cell is unusable (caught per row; becomes DataError or SkippedRow)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class ColumnSpec:
    """Cell `column` of the file -> field `key`. kind: float | int | str.

    required: the cell must be non-empty (and finite for floats); otherwise an empty cell
    becomes NaN (floats) and is an error for ints. scale multiplies floats (unit -> SI).
    """

    key: str
    column: str
    kind: str = "float"
    required: bool = True
    scale: float = 1.0


def parse_number(text: str, decimal: str = ".") -> float:
    s = text.strip()
    if decimal == ",":
        if "." in s:  # '.' is not allowed once ',' is the decimal mark (thousands separators?)
            raise CellError("not a number with decimal comma")
        s = s.replace(",", ".")
    elif "," in s:
        raise CellError("not a number (decimal comma in a '.'-decimal file?)")
    try:
        return float(s)
    except ValueError:
        raise CellError("not a number") from None


def _parse_cell(cell: str, spec: ColumnSpec, decimal: str):
    text = cell.strip()
    if spec.kind == "str":
        if spec.required and not text:
            raise CellError("empty cell")
        return text
    if not text:
        if spec.required or spec.kind == "int":
            raise CellError("empty cell")
        return math.nan
    v = parse_number(text, decimal)
    if spec.kind == "int":
        if not math.isfinite(v) or v != int(v):
            raise CellError("not an integer")
        return int(v)
    if not math.isfinite(v):
        if spec.required:
            raise CellError("not a finite number")
        return math.nan
    return v * spec.scale


def text_encoding(name: str) -> str:
    """`name` if Python knows the codec (a mapping's `encoding:` key), else ValueError saying what is allowed."""
    import codecs

    try:
        codecs.lookup(name)
    except LookupError:
        raise ValueError(f"unknown text encoding {name!r} (e.g. utf-8, latin-1, cp1252)") from None
    return name


def read_header(path: str | Path, separator: str, encoding: str = "utf-8-sig") -> list[str]:
    path = Path(path)
    try:
        with path.open(newline="", encoding=encoding) as f:
            first = next(csv.reader(f, delimiter=separator), None)
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: not {encoding} text ({exc}); an instrument's export may be latin-1: "
                        "set `encoding: latin-1` in the import mapping") from exc
    if not first:
        raise DataError(f"{path}: line 1: empty file, expected a header row")
    header = [c.strip() for c in first]
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise DataError(f"{path}: line 1: duplicate column(s) {dup}")
    return header


def parse_rows(path: str | Path, separator: str, decimal: str, specs: Sequence[ColumnSpec],
               skip_bad: bool = False,
               row_check: Callable[[dict], None] | None = None,
               encoding: str = "utf-8-sig",
               ) -> tuple[dict[str, list], list[int], list[SkippedRow], list[str]]:
    """Parse every data row of `path` by `specs`.

    Returns (values per key, source line per kept row, skipped rows, header). A bad row
    raises DataError '<file>: line N: column C: value V: reason' unless skip_bad. `row_check`
    sees each parsed row (a dict key -> value) and may raise CellError with `.column` set.
    """
    path = Path(path)
    header = read_header(path, separator, encoding)
    missing = [s.column for s in specs if s.column not in header]
    if missing:
        raise DataError(f"{path}: line 1: missing column(s) {missing}; header has {header}")
    pos = [header.index(s.column) for s in specs]
    out: dict[str, list] = {s.key: [] for s in specs}
    lines: list[int] = []
    skipped: list[SkippedRow] = []
    try:
        with path.open(newline="", encoding=encoding) as f:
            reader = csv.reader(f, delimiter=separator)
            next(reader)
            while True:
                try:
                    row = next(reader)
                except StopIteration:
                    break
                except csv.Error as exc:
                    bad = SkippedRow(reader.line_num, "<row>", "", f"unreadable CSV ({exc})")
                    if not skip_bad:
                        raise DataError(f"{path}: {bad}") from exc
                    skipped.append(bad)
                    continue
                line = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue  # blank lines carry no row
                try:
                    if len(row) != len(header):
                        raise _BadRow("<row>", separator.join(row)[:80],
                                      f"{len(row)} cells, header has {len(header)}")
                    parsed = {}
                    for spec, p in zip(specs, pos):
                        try:
                            parsed[spec.key] = _parse_cell(row[p], spec, decimal)
                        except CellError as exc:
                            raise _BadRow(spec.column, row[p], exc.reason) from None
                    if row_check is not None:
                        try:
                            row_check(parsed)
                        except CellError as exc:
                            col = getattr(exc, "column", "<row>")
                            raise _BadRow(col, row[header.index(col)] if col in header else "",
                                          exc.reason) from None
                except _BadRow as bad:
                    sk = SkippedRow(line, bad.column, bad.value, bad.reason)
                    if not skip_bad:
                        raise DataError(f"{path}: {sk}") from None
                    skipped.append(sk)
                    continue
                for k, v in parsed.items():
                    out[k].append(v)
                lines.append(line)
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: not UTF-8 text ({exc})") from exc
    if skipped:
        log.warning("%s: skipped %d bad row(s), first: %s", path, len(skipped), skipped[0])
    return out, lines, skipped, header


class _BadRow(Exception):
    def __init__(self, column: str, value: str, reason: str):
        super().__init__(reason)
        self.column, self.value, self.reason = column, value, reason


def cell_error(column: str, reason: str) -> CellError:
    exc = CellError(reason)
    exc.column = column  # type: ignore[attr-defined]
    return exc




def data_row_lines(path: str | Path, separator: str, encoding: str = "utf-8-sig") -> list[int]:
    """The file line of every data row (blank lines skipped, as `parse_rows` does): a row's index
    in this list is its position in the file, which a join by row order pairs across two files."""
    path = Path(path)
    out: list[int] = []
    try:
        with path.open(newline="", encoding=encoding) as f:
            reader = csv.reader(f, delimiter=separator)
            next(reader, None)
            for row in reader:
                if row and any(c.strip() for c in row):
                    out.append(reader.line_num)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"{path}: cannot read its rows ({exc})") from exc
    return out
