"""Spreadsheets read as they are (issue 21, part 6): a measurement file and a joint-angle table as
.xlsx (written by openpyxl) or .ods (written by odfpy), read through an import mapping into the
same numbers as the CSV of the same data; the sheet chosen by name or index; date-time cells as
timestamps; and any other binary file refused with what it looks like, never with advice about a
text encoding."""
from __future__ import annotations

import zipfile
from datetime import datetime, timedelta

import numpy as np
import pytest

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import read_table
from dt_runtime.measurements.importer import ImportMapping, import_file, load_mapping
from tests.support.spreadsheet_files import write_ods, write_xlsx
from tests.support.ur10_generator import fk

UR10 = CONFIGS / "robots" / "ur10.yaml"
HEADER = ["Zeit", "X", "Y", "Z", "dX", "dY", "dZ", "Punkt", "Bemerkung"]
T0 = datetime(2024, 3, 1, 9, 59, 58)


def _rows(n: int = 8, seed: int = 2):
    """n rows (mm; error in mm; a timestamp every 7.25 s) as typed cells, and the truth (m, s)."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-900, 900, (n, 3)).round(4)
    err = rng.normal(0, 0.05, (n, 3)).round(6)
    t = np.arange(n) * 7.25
    rows = [[T0 + timedelta(seconds=float(s)), *p, *e, i + 1, "ok" if i % 2 else "nachgemessen"]
            for i, (s, p, e) in enumerate(zip(t, xyz, err))]
    return rows, xyz * 1e-3, err * 1e-3, t


MAPPING = {"columns": {"x": "X", "y": "Y", "z": "Z", "ex": "dX", "ey": "dY", "ez": "dZ", "point_id": "Punkt"},
           "time": {"source": "timestamp", "column": "Zeit"}}


@pytest.mark.parametrize("writer,suffix", [(write_xlsx, "xlsx"), (write_ods, "ods")])
def test_a_spreadsheet_reads_to_the_numbers_it_holds(tmp_path, writer, suffix):
    rows, xyz, err, t = _rows()
    p = writer(tmp_path / f"m.{suffix}", {"Messung": [HEADER, *rows]})
    ds, rep = import_file(p, ImportMapping.model_validate(MAPPING))
    np.testing.assert_allclose(ds.commanded, xyz, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ds.error, err, rtol=0, atol=1e-15)
    # date-time cells are timestamps as they are: seconds from the earliest row, no format needed
    np.testing.assert_allclose(ds.t, t, atol=1e-6)
    assert ds.point_id.tolist() == list(range(1, 9))
    assert ds.lines.tolist() == list(range(2, 10))  # the sheet's row numbers (header in row 1)
    assert "Bemerkung" not in ds.extra  # text: left out, and said
    assert any("non-numeric column(s) left out" in n and "Bemerkung" in n for n in rep.notes)


def test_the_same_data_as_csv_with_decimal_commas_gives_the_same_dataset(tmp_path):
    rows, *_ = _rows()
    xl = write_xlsx(tmp_path / "m.xlsx", {"Messung": [HEADER, *rows]})
    csv_rows = [[r[0].strftime("%d.%m.%Y %H:%M:%S.%f")] + [repr(float(v)).replace(".", ",") for v in r[1:7]]
                + [str(r[7]), r[8]] for r in rows]
    (tmp_path / "m.csv").write_text(";".join(HEADER) + "\n" + "\n".join(";".join(r) for r in csv_rows) + "\n",
                                    encoding="utf-8")
    a, _ = import_file(xl, ImportMapping.model_validate(MAPPING))
    csv_map = MAPPING | {"separator": ";", "decimal": ",",
                         "time": {"source": "timestamp", "column": "Zeit", "format": "%d.%m.%Y %H:%M:%S.%f"}}
    b, _ = import_file(tmp_path / "m.csv", ImportMapping.model_validate(csv_map))
    for f in ("commanded", "error", "t", "point_id"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_the_sheet_is_chosen_by_name_or_index_and_a_wrong_one_names_the_sheets(tmp_path):
    rows, xyz, *_ = _rows()
    other = [["Notiz"], ["Kalibrierung am Montag"]]
    p = write_xlsx(tmp_path / "m.xlsx", {"Deckblatt": other, "Messung": [HEADER, *rows]})
    for sheet in ("Messung", 1):
        ds, _ = import_file(p, ImportMapping.model_validate(MAPPING | {"sheet": sheet}))
        np.testing.assert_allclose(ds.commanded, xyz, atol=1e-15)
    # the first sheet is the default: the message names it and the workbook's sheets
    with pytest.raises(DataError, match=r"not in the header \[.Notiz.\] \(sheet .Deckblatt. of "
                                        r"\[.Deckblatt., .Messung.\]: the mapping.s `sheet:` picks another\)"):
        import_file(p, ImportMapping.model_validate(MAPPING))
    with pytest.raises(DataError, match=r"no sheet named 'Daten'; the workbook has \['Deckblatt', 'Messung'\]"):
        import_file(p, ImportMapping.model_validate(MAPPING | {"sheet": "Daten"}))
    with pytest.raises(DataError, match=r"no sheet with index 2 .* 2 sheet\(s\)"):
        import_file(p, ImportMapping.model_validate(MAPPING | {"sheet": 2}))
    (tmp_path / "bad.yaml").write_text("sheet: -1\ncolumns: {x: X, y: Y, z: Z, ex: dX, ey: dY, ez: dZ}\n")
    with pytest.raises(ConfigError, match="sheet"):
        load_mapping(tmp_path / "bad.yaml")


def test_a_table_off_the_corner_keeps_its_row_numbers_and_a_bad_cell_is_named(tmp_path):
    rows, xyz, *_ = _rows()
    rows[3][2] = "n/a"  # Y of data row 4: text where a number belongs
    rows[5][4] = "0,125"  # a number typed as text with a decimal comma (the mapping's `decimal`)
    blank = [None] * (len(HEADER) + 2)
    sheet = [blank, blank, [None, None, *HEADER]] + [[None, None, *r] for r in rows]  # header in C3
    p = write_xlsx(tmp_path / "m.xlsx", {"Messung": sheet})
    m = ImportMapping.model_validate(MAPPING | {"decimal": ","})
    with pytest.raises(DataError, match=r"m.xlsx: line 7: column 'Y': value 'n/a': not a number"):
        import_file(p, m)
    ds, _ = import_file(p, m, skip_bad=True)
    assert ds.n == 7 and [s.line for s in ds.skipped] == [7]
    assert ds.lines.tolist() == [4, 5, 6, 8, 9, 10, 11]
    assert ds.error[4, 0] == pytest.approx(0.125e-3, abs=1e-15)


def test_a_number_in_a_timestamp_column_reads_as_its_digits(tmp_path):
    rows, *_ = _rows()
    for i, r in enumerate(rows):  # what a spreadsheet makes of YYYYmmddHHMMSS: a number
        r[0] = int((T0 + timedelta(seconds=10 * i)).strftime("%Y%m%d%H%M%S"))
    p = write_xlsx(tmp_path / "m.xlsx", {"Messung": [HEADER, *rows]})
    ds, _ = import_file(p, ImportMapping.model_validate(MAPPING))
    np.testing.assert_allclose(ds.t, 10.0 * np.arange(8))


def test_a_joint_table_in_a_spreadsheet_is_joined_by_key(tmp_path):
    rng = np.random.default_rng(5)
    q_deg = np.round(rng.uniform(-120, 120, (10, 6)), 4)
    err = rng.normal(0, 2e-4, (10, 3))
    meas = fk(np.deg2rad(q_deg)) - err
    (tmp_path / "p.csv").write_text("id;mx;my;mz\n" + "\n".join(
        f"{i + 1};" + ";".join(f"{v * 1e3:.6f}" for v in m) for i, m in enumerate(meas)) + "\n", encoding="utf-8")
    order = rng.permutation(10)
    cols = [f"Achse {j} [°]" for j in range(1, 7)]
    write_xlsx(tmp_path / "p_joints.xlsx", {"Info": [["Roboter", "UR10"]],
                                            "Achsen": [["Punkt", *cols]] + [[int(i + 1), *q_deg[i]] for i in order]})
    m = ImportMapping.model_validate({
        "separator": ";", "columns": {"mx": "mx", "my": "my", "mz": "mz"},
        "joints": {"path": "{stem}_joints.xlsx", "sheet": "Achsen", "columns": cols, "unit": "deg",
                   "join": {"key": "id", "joints_key": "Punkt"}}})
    ds, _ = import_file(tmp_path / "p.csv", m, robot=UR10)
    np.testing.assert_allclose(ds.joints, np.deg2rad(q_deg), atol=1e-12)
    np.testing.assert_allclose(ds.error, err, atol=1e-9)


def test_an_ods_measurement_file_joins_an_xlsx_joint_table_by_row_order(tmp_path):
    rng = np.random.default_rng(6)
    q_deg = np.round(rng.uniform(-120, 120, (9, 6)), 4)
    err = rng.normal(0, 2e-4, (9, 3))
    meas = (fk(np.deg2rad(q_deg)) - err) * 1e3
    blank = [None] * 4
    # a blank row inside each table: it carries no row, in either file, so row i still pairs with row i
    write_ods(tmp_path / "p.ods", {"Punkte": [["mx", "my", "mz", "Luftfeuchte"]] + [[*m, 40.0 + i] for i, m in
                                                                                   enumerate(meas[:4])]
                                   + [blank] + [[*m, 44.0 + i] for i, m in enumerate(meas[4:])]})
    write_xlsx(tmp_path / "p_joints.xlsx", {"Achsen": [[f"A{j}" for j in range(1, 7)], [None] * 6]
                                            + [list(map(float, q)) for q in q_deg]})
    m = ImportMapping.model_validate({"columns": {"mx": "mx", "my": "my", "mz": "mz"},
                                      "joints": {"path": "{stem}_joints.xlsx", "columns": [f"A{j}" for j in range(1, 7)],
                                                 "unit": "deg", "join": "row"}})
    ds, _ = import_file(tmp_path / "p.ods", m, robot=UR10)
    np.testing.assert_allclose(ds.joints, np.deg2rad(q_deg), atol=1e-12)
    np.testing.assert_allclose(ds.error, err, atol=1e-9)
    np.testing.assert_array_equal(ds.extra["Luftfeuchte"], 40.0 + np.arange(9))
    assert ds.lines.tolist() == [2, 3, 4, 5, 7, 8, 9, 10, 11]


def _binary_files(tmp_path):
    text = "x,y,z,ex,ey,ez\n1,2,3,0.1,0.2,0.3\n"
    files = {
        "report.pdf": (b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n1 0 obj\n", "a PDF document"),
        "points.parquet": (b"PAR1\x15\x04\x15\x10", "a Parquet file"),
        "photo.png": (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "a PNG image"),
        "export.csv": (text.encode("utf-16-le"), "UTF-16 text without a byte-order mark (little-endian)"),
        "unicode.txt": (b"\xff\xfe" + text.encode("utf-16-le"), "UTF-16 text with a byte-order mark"),
        "blob.bin": (b"\x01\x02\x00\x00\x07binary\x00stuff", "a binary file"),
    }
    out = {}
    for name, (data, what) in files.items():
        (tmp_path / name).write_bytes(data)
        out[name] = what
    with zipfile.ZipFile(tmp_path / "campaign.zip", "w") as z:
        z.writestr("day1/points.csv", text)
    out["campaign.zip"] = "a zip archive (holding day1/points.csv)"
    return out


def test_other_binary_files_are_named_for_what_they_look_like_never_latin1(tmp_path):
    m = ImportMapping.model_validate({"columns": {"x": "x", "y": "y", "z": "z", "ex": "ex", "ey": "ey", "ez": "ez"}})
    for name, what in _binary_files(tmp_path).items():
        for read in (lambda p: import_file(p, m), read_table):
            with pytest.raises(DataError) as e:
                read(tmp_path / name)
            msg = str(e.value)
            assert msg.startswith(str(tmp_path / name)) and f"it looks like {what}" in msg, msg
            assert "latin-1" not in msg
    # the advice for UTF-16 works: the mapping's encoding reads the file
    for name, enc in (("unicode.txt", "utf-16"), ("export.csv", "utf-16-le")):
        ds, _ = import_file(tmp_path / name, m.model_copy(update={"encoding": enc}))
        assert ds.n == 1 and ds.error[0, 2] == pytest.approx(0.3e-3)


def test_a_contract_table_as_a_spreadsheet_is_pointed_at_the_mapping(tmp_path):
    p = write_xlsx(tmp_path / "t.xlsx", {"Tabelle1": [["x", "y", "z", "ex", "ey", "ez"], [1, 2, 3, 0.1, 0.2, 0.3]]})
    with pytest.raises(DataError, match=r"t.xlsx: an Excel workbook, and this input is read as CSV text: .*`sheet:`"):
        read_table(p)
    # a workbook named .csv is still a workbook: told by its bytes, read by a mapping
    p.rename(tmp_path / "t.csv")
    m = ImportMapping.model_validate({"columns": {"x": "x", "y": "y", "z": "z", "ex": "ex", "ey": "ey", "ez": "ez"}})
    ds, _ = import_file(tmp_path / "t.csv", m)
    assert ds.error[0, 1] == pytest.approx(0.2e-3)
