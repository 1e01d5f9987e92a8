"""Cells and rows of a measurement file: the one row parser (`parse_rows`) behind the contract
table (`dataset.read_table`) and the import mappings (`importer`).

Each column spec turns one cell into a number; a failure names file, line, column and value
(`DataError`), or with skip_bad becomes a `SkippedRow`. See docs/measurement-table.md.
"""
from __future__ import annotations

import csv
import difflib
import logging
import math
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import TextIO

from dt_kernel.errors import DataError
from dt_runtime.measurements.limits import check_text_rows
from dt_runtime.measurements.sheets import SPREADSHEETS, Cell, cell_text, describe, read_sheet, sheet_note, sniff

log = logging.getLogger(__name__)

#: A header names columns: 64 k characters are a thousand columns of long names.
MAX_HEADER_CHARS = 2 ** 16
#: A row of numbers; csv's own limit for one field is 128 k characters.
MAX_LINE_CHARS = 2 ** 20


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
    kind: str = "float"  # or "cell": the cell as it is (text stripped; a spreadsheet's date-time typed)
    required: bool = True
    scale: float = 1.0


def parse_number(text: str, decimal: str = ".") -> float:
    """A number as a file's text cell writes it.

    Parameters
    ----------
    text : str
        The cell's text.
    decimal : str, optional
        The decimal mark, "." or ",".

    Returns
    -------
    float

    Raises
    ------
    CellError
        When the text is not a number with that decimal mark.
    """
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


def _parse_cell(cell: Cell, spec: ColumnSpec, decimal: str):
    if not isinstance(cell, str):
        return _parse_typed(cell, spec)
    text = cell.strip()
    if spec.kind in ("str", "cell"):
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


def _parse_typed(cell: Cell, spec: ColumnSpec):
    """A spreadsheet's non-text cell: a number is taken as it is (no decimal mark to guess), a
    duration (e.g. an elapsed-time column formatted [h]:mm:ss) is seconds; a date-time is a number
    of nothing (it belongs in a `time: {source: timestamp}` column, read with kind 'cell')."""
    if spec.kind == "cell":
        return cell
    if spec.kind == "str":
        return cell_text(cell)
    if isinstance(cell, bool):
        raise CellError("a TRUE/FALSE cell, not a number")
    if isinstance(cell, timedelta):
        v = cell.total_seconds()
    elif isinstance(cell, (int, float)):
        v = float(cell)
    else:
        raise CellError("a date/time cell, not a number (a time stamp column goes in the mapping's "
                        "`time: {source: timestamp, column: ...}`)")
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
    """`name` if Python knows the codec (a mapping's `encoding:` key), else ValueError saying what is allowed.

    Parameters
    ----------
    name : str
        A codec name.

    Returns
    -------
    str
    """
    import codecs

    try:
        codecs.lookup(name)
    except LookupError:
        raise ValueError(f"unknown text encoding {name!r} (e.g. utf-8, latin-1, cp1252)") from None
    return name


@dataclass(frozen=True)
class _Unreadable:
    """A CSV record the csv module could not split (e.g. a quote never closed)."""

    reason: str


Record = tuple[int, "Sequence[Cell] | _Unreadable"]


def _decode_error(path: Path, encoding: str, exc: UnicodeDecodeError) -> DataError:
    """A text file with bytes that are not `encoding`: 8-bit text from an instrument (sniff has
    already refused binary files and UTF-16, so the advice about latin-1 fits what is left)."""
    bad = exc.object[exc.start:exc.start + 1] if isinstance(exc.object, bytes) else b""
    where = f"byte {bad!r} at offset {exc.start}" if bad else str(exc)
    return DataError(f"{path}: not {encoding} text ({where}); an instrument's export is often latin-1 or cp1252: "
                     "set `encoding: latin-1` (or cp1252) in the import mapping")


def _records(path: Path, separator: str, encoding: str, sheet: str | int | None) -> tuple[bool, Iterator[Record]]:
    """Whether `path` is a spreadsheet, and every record of it, header first: (line, cells). CSV
    text, or with `sheet` given a spreadsheet's rows (line = the spreadsheet's row number);
    `_Unreadable` for a CSV record the csv module refuses. `sheet` None: the caller takes CSV
    only, and a spreadsheet is refused."""
    kind = sniff(path, encoding)
    if kind in SPREADSHEETS:
        if sheet is None:
            raise DataError(f"{path}: {describe(kind)}, and this input is read as CSV text: save the sheet as CSV "
                            "(a measurement file or a joint-angle table can be read as it is through an import "
                            "mapping, whose `sheet:` key picks the sheet)")
        return True, iter(read_sheet(path, sheet)[2])
    check_text_rows(path)  # a CSV of 10^7 rows: refused now, not after minutes and gigabytes
    return False, _csv_records(path, separator, encoding)


def _bounded_lines(f: TextIO, path: Path) -> Iterator[str]:
    """The lines of text file `f`, each read with a bound: DataError for the header (the first
    non-blank line) over MAX_HEADER_CHARS or any line over MAX_LINE_CHARS."""
    header, n = True, 0
    while line := f.readline(MAX_LINE_CHARS + 1):
        n += 1
        cap = MAX_HEADER_CHARS if header else MAX_LINE_CHARS
        if len(line.rstrip("\r\n")) > cap:
            what = "header line" if header else "line"
            raise DataError(f"{path}: line {n}: a {what} of more than {cap} characters; a measurement table's "
                            f"{what}s are shorter (is this the right file, with line breaks?)")
        header = header and not line.strip()
        yield line


def _csv_records(path: Path, separator: str, encoding: str) -> Iterator[Record]:
    try:
        with path.open(newline="", encoding=encoding) as f:
            reader = csv.reader(_bounded_lines(f, path), delimiter=separator)
            while True:
                try:
                    row = next(reader)
                except StopIteration:
                    return
                except csv.Error as exc:
                    yield reader.line_num, _Unreadable(f"unreadable CSV ({exc})")
                    continue
                yield reader.line_num, row
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise _decode_error(path, encoding, exc) from exc


def _blank(row) -> bool:
    # a typed (non-text) cell holds a value; a text cell may be spaces
    return not row or all(isinstance(c, str) and not c.strip() for c in row)


@dataclass
class _Table:
    header: list[str]
    line: int  # the header's line (a sheet's row number)
    spreadsheet: bool
    records: Iterator[Record]  # the records after the header


def _open(path: Path, separator: str, encoding: str, sheet: str | int | None) -> _Table:
    spreadsheet, records = _records(path, separator, encoding, sheet)
    first = next(records, None)
    # leading blank lines (a sheet's empty rows: layout) carry no header (docs/measurement-table.md)
    while first is not None and not isinstance(first[1], _Unreadable) and _blank(first[1]):
        first = next(records, None)
    if first is None:
        raise DataError(f"{path}: line 1: empty file, expected a header row")
    if isinstance(first[1], _Unreadable):
        raise DataError(f"{path}: line {first[0]}: unreadable header ({first[1].reason})")
    header = [cell_text(c) for c in first[1]]
    named = [c for c in header if c] if spreadsheet else header  # a sheet's unnamed columns are its margin
    dup = sorted({c for c in named if named.count(c) > 1})
    if dup:
        raise DataError(f"{path}: line {first[0]}: duplicate column(s) {dup}")
    return _Table(header, first[0], spreadsheet, records)


def sheet_hint(path: str | Path, encoding: str = "utf-8-sig", sheet: str | int | None = None) -> str:
    """'' for a text file, ' (sheet NAME of [...])' for a spreadsheet: for messages about columns.

    Parameters
    ----------
    path : str or Path
        The file.
    encoding : str, optional
        Its text encoding.
    sheet : str or int, optional
        The sheet a mapping names.

    Returns
    -------
    str
    """
    if sheet is None or not _is_sheet(Path(path), encoding, sheet):
        return ""
    return sheet_note(path, sheet)


def _is_sheet(path: Path, encoding: str, sheet: str | int | None) -> bool:
    return sheet is not None and sniff(path, encoding) in SPREADSHEETS


def read_header(path: str | Path, separator: str, encoding: str = "utf-8-sig",
                sheet: str | int | None = None) -> list[str]:
    """The column names of `path` (CSV; with `sheet` also a spreadsheet, by sheet name or index).

    Parameters
    ----------
    path : str or Path
        The file.
    separator : str
        The CSV separator.
    encoding : str, optional
        Its text encoding.
    sheet : str or int, optional
        A spreadsheet's sheet.

    Returns
    -------
    list of str
    """
    return _open(Path(path), separator, encoding, sheet).header


# How close a column name must come to a contract name to be taken for a misspelling of it
# (difflib's ratio of the two names lowercased without separators: 'sped' / 'speed' 0.89,
# 'temprature' / 'temperature' 0.95; 'humidity', 'session', 'fixture_temperature' stay far).
NEAR_MISS_RATIO = 0.8


def _folded(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def near_miss(column: str, names: Iterable[str]) -> str | None:
    """The contract name among `names` that `column` most likely misspells, or None: the same
    name but for case and separators ('Speed', 'point id', 'e_x'), or, for names of three
    characters and more, a difflib ratio of at least NEAR_MISS_RATIO ('sped' -> 'speed').

    Parameters
    ----------
    column : str
        A column name of the file.
    names : iterable of str
        The contract names it may misspell.

    Returns
    -------
    str or None
    """
    c = _folded(column)
    best: tuple[float, str] | None = None
    for name in names:
        k = _folded(name)
        if not c:
            break
        if c == k:
            return name
        if min(len(c), len(k)) >= 3:
            r = difflib.SequenceMatcher(None, c, k).ratio()
            if r >= NEAR_MISS_RATIO and (best is None or r > best[0]):
                best = (r, name)
    return None if best is None else best[1]


def refuse_near_misses(path: str | Path, unknown: Iterable[str], absent: Iterable[str], what: str) -> None:
    """DataError for the first column of `unknown` (not read as a contract column) that misspells
    a contract name of `absent` (one the file lacks): a misspelt `sped` must not pass as a column
    of the user's own while the speed silently drops out. `what`: where the names are documented.

    Parameters
    ----------
    path : str or Path
        The file, for the message.
    unknown : iterable of str
        The file's columns not read as contract columns.
    absent : iterable of str
        The contract names the file lacks.
    what : str
        Where the names are documented.

    Raises
    ------
    DataError
        For the first misspelt column, naming the contract name.
    """
    absent = list(absent)
    for col in unknown:
        name = near_miss(col, absent)
        if name is not None:
            raise DataError(f"{path}: line 1: column {col!r} is not a contract column but looks like {name!r} "
                            f"({what}): rename it to {name!r}, or give a column of your own a name further "
                            "from the contract's")


def parse_rows(path: str | Path, separator: str, decimal: str, specs: Sequence[ColumnSpec],
               skip_bad: bool = False,
               row_check: Callable[[dict], None] | None = None,
               encoding: str = "utf-8-sig",
               sheet: str | int | None = None,
               ) -> tuple[dict[str, list], list[int], list[SkippedRow], list[str]]:
    """Parse every data row of `path` by `specs` (CSV; with `sheet` also a spreadsheet).

    Returns (values per key, source line per kept row, skipped rows, header). A bad row
    raises DataError '<file>: line N: column C: value V: reason' unless skip_bad. `row_check`
    sees each parsed row (a dict key -> value) and may raise CellError with `.column` set.

    A file is CSV text, or, where the caller names a sheet (an import mapping's `sheet:`), a
    spreadsheet (`sheets`: .xlsx, .xls, .ods), whose typed cells go through the same specs: a number
    cell is taken as it is, a text cell is parsed like a CSV cell, and the "line" of a message is
    the spreadsheet's row number. The header is the first non-blank row: blank lines (and a sheet's
    empty rows) are ignored wherever they are, leading ones too. Lines are read bounded: a header
    line over MAX_HEADER_CHARS or any line over MAX_LINE_CHARS is a DataError naming the line (a
    file without line breaks is not read whole).

    Parameters
    ----------
    path : str or Path
        The file.
    separator : str
        The CSV separator.
    decimal : str
        The decimal mark of text cells.
    specs : sequence of ColumnSpec
        One per column read.
    skip_bad : bool, optional
        Skip bad rows (listed) instead of raising.
    row_check : callable, optional
        Called with each parsed row.
    encoding : str, optional
        The text encoding.
    sheet : str or int, optional
        A spreadsheet's sheet.

    Returns
    -------
    values : dict of str to list
    lines : list of int
        The source line of each kept row.
    skipped : list of SkippedRow
    header : list of str
    """
    path = Path(path)
    table = _open(path, separator, encoding, sheet)
    header, spreadsheet = table.header, table.spreadsheet
    missing = [s.column for s in specs if s.column not in header]
    if missing:
        raise DataError(f"{path}: line {table.line}: missing column(s) {missing}; header has {header}"
                        + sheet_hint(path, encoding, sheet))
    pos = [header.index(s.column) for s in specs]
    out: dict[str, list] = {s.key: [] for s in specs}
    lines: list[int] = []
    skipped: list[SkippedRow] = []
    for line, row in table.records:
        if isinstance(row, _Unreadable):
            bad = SkippedRow(line, "<row>", "", row.reason)
            if not skip_bad:
                raise DataError(f"{path}: {bad}")
            skipped.append(bad)
            continue
        if _blank(row):
            continue  # blank lines carry no row
        try:
            # a sheet is rectangular: its rows are as wide as its used area, header or not
            if not spreadsheet and len(row) != len(header):
                raise _BadRow("<row>", separator.join(map(str, row))[:80],
                              f"{len(row)} cells, header has {len(header)}")
            parsed = {}
            for spec, p in zip(specs, pos):
                try:
                    parsed[spec.key] = _parse_cell(row[p], spec, decimal)
                except CellError as exc:
                    raise _BadRow(spec.column, cell_text(row[p]), exc.reason) from None
            if row_check is not None:
                try:
                    row_check(parsed)
                except CellError as exc:
                    col = getattr(exc, "column", "<row>")
                    raise _BadRow(col, cell_text(row[header.index(col)]) if col in header else "",
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
    if skipped:
        log.warning("%s: skipped %d bad row(s), first: %s", path, len(skipped), skipped[0])
    return out, lines, skipped, header


class _BadRow(Exception):
    def __init__(self, column: str, value: str, reason: str):
        super().__init__(reason)
        self.column, self.value, self.reason = column, value, reason


def cell_error(column: str, reason: str) -> CellError:
    """A CellError naming the column it is about.

    Parameters
    ----------
    column : str
        The column's name.
    reason : str
        What is wrong.

    Returns
    -------
    CellError
    """
    exc = CellError(reason)
    exc.column = column  # type: ignore[attr-defined]
    return exc


def data_row_lines(path: str | Path, separator: str, encoding: str = "utf-8-sig",
                   sheet: str | int | None = None) -> list[int]:
    """The file line of every data row (blank lines skipped, as `parse_rows` does): a row's index
    in this list is its position in the file, which a join by row order pairs across two files.

    Parameters
    ----------
    path : str or Path
        The file.
    separator : str
        The CSV separator.
    encoding : str, optional
        The text encoding.
    sheet : str or int, optional
        A spreadsheet's sheet.

    Returns
    -------
    list of int
    """
    out: list[int] = []
    for line, row in _open(Path(path), separator, encoding, sheet).records:
        if isinstance(row, _Unreadable):
            raise DataError(f"{path}: line {line}: cannot read its rows ({row.reason})")
        if not _blank(row):
            out.append(line)
    return out


def numeric_columns(path: str | Path, names: Sequence[str], lines: Sequence[int], separator: str = ",",
                    decimal: str = ".", encoding: str = "utf-8-sig", sheet: str | int | None = None,
                    ) -> tuple[dict[str, list[float]], list[str]]:
    """The columns `names` of `path` on the data rows at `lines` (in that order), as numbers (NaN
    where a cell is empty): the file's own columns beside the ones a reader parsed. A column with
    any cell that is not a number is left out. Returns (values per kept column, the columns left out).

    Parameters
    ----------
    path : str or Path
        The file.
    names : sequence of str
        The columns wanted.
    lines : sequence of int
        The data rows' lines, in the order wanted.
    separator : str, optional
        The CSV separator.
    decimal : str, optional
        The decimal mark.
    encoding : str, optional
        The text encoding.
    sheet : str or int, optional
        A spreadsheet's sheet.

    Returns
    -------
    values : dict of str to list of float
    left_out : list of str
    """
    path = Path(path)
    if not names:
        return {}, []
    table = _open(path, separator, encoding, sheet)
    specs = [(ColumnSpec(c, c, required=False), table.header.index(c)) for c in names]
    at = {int(line): i for i, line in enumerate(lines)}
    cols: dict[str, list[float]] = {c: [math.nan] * len(at) for c in names}
    bad: set[str] = set()
    for line, row in table.records:
        i = at.get(line)
        if i is None or isinstance(row, _Unreadable):
            continue
        for spec, j in specs:
            if spec.column in bad:
                continue
            try:
                cols[spec.column][i] = _parse_cell(row[j] if j < len(row) else "", spec, decimal)
            except CellError:
                bad.add(spec.column)
    left_out = [c for c in names if c in bad]
    return {c: v for c, v in cols.items() if c not in bad}, left_out
