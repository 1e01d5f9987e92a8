"""What a data file is (text, a spreadsheet, or something else: `sniff`), and a spreadsheet's cells
(`read_sheet`).

Spreadsheets (.xlsx, .xlsm, .xlsb, .xls, .ods) are read through python-calamine; their cells keep
their types. See docs/measurement-table.md and docs/campaigns.md.
"""
from __future__ import annotations

import codecs
import functools
import zipfile
from collections.abc import Sequence
from datetime import date, datetime, time, timedelta
from pathlib import Path
from typing import Literal

from dt_kernel.errors import DataError

Kind = Literal["text", "xlsx", "xls", "ods"]
Cell = str | float | int | bool | datetime | date | time | timedelta
SPREADSHEETS = ("xlsx", "xls", "ods")
WHAT_TO_DO = "export the data as CSV (or as an .xlsx / .ods spreadsheet) and give that file"

# First bytes of formats a user may hand over by mistake: what they are, to say so.
_MAGIC: tuple[tuple[bytes, str], ...] = (
    (b"%PDF", "a PDF document"),
    (b"PAR1", "a Parquet file"),
    (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"GIF8", "a GIF image"),
    (b"II*\x00", "a TIFF image"),
    (b"MM\x00*", "a TIFF image"),
    (b"\x1f\x8b", "a gzip-compressed file (unpack it first)"),
    (b"BZh", "a bzip2-compressed file (unpack it first)"),
    (b"\xfd7zXZ\x00", "an xz-compressed file (unpack it first)"),
    (b"7z\xbc\xaf\x27\x1c", "a 7-Zip archive (unpack it first)"),
    (b"Rar!", "a RAR archive (unpack it first)"),
    (b"\x89HDF", "an HDF5 file"),
    (b"SQLite format 3\x00", "an SQLite database"),
    (b"\x93NUMPY", "a NumPy array file (.npy)"),
    (b"ARROW1", "an Arrow/Feather file"),
    (b"\x00\x00\xfe\xff", "UTF-32 text (big-endian byte-order mark)"),
    (b"\xff\xfe\x00\x00", "UTF-32 text (little-endian byte-order mark)"),
)
_OLE2 = b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1"  # compound file: the old .xls (or .doc, .msg ...)
_ODS = "application/vnd.oasis.opendocument.spreadsheet"


def _codec(encoding: str) -> str:
    try:
        return codecs.lookup(encoding).name
    except LookupError:
        return encoding


def _utf16_guess(head: bytes) -> str | None:
    """'le' / 'be' when `head` reads as mostly-ASCII UTF-16 without a byte-order mark (every other
    byte NUL), else None."""
    n = len(head) - len(head) % 2
    if n < 4:
        return None
    even, odd = head[0:n:2], head[1:n:2]
    for zeros, text, order in ((odd, even, "le"), (even, odd, "be")):
        if zeros.count(0) >= 0.9 * len(zeros) and text.count(0) <= 0.1 * len(text):
            return order
    return None


def _refuse(path: Path, what: str, todo: str = WHAT_TO_DO) -> DataError:
    return DataError(f"{path}: not a table this reader takes: it looks like {what}; {todo}")


def sniff(path: str | Path, encoding: str = "utf-8-sig") -> Kind:
    """The kind of `path` by its first bytes; DataError (naming what the file looks like and what
    to do) for a file that is neither text in `encoding` nor a spreadsheet.

    Parameters
    ----------
    path : str or Path
        The file.
    encoding : str, optional
        The text encoding expected.

    Returns
    -------
    str
        "xlsx", "xls", "ods" or "text".

    Notes
    -----
    The kind is told by the file's first bytes, not its name (a workbook saved as `points.csv` is
    still a workbook). Any other binary file (a PDF, a zip archive, Parquet, an image, UTF-16 text
    without a byte-order mark ...) is refused with what it looks like and what to do, never with
    advice about a text encoding it does not have.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(4096)
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    codec = _codec(encoding)
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return _zip_kind(path)
    if head.startswith(_OLE2):
        return "xls"
    for magic, what in _MAGIC:
        if head.startswith(magic) and not (what.startswith("UTF-32") and codec.startswith("utf-32")):
            raise _refuse(path, what)
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        if codec.startswith("utf-16"):
            return "text"
        raise _refuse(path, "UTF-16 text with a byte-order mark (a spreadsheet's 'Unicode text' export)",
                      "set `encoding: utf-16` in the import mapping, or export the data as UTF-8 CSV or .xlsx / .ods")
    if b"\x00" in head and not codec.startswith(("utf-16", "utf-32")):
        order = _utf16_guess(head)
        if order is not None:
            endian = "little" if order == "le" else "big"
            raise _refuse(path, f"UTF-16 text without a byte-order mark ({endian}-endian)",
                          f"set `encoding: utf-16-{order}` in the import mapping, or export the data as UTF-8 CSV "
                          "or .xlsx / .ods")
        raise _refuse(path, "a binary file (it holds NUL bytes), not text")
    return "text"


def _zip_kind(path: Path) -> Kind:
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
            mimetype = z.read("mimetype").decode("ascii", "replace").strip() if "mimetype" in names else None
    except (zipfile.BadZipFile, OSError) as exc:
        raise _refuse(path, f"a damaged zip archive or spreadsheet ({exc})") from exc
    if any(n in names for n in ("xl/workbook.xml", "xl/workbook.bin")):
        return "xlsx"
    if mimetype == _ODS:
        return "ods"
    if mimetype is not None:
        raise _refuse(path, f"an OpenDocument file of type {mimetype!r}, not a spreadsheet")
    if "word/document.xml" in names:
        raise _refuse(path, "a Word document (.docx)")
    if any(n.startswith("ppt/") for n in names):
        raise _refuse(path, "a PowerPoint presentation (.pptx)")
    shown = ", ".join(names[:5]) + (f" ... ({len(names)} entries)" if len(names) > 5 else "")
    raise _refuse(path, f"a zip archive (holding {shown or 'nothing'})",
                  "unpack it and give the measurement file inside")


def describe(kind: Kind) -> str:
    """How a message names a kind of file.

    Parameters
    ----------
    kind : str
        "xlsx", "xls", "ods" or "text".

    Returns
    -------
    str
    """
    return {"xlsx": "an Excel workbook", "xls": "an Excel 97-2003 workbook (.xls)",
            "ods": "an OpenDocument spreadsheet (.ods)", "text": "text"}[kind]


def check_sheet(v: str | int) -> str | int:
    """A mapping's `sheet:` value: a sheet name, or its index (0 = the first).

    Parameters
    ----------
    v : str or int
        The value.

    Returns
    -------
    str or int

    Raises
    ------
    ValueError
        For a negative index or an empty name.
    """
    if isinstance(v, int) and v < 0:
        raise ValueError("a sheet name, or its index: 0 for the first sheet, 1 for the second ...")
    if isinstance(v, str) and not v.strip():
        raise ValueError("a sheet name (not empty), or its index: 0 for the first sheet")
    return v


def read_sheet(path: str | Path, sheet: str | int) -> tuple[str, list[str], Sequence[tuple[int, tuple[Cell, ...]]]]:
    """The rows of one sheet of the spreadsheet `path`: (the sheet's name, the workbook's sheet
    names, [(row number as the spreadsheet shows it, cells from column A)]). DataError when the
    workbook cannot be read or has no such sheet (the sheets it has named).

    Parameters
    ----------
    path : str or Path
        The spreadsheet.
    sheet : str or int
        Sheet name or index.

    Returns
    -------
    name : str
    sheets : list of str
    rows : sequence of (int, tuple of Cell)

    Notes
    -----
    Refused before it is read when it passes a size limit (`limits.check_spreadsheet`:
    DT_MAX_SHEET_MB, DT_MAX_ROWS, DT_MAX_COLUMNS). Read through python-calamine (Rust's calamine:
    one reader for all formats); cells keep their types: numbers as floats (no decimal-comma
    question), dates and times as `datetime` / `date` / `time` / `timedelta`, text as `str`, an
    empty cell as ''.
    """
    from dt_runtime.measurements.limits import check_spreadsheet

    path = Path(path)
    try:
        st = path.stat()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    # sizes and rows first: the reader holds a whole sheet in memory, and aborts the process when it
    # cannot (an .xlsx whose sheet inflates to 2.4 GB: a Rust out-of-memory panic)
    check_spreadsheet(path, sniff(path))
    # import_file reads a file's header, rows and extra columns in turn: one load serves them
    return _load(str(path), st.st_mtime_ns, st.st_size, sheet)


@functools.lru_cache(maxsize=2)
def _load(path: str, _mtime: int, _size: int, sheet: str | int):
    import python_calamine as pc

    try:
        wb = pc.CalamineWorkbook.from_path(path)
    except Exception as exc:  # calamine's errors (zip, xml, password, format) share no base class
        raise DataError(f"{path}: cannot read it as a spreadsheet ({type(exc).__name__}: {exc}); "
                        f"{WHAT_TO_DO}") from exc
    names = list(wb.sheet_names)
    if isinstance(sheet, int):
        if sheet >= len(names):
            raise DataError(f"{path}: no sheet with index {sheet} (0 = the first): the workbook has {len(names)} "
                            f"sheet(s), {names}; set the mapping's `sheet:` to a name or an index below {len(names)}")
        name = names[sheet]
    elif sheet in names:
        name = sheet
    else:
        raise DataError(f"{path}: no sheet named {sheet!r}; the workbook has {names} "
                        "(set the mapping's `sheet:` to one of them, or to an index, 0 = the first)")
    try:
        # from A1, so that a row's index is its number in the sheet (leading empty rows and columns
        # are skipped by the reader of the rows, not here)
        rows = wb.get_sheet_by_name(name).to_python(skip_empty_area=False)
    except Exception as exc:
        raise DataError(f"{path}: sheet {name!r}: cannot read its cells ({type(exc).__name__}: {exc})") from exc
    return name, names, tuple((i + 1, tuple(r)) for i, r in enumerate(rows))


def sheet_note(path: str | Path, sheet: str | int) -> str:
    """' (sheet NAME of [...])' for messages about a spreadsheet's columns: the wrong sheet is the
    likeliest reason a column is missing.

    Parameters
    ----------
    path : str or Path
        The spreadsheet.
    sheet : str or int
        Sheet name or index.

    Returns
    -------
    str
    """
    name, names, _ = read_sheet(path, sheet)
    return (f" (sheet {name!r} of {names}: the mapping's `sheet:` picks another)" if len(names) > 1
            else f" (sheet {name!r})")


def cell_text(cell: Cell) -> str:
    """A cell as text (for header names, key columns and messages): an integral number without
    '.0', a date-time in ISO 8601.

    Parameters
    ----------
    cell : Cell
        A typed cell.

    Returns
    -------
    str
    """
    if isinstance(cell, str):
        return cell.strip()
    if isinstance(cell, bool):
        return "TRUE" if cell else "FALSE"
    if isinstance(cell, float) and cell.is_integer():
        return str(int(cell))
    if isinstance(cell, (datetime, date, time)):
        return cell.isoformat(sep=" ") if isinstance(cell, datetime) else cell.isoformat()
    return str(cell)
