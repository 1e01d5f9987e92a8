"""The contract measurement table: write/read round trip, ex vs mx, bad rows."""
import math

import numpy as np
import pytest

from dt_runtime.measurements.dataset import Dataset, concat, read_table, write_table
from dt_kernel.errors import DataError


def _dataset(n=7, seed=0, measured=True):
    rng = np.random.default_rng(seed)
    cmd = rng.uniform(-0.8, 0.8, (n, 3))
    meas = cmd - rng.normal(0, 3e-4, (n, 3))
    temp = rng.uniform(20, 25, n)
    temp[2] = np.nan  # an empty cell in an optional column
    kw = dict(speed=rng.uniform(0.1, 1.0, n), joints=rng.uniform(-3, 3, (n, 6)), temperature=temp,
              payload=np.full(n, 2.5), t=np.cumsum(rng.uniform(0, 5, n)),
              point_id=np.arange(n) % 3, rep=np.arange(n) // 3, u=np.full((n, 3), 1e-5))
    if measured:
        return Dataset.from_measured(cmd, meas, **kw)
    return Dataset(commanded=cmd, error=cmd - meas, **kw)


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_round_trip_all_columns(tmp_path):
    ds = _dataset()
    p = write_table(ds, tmp_path / "m.csv")
    header = p.read_text().splitlines()[0].split(",")
    assert header == ["x", "y", "z", "speed", "q1", "q2", "q3", "q4", "q5", "q6", "temperature",
                      "payload", "t", "point_id", "rep", "ex", "ey", "ez", "mx", "my", "mz", "ux", "uy", "uz"]
    back = read_table(p)
    assert back.n == ds.n and back.skipped == []
    for f in ("commanded", "error", "measured", "speed", "joints", "payload", "t", "u"):
        np.testing.assert_allclose(getattr(back, f), getattr(ds, f), rtol=1e-12, atol=1e-15, err_msg=f)
    np.testing.assert_array_equal(back.point_id, ds.point_id)
    np.testing.assert_array_equal(back.rep, ds.rep)
    assert math.isnan(back.temperature[2])
    np.testing.assert_allclose(np.delete(back.temperature, 2), np.delete(ds.temperature, 2))
    # file holds mm and mm/s
    row1 = dict(zip(header, p.read_text().splitlines()[1].split(",")))
    assert float(row1["x"]) == pytest.approx(ds.commanded[0, 0] * 1e3)
    assert float(row1["speed"]) == pytest.approx(ds.speed[0] * 1e3)
    assert list(back.lines) == list(range(2, ds.n + 2))


def test_minimal_table_and_select_concat(tmp_path):
    ds = Dataset(commanded=np.zeros((2, 3)), error=np.full((2, 3), 1e-3))
    back = read_table(write_table(ds, tmp_path / "min.csv"))
    assert back.columns() == ["x", "y", "z", "ex", "ey", "ez"]
    assert back.measured is None and back.joints is None and back.t is None
    np.testing.assert_allclose(back.actual, -1e-3)
    both = concat([back, back.select([1])])
    assert both.n == 3 and both.lines.tolist() == [2, 3, 3]


def test_ex_versus_mx_columns(tmp_path):
    # measured only: error = commanded - measured (Eq. 8 sign)
    p = _write(tmp_path, "m.csv", "x,y,z,mx,my,mz\n100,200,300,100.5,199,300\n")
    ds = read_table(p)
    np.testing.assert_allclose(ds.error, [[-0.5e-3, 1e-3, 0.0]], atol=1e-15)
    np.testing.assert_allclose(ds.measured, [[0.1005, 0.199, 0.3]])
    # error only: taken as is, no measured
    ds = read_table(_write(tmp_path, "e.csv", "x,y,z,ex,ey,ez\n100,200,300,-0.5,1,0\n"))
    assert ds.measured is None
    np.testing.assert_allclose(ds.error, [[-0.5e-3, 1e-3, 0.0]])
    # both, consistent: accepted; inconsistent: the row is bad
    read_table(_write(tmp_path, "b.csv", "x,y,z,ex,ey,ez,mx,my,mz\n100,200,300,-0.5,1,0,100.5,199,300\n"))
    with pytest.raises(DataError, match=r"line 2: column 'ex'.*disagrees"):
        read_table(_write(tmp_path, "c.csv", "x,y,z,ex,ey,ez,mx,my,mz\n100,200,300,0.5,1,0,100.5,199,300\n"))
    with pytest.raises(DataError, match="ex, ey, ez or mx, my, mz"):
        read_table(_write(tmp_path, "n.csv", "x,y,z\n1,2,3\n"))
    with pytest.raises(DataError, match="incomplete"):
        read_table(_write(tmp_path, "i.csv", "x,y,z,ex,ey\n1,2,3,4,5\n"))


def test_bad_row_message_names_file_line_column_value(tmp_path):
    p = _write(tmp_path, "bad_table.csv", "x,y,z,ex,ey,ez\n1,2,3,0,0,0\n1,abc,3,0,0,0\n")
    with pytest.raises(DataError) as exc:
        read_table(p)
    msg = str(exc.value)
    assert "bad_table.csv" in msg and "line 3" in msg and "column 'y'" in msg and "'abc'" in msg


def test_skip_bad_lists_every_skipped_row(tmp_path):
    text = ("x,y,z,t,point_id,ex,ey,ez\n"
            "1,2,3,0.0,0,0,0,0\n"          # line 2 ok
            "1,2,,1.0,0,0,0,0\n"           # line 3 empty required cell
            "1,2,3,2.0,1.5,0,0,0\n"        # line 4 non-integer id
            "1,2,3,3.0,1,0,0\n"            # line 5 ragged row
            "1,2,3,-0.5,1,0,0,0\n"         # line 6 time goes backwards
            "\n"                           # line 7 blank: not a row
            "4,5,6,4.0,2,nan,0,0\n"        # line 8 non-finite error
            "4,5,6,5.0,2,0.1,0.2,0.3\n")   # line 9 ok
    p = _write(tmp_path, "s.csv", text)
    with pytest.raises(DataError, match="line 3: column 'z'"):
        read_table(p)
    ds = read_table(p, skip_bad=True)
    assert ds.n == 2 and ds.lines.tolist() == [2, 9]
    assert [(s.line, s.column) for s in ds.skipped] == [(3, "z"), (4, "point_id"), (5, "<row>"), (6, "t"), (8, "ex")]
    assert ds.skipped[1].value == "1.5" and "integer" in ds.skipped[1].reason
    assert "decreases" in ds.skipped[3].reason
    np.testing.assert_allclose(ds.error[1], [1e-4, 2e-4, 3e-4])


def test_write_refuses_decreasing_time_and_bad_shapes(tmp_path):
    ds = _dataset()
    ds.t[3] = -1.0
    with pytest.raises(DataError, match="'t' decreases"):
        write_table(ds, tmp_path / "x.csv")
    with pytest.raises(DataError, match="error"):
        Dataset(commanded=np.zeros((3, 3)), error=np.zeros((2, 3)))
    with pytest.raises(DataError, match="missing|cannot read"):
        read_table(tmp_path / "nope.csv")
