"""The size limits of input tables (measurements.limits): counted cheaply before parsing, each
named with how to raise it; a zip member that unpacks to more than it declares is refused as
damaged; a stray cell far to the right is refused by the column limit; a normal workbook and CSV
pass and read as before."""
from __future__ import annotations

import zlib

import pytest

from dt_kernel.errors import DataError
from dt_runtime.measurements import limits
from dt_runtime.measurements.sheets import read_sheet
from tests.support import hostile_files as hf
from tests.support.spreadsheet_files import write_ods, write_xlsx


@pytest.fixture(autouse=True)
def _fresh_cache():
    limits._text_rows.cache_clear()
    limits._spreadsheet.cache_clear()


def test_a_csv_over_the_row_limit_is_refused_and_the_variable_raises_it(tmp_path, monkeypatch):
    p = hf.long_csv(tmp_path / "m.csv", 50)
    limits.check_text_rows(p)
    monkeypatch.setenv("DT_MAX_ROWS", "20")
    with pytest.raises(DataError, match=r"at least \d+ rows, over the limit of 20 rows \(DT_MAX_ROWS\).*DT_MAX_ROWS="):
        limits.check_text_rows(p)
    monkeypatch.setenv("DT_MAX_ROWS", "60")
    limits.check_text_rows(p)


def test_a_workbook_within_the_limits_reads_as_before(tmp_path):
    p = write_xlsx(tmp_path / "m.xlsx", {"Messung": [hf.HEADER, *[[1.0, 2.0, 3.0, 0.1, 0.2, 0.3]] * 30]})
    name, _, rows = read_sheet(p, 0)
    assert name == "Messung" and len(rows) == 31


def test_the_row_limit_counts_a_sheets_rows_and_their_numbers(tmp_path, monkeypatch):
    p = hf.long_xlsx(tmp_path / "m.xlsx", 500)
    monkeypatch.setenv("DT_MAX_ROWS", "100")
    with pytest.raises(DataError, match=r"sheet1.xml has (at least )?4\d\d rows, over the limit of 100 rows"):
        read_sheet(p, 0)
    monkeypatch.setenv("DT_MAX_ROWS", "1000")
    assert len(read_sheet(p, 0)[2]) == 500


def test_one_cell_far_down_or_far_right_is_refused_before_the_reader_makes_the_sheet_that_big(tmp_path):
    parts = hf._parts(tmp_path / "x.xlsx")
    for body, what in ((b'<row r="1"><c r="A1"><v>1</v></c></row><row r="1000000"><c r="A1000000"><v>1</v></c></row>',
                        r"has 1,000,000 rows"),
                       (b'<row r="1"><c r="A1"><v>1</v></c><c r="XFD1"><v>1</v></c></row>',
                        r"spans 16,384 columns, more than the limit of 1,000 \(DT_MAX_COLUMNS\)")):
        sheet = hf._SHEET_HEAD + body + hf._SHEET_TAIL
        members = [(n, hf._deflate(b), zlib.crc32(b), len(b)) for n, b in parts.items() if n != hf._SHEET]
        members.append((hf._SHEET, hf._deflate(sheet), zlib.crc32(sheet), len(sheet)))
        p = tmp_path / "stray.xlsx"
        hf._write_zip(p, members)
        limits._spreadsheet.cache_clear()
        with pytest.raises(DataError, match=what):
            read_sheet(p, 0)


def test_a_member_that_unpacks_to_more_than_it_declares_is_refused_as_damaged(tmp_path):
    parts = hf._parts(tmp_path / "x.xlsx")
    sheet = hf._SHEET_HEAD + hf._row(hf.HEADER, 1) + hf._row([1.0] * 6) * 20000 + hf._SHEET_TAIL
    members = [(n, hf._deflate(b), zlib.crc32(b), len(b)) for n, b in parts.items() if n != hf._SHEET]
    members.append((hf._SHEET, hf._deflate(sheet), zlib.crc32(sheet), 4096))  # declares 4 kB
    p = tmp_path / "lying.xlsx"
    hf._write_zip(p, members)
    with pytest.raises(DataError, match="damaged spreadsheet"):
        read_sheet(p, 0)


def test_an_ods_counts_its_repeated_rows(tmp_path, monkeypatch):
    p = write_ods(tmp_path / "m.ods", {"Messung": [hf.HEADER, *[[1.0, 2.0, 3.0, 0.1, 0.2, 0.3]] * 30]})
    monkeypatch.setenv("DT_MAX_ROWS", "10")
    with pytest.raises(DataError, match="over the limit of 10 rows"):
        read_sheet(p, 0)
