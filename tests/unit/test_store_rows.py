"""The store's one write path: typed rows through one queue, committed by the caller's batch
triggers or by the writer thread (real SQLite; no test depends on timing)."""
from __future__ import annotations

import sqlite3
import time

import numpy as np
import pytest

from dt_runtime.service.rows import ROW_TYPES, CommandRow, CorrectionRow, MeasurementRow, TTestRow
from dt_runtime.service.store import Store, StoreError


def wait_until(pred, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and not pred():
        time.sleep(0.01)
    return pred()


def test_rows_are_frozen_and_carry_their_table_and_columns():
    r = TTestRow(1.0, np.float64(2.5), None, 0.03, False, data={"t": [2.5, float("nan"), 0.1]})
    with pytest.raises(AttributeError):
        r.t = 2.0  # type: ignore[misc]
    assert r.TABLE == "t_stats" and r.columns() == ("t", "t_value", "dof", "p_value", "passed", "data")
    assert r.values() == (1.0, 2.5, None, 0.03, 0, '{"t":[2.5,null,0.1]}')
    assert set(ROW_TYPES) == {"commands", "corrections", "measurements", "t_stats"}
    assert CorrectionRow.from_mapping({"t": 1.0, "dx": 1e-4, "note": "x"}).data == {"note": "x"}


def test_background_writer_commits_typed_rows_without_the_caller_flushing(tmp_path):
    path = tmp_path / "bg.db"
    s = Store(path, batch_ms=20, background=True)
    p = np.array([0.9, 0.0, 0.55])
    for i in range(50):
        s.put(CommandRow(float(i), *p, speed=0.4))
        s.put(CorrectionRow(float(i), *(p * 1e-3), 1e-5, 1e-5, 2e-5))
        s.put(MeasurementRow(float(i), *p, 1e-4, 0.0, -1e-4))
        s.put(TTestRow(float(i), 0.5, None, 0.6, True, data={"t": [0.5, 0.1, -0.2]}))
    assert wait_until(lambda: s.count("t_stats") == 50, 10)  # committed by the writer thread
    s.put(CommandRow(50.0, *p))
    s.close()  # stops the writer, commits what is queued
    con = sqlite3.connect(path)
    assert con.execute("SELECT COUNT(*) FROM commands").fetchone()[0] == 51
    assert con.execute("SELECT x, speed FROM commands WHERE t = 3").fetchone() == (0.9, 0.4)
    assert con.execute("SELECT ux, uz FROM corrections WHERE t = 3").fetchone() == (1e-5, 2e-5)
    assert con.execute("SELECT passed, data FROM t_stats WHERE t = 7").fetchone() == (1, '{"t":[0.5,0.1,-0.2]}')
    con.close()


def test_background_store_never_commits_on_the_callers_thread(tmp_path):
    s = Store(tmp_path / "q.db", batch_rows=1, batch_ms=1e9, background=True)  # writer never wakes
    for i in range(10):
        s.put(MeasurementRow(float(i), 0.1, 0.2, 0.3))
    assert s.count("measurements") == 0 and s.last_figures()["buffered_rows"] == 10
    # an immediate write commits the queued evidence with it, in one transaction
    s.record_transition("nominal", "suspect", {"window_failures": 5}, 9.0)
    assert s.count("measurements") == 10 and s.last_figures()["buffered_rows"] == 0
    s.close()
    with pytest.raises(StoreError):
        s.put(MeasurementRow(0.0, 0, 0, 0))


def test_put_is_the_one_way_rows_are_written(tmp_path):
    """Typed rows through put, committed by flush; the store has no other writer of rows."""
    from dt_runtime.service.rows import TTestRow
    from dt_runtime.service.store import Store as S

    with S(tmp_path / "w.db", batch_ms=1e9) as s:
        s.put(CommandRow(1.0, 0.1, 0.2, 0.3))
        s.put(TTestRow(1.0, 2.0))
        assert s.flush() == 2
        assert (s.count("commands"), s.count("t_stats")) == (1, 1)
    assert not [n for n in dir(S) if n.startswith("log_") or n == "write_batch"]

def test_the_high_rate_schema_is_the_row_types_and_a_newer_store_is_refused(tmp_path):
    path = tmp_path / "v.db"
    with Store(path) as s:
        for table, cls in ROW_TYPES.items():
            cols = [r[1] for r in s._query(f"PRAGMA table_info({table})")]
            assert cols == ["id", *cls.columns()]
    db = sqlite3.connect(path)
    db.execute("PRAGMA user_version=99")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="schema version 99 is newer"):
        Store(path)
