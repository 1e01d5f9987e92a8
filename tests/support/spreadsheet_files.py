"""Real spreadsheets for the tests, written by the libraries a user's tools resemble: openpyxl
(.xlsx, as Excel saves it: numbers as numbers, date-times as date-formatted serials) and odfpy
(.ods, LibreOffice's format). Both are in the project's test extra.

    write_xlsx(path, {"Messung": [header, row, row, ...], "Notizen": [...]})
    write_ods(path, {"Messung": [...]})

A cell is a number, a str, a datetime, or None (empty); a row of None is an empty row.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

Rows = Sequence[Sequence[Any]]


def write_xlsx(path: str | Path, sheets: Mapping[str, Rows]) -> Path:
    from openpyxl import Workbook

    path = Path(path)
    wb = Workbook()
    wb.remove(wb.active)
    for name, rows in sheets.items():
        ws = wb.create_sheet(name)
        for r, row in enumerate(rows, start=1):
            for c, v in enumerate(row, start=1):
                if v is not None:
                    cell = ws.cell(row=r, column=c, value=v)
                    if isinstance(v, datetime):
                        cell.number_format = "yyyy-mm-dd hh:mm:ss"
    wb.save(path)
    return path


def write_ods(path: str | Path, sheets: Mapping[str, Rows]) -> Path:
    from odf.opendocument import OpenDocumentSpreadsheet
    from odf.table import Table, TableCell, TableRow
    from odf.text import P

    path = Path(path)
    doc = OpenDocumentSpreadsheet()
    for name, rows in sheets.items():
        table = Table(name=name)
        for row in rows:
            tr = TableRow()
            for v in row:
                if v is None:
                    cell = TableCell()
                elif isinstance(v, datetime):
                    cell = TableCell(valuetype="date", datevalue=v.isoformat())
                    cell.addElement(P(text=v.isoformat(sep=" ")))
                elif isinstance(v, (int, float)):
                    cell = TableCell(valuetype="float", value=v)
                    cell.addElement(P(text=str(v)))
                else:
                    cell = TableCell(valuetype="string")
                    cell.addElement(P(text=str(v)))
                tr.addElement(cell)
            table.addElement(tr)
        doc.spreadsheet.addElement(table)
    doc.save(str(path))
    return path
