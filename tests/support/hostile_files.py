"""Hostile or oversized input files, made small and fast for the tests (issue 33, item 4):

    inflating_xlsx(path, gigabytes)   a real workbook whose sheet deflates from a few MB to GBs
    long_xlsx(path, rows)             a real workbook of that many numbered rows (1,048,576: Excel's maximum)
    long_csv(path, rows)              a measurement CSV of that many rows

The inflating sheet repeats one block of rows; each block is deflated once and its compressed
bytes repeated (a full flush between blocks resets the compressor, so every block compresses to
the same bytes), so a 2.4 GB sheet costs a 2 MB file and one CRC pass to make.
"""
from __future__ import annotations

import struct
import zipfile
import zlib
from pathlib import Path

from tests.support.spreadsheet_files import write_xlsx

HEADER = ["x", "y", "z", "ex", "ey", "ez"]
_SHEET_HEAD = (b'<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'
               b'<worksheet xmlns="http://schemas.openxmlformats.org/spreadsheetml/2006/main"><sheetData>')
_SHEET_TAIL = b"</sheetData></worksheet>"
_SHEET = "xl/worksheets/sheet1.xml"


def _row(values: list[str] | list[float], r: int | None = None) -> bytes:
    cells = "".join(f'<c t="inlineStr"><is><t>{v}</t></is></c>' if isinstance(v, str) else f"<c><v>{v}</v></c>"
                    for v in values)
    return (f'<row r="{r}">' if r is not None else "<row>").encode() + cells.encode() + b"</row>"


def _parts(tmp: Path) -> dict[str, bytes]:
    """The members of a real one-sheet workbook (openpyxl's), to keep all but the sheet."""
    small = write_xlsx(tmp, {"Messung": [HEADER]})
    with zipfile.ZipFile(small) as z:
        parts = {n: z.read(n) for n in z.namelist()}
    small.unlink()
    return parts


def _write_zip(path: Path, members: list[tuple[str, bytes, int, int]]) -> None:
    """A zip of (name, raw deflate stream, crc32, unpacked size) members, written by hand."""
    central, offset = [], 0
    with path.open("wb") as f:
        for name, data, crc, size in members:
            n = name.encode()
            head = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0x21, crc, len(data), size, len(n), 0)
            f.write(head + n + data)
            central.append(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0x21, crc, len(data), size,
                                       len(n), 0, 0, 0, 0, 0, offset) + n)
            offset += len(head) + len(n) + len(data)
        cd = b"".join(central)
        f.write(cd + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(cd), offset, 0))


def _deflate(data: bytes) -> bytes:
    c = zlib.compressobj(6, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush()


def inflating_xlsx(path: str | Path, gigabytes: float = 2.4) -> Path:
    """A valid .xlsx whose sheet unpacks to `gigabytes` GB of rows (CRC and sizes right).

    Parameters
    ----------
    path : str or Path
    gigabytes : float

    Returns
    -------
    Path
    """
    path = Path(path)
    parts = _parts(path)
    block = _row([1.5, 2.5, 3.5, 0.01, 0.02, 0.03]) * 16384  # ~1.3 MB of identical rows
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = c.compress(_SHEET_HEAD) + c.flush(zlib.Z_FULL_FLUSH)
    packed = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    assert again == packed, "a full flush must make every block compress alike"
    k = int(gigabytes * 1e9 / len(block)) + 1
    crc = zlib.crc32(_SHEET_HEAD)
    for _ in range(k):
        crc = zlib.crc32(block, crc)
    crc = zlib.crc32(_SHEET_TAIL, crc)
    data = head + packed * k + c.compress(_SHEET_TAIL) + c.flush()
    members = [(n, _deflate(b), zlib.crc32(b), len(b)) for n, b in parts.items() if n != _SHEET]
    members.append((_SHEET, data, crc, len(_SHEET_HEAD) + k * len(block) + len(_SHEET_TAIL)))
    _write_zip(path, members)
    return path


def long_xlsx(path: str | Path, rows: int = 1_048_576) -> Path:
    """A valid .xlsx of a header and `rows` - 1 numbered rows of six numbers (Excel's maximum sheet
    by default).

    Parameters
    ----------
    path : str or Path
    rows : int

    Returns
    -------
    Path
    """
    path = Path(path)
    parts = _parts(path)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for n, b in parts.items():
            if n != _SHEET:
                z.writestr(n, b)
        with z.open(_SHEET, "w", force_zip64=True) as f:
            f.write(_SHEET_HEAD + _row(HEADER, 1))
            for start in range(2, rows + 1, 50_000):
                f.write(b"".join(_row([1.5, 2.5, 3.5, 0.01, 0.02, 0.03], r)
                                 for r in range(start, min(start + 50_000, rows + 1))))
            f.write(_SHEET_TAIL)
    return path


def long_csv(path: str | Path, rows: int = 10_000_000) -> Path:
    """A measurement CSV (docs/measurement-table.md) of `rows` identical rows.

    Parameters
    ----------
    path : str or Path
    rows : int

    Returns
    -------
    Path
    """
    path = Path(path)
    line = b"0.5,0.1,0.4,1e-5,2e-5,3e-5\n"
    with path.open("wb") as f:
        f.write(b"x,y,z,ex,ey,ez\n")
        for _ in range(rows // 100_000):
            f.write(line * 100_000)
        f.write(line * (rows % 100_000))
    return path
