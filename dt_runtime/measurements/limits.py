"""How large an input table may be, checked before it is parsed: a file that would take minutes and
gigabytes (a CSV of 10^7 rows, a full 1,048,576-row sheet, an .xlsx whose sheet inflates to
2.4 GB) is refused at once, naming the limit and how to raise it.

The limits (docs/measurement-table.md, "Size limits"), each an environment variable:

- DT_MAX_ROWS (default 200,000): rows of a CSV file or of a spreadsheet's sheet. The largest real
  series shipped (IPA's UR10, Series A) has 11,910;
- DT_MAX_SHEET_MB (default 256): what a spreadsheet unpacks to (its zip members), or an .xls file's
  size: the reader holds the sheet's cells in memory;
- DT_MAX_COLUMNS (default 1,000): the widest row a sheet may span (Excel allows 16,384; a cell far
  to the right makes the reader allocate every column up to it, on every row).

A CSV file's rows are counted by its line breaks (a quick byte scan that stops past the limit); a
spreadsheet's by streaming its sheets' XML (`<row>` elements and the row numbers they carry, the
declared `<dimension>`), never by loading them: the declared unpacked sizes are checked first, and
a member that unpacks to more than it declares fails its CRC check, so a lying zip is refused too.
"""
from __future__ import annotations

import functools
import os
import re
import zipfile
from pathlib import Path

from dt_kernel.errors import ConfigError, DataError

ROWS_ENV, ROWS_DEFAULT = "DT_MAX_ROWS", 200_000
SHEET_MB_ENV, SHEET_MB_DEFAULT = "DT_MAX_SHEET_MB", 256
COLUMNS_ENV, COLUMNS_DEFAULT = "DT_MAX_COLUMNS", 1_000
CHUNK = 1 << 20  # bytes read (or unpacked) at a time: the check's memory is a few of these
_OVERLAP = 256  # bytes kept between chunks, so that a tag cut by a chunk's end is still seen whole

_ROW = re.compile(rb"<row[\s>/]")
_ROW_NUMBER = re.compile(rb"<row\s[^>]*?\br=\"(\d{1,12})\"")
_CELL_COLUMN = re.compile(rb"<c\s[^>]*?\br=\"([A-Z]{1,7})\d")
_DIMENSION = re.compile(rb"<dimension\s+ref=\"([A-Z]{1,7})?(\d{1,12})?(?::([A-Z]{1,7})(\d{1,12}))?\"")
_ODS_ROW = re.compile(rb"<table:table-row[\s>/]")
_ODS_REPEAT = re.compile(rb"<table:table-row\s[^>]*?table:number-rows-repeated=\"(\d{1,12})\"")


def _limit(env: str, default: int) -> int:
    raw = os.environ.get(env)
    if raw is None:
        return default
    try:
        v = int(raw.replace("_", ""))
    except ValueError:
        v = 0
    if v < 1:
        raise ConfigError("environment", env, raw, f"a whole number >= 1 (default {default:,})")
    return v


def max_rows() -> int:
    """The most rows a table may have: $DT_MAX_ROWS, else 200,000.

    Returns
    -------
    int

    Raises
    ------
    ConfigError
        When the variable is not a whole number >= 1.
    """
    return _limit(ROWS_ENV, ROWS_DEFAULT)


def max_sheet_bytes() -> int:
    """The most bytes a spreadsheet may unpack to: $DT_MAX_SHEET_MB (MB), else 256 MB.

    Returns
    -------
    int

    Raises
    ------
    ConfigError
        When the variable is not a whole number >= 1.
    """
    return _limit(SHEET_MB_ENV, SHEET_MB_DEFAULT) * 1_000_000


def max_columns() -> int:
    """The widest a sheet's rows may span: $DT_MAX_COLUMNS, else 1,000.

    Returns
    -------
    int

    Raises
    ------
    ConfigError
        When the variable is not a whole number >= 1.
    """
    return _limit(COLUMNS_ENV, COLUMNS_DEFAULT)


def _too_many_rows(path: Path, what: str, n: int | str, limit: int) -> DataError:
    return DataError(f"{path}: {what} has {n} rows, over the limit of {limit:,} rows ({ROWS_ENV}); a measurement "
                     f"table is far shorter (is this the right file?); if it is, raise the limit, e.g. "
                     f"{ROWS_ENV}={max(limit * 10, 1_000_000)} dt ...")


def check_text_rows(path: str | Path) -> None:
    """Refuse a text table of more than `max_rows()` rows (plus a header), counting its line breaks
    without parsing it (stops reading once past the limit).

    Parameters
    ----------
    path : str or Path
        The CSV file.

    Raises
    ------
    DataError
        When it has more rows than the limit (naming it and how to raise it), or cannot be read.
    ConfigError
        When $DT_MAX_ROWS is not a whole number >= 1.
    """
    path = Path(path)
    limit = max_rows()
    try:
        st = path.stat()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    _text_rows(str(path), st.st_mtime_ns, st.st_size, limit)


@functools.lru_cache(maxsize=8)
def _text_rows(path: str, _mtime: int, _size: int, limit: int) -> None:
    # a header, a units line, a few comment or blank lines: the limit is on the rows, not exact to one
    allowed = limit + 10
    lines = 0
    try:
        with open(path, "rb") as f:
            while chunk := f.read(CHUNK):
                lines += chunk.count(b"\n")
                if lines > allowed:
                    raise _too_many_rows(Path(path), "the file", f"at least {lines:,}", limit)
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc


def check_spreadsheet(path: str | Path, kind: str) -> None:
    """Refuse a spreadsheet that would unpack to more than `max_sheet_bytes()`, or a sheet of more
    rows than `max_rows()` or wider than `max_columns()`, before any of it is parsed.

    Parameters
    ----------
    path : str or Path
        The spreadsheet.
    kind : str
        "xlsx" (also .xlsm / .xlsb), "ods" or "xls" (`sheets.sniff`).

    Raises
    ------
    DataError
        Naming the limit passed and how to raise it, or the damage found (a member that unpacks to
        more than it declares).
    ConfigError
        When a limit's variable is not a whole number >= 1.
    """
    path = Path(path)
    limits = (max_sheet_bytes(), max_rows(), max_columns())
    try:
        st = path.stat()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    _spreadsheet(str(path), st.st_mtime_ns, st.st_size, kind, *limits)


def _mb(n: int) -> str:
    return f"{n / 1e6:,.0f} MB" if n >= 10_000_000 else f"{n / 1e6:.1f} MB"


@functools.lru_cache(maxsize=8)
def _spreadsheet(path_s: str, _mtime: int, size: int, kind: str, max_bytes: int, rows: int, columns: int) -> None:
    path = Path(path_s)
    raise_it = (f"if it is genuine, raise the limit, e.g. {SHEET_MB_ENV}={max(2 * max_bytes // 1_000_000, 1024)} "
                "dt ..., or export the sheet as CSV")
    if kind == "xls":  # one compound file, not a zip: the sheet is about the file's size
        if size > max_bytes:
            raise DataError(f"{path}: an .xls workbook of {_mb(size)}, more than the limit of {_mb(max_bytes)} "
                            f"({SHEET_MB_ENV}); {raise_it}")
        return
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
            unpacked = sum(i.file_size for i in infos)
            if unpacked > max_bytes:
                big = max(infos, key=lambda i: i.file_size)
                raise DataError(f"{path}: the spreadsheet unpacks to {_mb(unpacked)} ({big.filename}: "
                                f"{_mb(big.file_size)} from {_mb(big.compress_size)} in the file), more than the limit "
                                f"of {_mb(max_bytes)} ({SHEET_MB_ENV}); {raise_it}")
            sheets = [i for i in infos if (i.filename.startswith("xl/worksheets/") and i.filename.endswith(".xml"))
                      or i.filename == "content.xml"]
            for info in sheets:
                _scan(path, z, info, kind, rows, columns)
    except zipfile.BadZipFile as exc:
        raise DataError(f"{path}: a damaged spreadsheet ({exc}): a part unpacks to something else than it declares; "
                        "save it again from the spreadsheet program, or export it as CSV") from exc
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from exc


def _column_number(letters: bytes) -> int:
    n = 0
    for ch in letters:
        n = n * 26 + ch - 64
    return n


def _scan(path: Path, z: zipfile.ZipFile, info: zipfile.ZipInfo, kind: str, rows: int, columns: int) -> None:
    """Stream one sheet's XML (CRC-checked by zipfile at its end) counting its rows: refused as soon
    as the count, a row's number or the declared dimension passes a limit."""
    what = f"sheet {info.filename}"
    n = last = widest = 0
    buf = b""
    head = True
    with z.open(info) as f:
        while True:
            chunk = f.read(CHUNK)
            eof = not chunk
            buf += chunk
            if head and kind != "ods":  # the declared <dimension> comes first: the reader sizes the sheet by it
                head = False
                dim = _DIMENSION.search(buf[:CHUNK])
                if dim and dim.group(4):
                    if int(dim.group(4)) > rows + 10:
                        raise _too_many_rows(path, f"{what} (its declared dimension)", f"{int(dim.group(4)):,}", rows)
                    if _column_number(dim.group(3)) > columns:
                        raise _too_wide(path, what, _column_number(dim.group(3)), columns)
            # a tag is counted in the chunk where it starts; the last _OVERLAP bytes wait for the next
            cut = len(buf) if eof else max(len(buf) - _OVERLAP, 0)
            if kind == "ods":
                n += sum(1 for m in _ODS_ROW.finditer(buf) if m.start() < cut)
                n += sum(int(m.group(1)) - 1 for m in _ODS_REPEAT.finditer(buf) if m.start() < cut)
            else:
                n += sum(1 for m in _ROW.finditer(buf) if m.start() < cut)
                last = max([last, *(int(m.group(1)) for m in _ROW_NUMBER.finditer(buf) if m.start() < cut)])
                cols = {m.group(1) for m in _CELL_COLUMN.finditer(buf) if m.start() < cut}
                widest = max([widest, *(_column_number(c) for c in cols)])
                if widest > columns:
                    raise _too_wide(path, what, widest, columns)
            if max(n, last) > rows + 10:
                raise _too_many_rows(path, what, f"{'at least ' if not eof else ''}{max(n, last):,}", rows)
            buf = buf[cut:]
            if eof:
                return


def _too_wide(path: Path, what: str, c: int, limit: int) -> DataError:
    return DataError(f"{path}: {what} spans {c:,} columns, more than the limit of {limit:,} ({COLUMNS_ENV}); a "
                     f"cell far to the right makes every row that wide; delete the stray cells, or raise the limit, "
                     f"e.g. {COLUMNS_ENV}={max(limit * 4, 16_384)} dt ...")
