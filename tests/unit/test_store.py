"""Store: durability under SIGKILL, disk-full handling, outbox and resume state (real SQLite)."""
from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from dt_kernel.errors import TwinError
from dt_runtime.service.rows import CommandRow, CorrectionRow, MeasurementRow, TTestRow
from dt_runtime.service.store import Store, StoreError

ROOT = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent("""
    import sys
    from dt_runtime.service.rows import MeasurementRow, TTestRow
    from dt_runtime.service.store import Store
    s = Store(sys.argv[1], batch_rows=50, batch_ms=1e9)
    i = 0
    while True:
        for _ in range(50):
            i += 1
            s.put(MeasurementRow(float(i), 0.1, 0.2, 0.3, 1e-4, 2e-4, 3e-4, data={"i": i}))
            s.put(TTestRow(float(i), 0.5, 10, 0.6, True))
        if i % 500 == 0:
            s.outbox_add("dt/c/r/maintenance/request", {"i": i})
        print(i, flush=True)   # only after the batch above was committed
""")


def test_sigkill_mid_run_keeps_every_committed_row(tmp_path):
    db = tmp_path / "twin.db"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(db)], stdout=subprocess.PIPE,
                            text=True, env=env, cwd=ROOT)
    reported = 0
    deadline = time.monotonic() + 20
    try:
        while reported < 3000 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            reported = int(line)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert reported >= 3000, "child did not make progress"
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    ids = [r[0] for r in con.execute("SELECT CAST(t AS INTEGER) FROM measurements ORDER BY id")]
    assert len(ids) >= reported
    assert ids[:reported] == list(range(1, reported + 1))
    n_t = con.execute("SELECT COUNT(*) FROM t_stats").fetchone()[0]
    assert n_t >= reported
    assert con.execute("SELECT COUNT(*) FROM outbox").fetchone()[0] >= reported // 500
    con.close()
    with Store(db) as s:  # reopens cleanly after the crash, and keeps writing
        s.put(MeasurementRow(1e9, 0, 0, 0))
        assert s.flush() == 1
        assert s.integrity_ok()


def test_disk_full_raises_store_error_and_keeps_committed_rows(tmp_path):
    s = Store(tmp_path / "full.db", batch_rows=10_000, batch_ms=1e9)
    for i in range(100):
        s.put(CommandRow(float(i), 0.1, 0.2, 0.3, 0.25))
    assert s.flush() == 100
    oid = s.outbox_add("k", {"a": 1})
    pages = s._db.execute("PRAGMA page_count").fetchone()[0]
    s._db.execute(f"PRAGMA max_page_count={pages}")  # the "disk" is now full
    for i in range(5000):
        s.put(CommandRow(1000.0 + i, 0.1, 0.2, 0.3, 0.25, data={"pad": "x" * 200}))
    with pytest.raises(StoreError) as ei:
        s.flush()
    assert isinstance(ei.value, TwinError) and isinstance(ei.value.__cause__, sqlite3.Error)
    with pytest.raises(StoreError):
        s.outbox_add("k", {"big": "y" * 100_000})
    # Committed rows intact, the file is consistent and still readable by the same store.
    assert s.count("commands") == 100
    assert [o.id for o in s.outbox_pending()] == [oid]
    assert s.integrity_ok()
    # Space comes back: the retained buffered rows are committed on the next flush.
    s._db.execute("PRAGMA max_page_count=1073741823")
    assert s.flush() == 5000
    assert s.count("commands") == 5100
    s.close()
    con = sqlite3.connect(tmp_path / "full.db")
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()


def test_failed_flush_buffer_is_bounded(tmp_path):
    s = Store(tmp_path / "b.db", batch_rows=10_000, batch_ms=1e9, max_pending_rows=300)
    s.put(TTestRow(0.0, 1.0))
    s.flush()
    pages = s._db.execute("PRAGMA page_count").fetchone()[0]
    s._db.execute(f"PRAGMA max_page_count={pages}")
    for i in range(1000):
        s.put(TTestRow(float(i), 1.0, data={"pad": "z" * 300}))
    with pytest.raises(StoreError):
        s.flush()
    assert s.dropped_rows == 700
    assert s.count("t_stats") == 1
    s.close()  # close after a failed flush must not raise


def test_batching_commits_by_rows_and_by_time(tmp_path):
    # The batch timer runs on a clock the test moves by hand: no wall-clock time in the test, so a
    # loaded machine cannot flush early (it did: the timer started before the file was synced).
    now = [0.0]
    with Store(tmp_path / "t.db", batch_rows=10, batch_ms=50, clock=lambda: now[0]) as s:
        for i in range(9):
            s.put(MeasurementRow(float(i), 0, 0, 0))
        assert s.count("measurements") == 0  # still buffered
        s.put(MeasurementRow(9.0, 0, 0, 0))
        assert s.count("measurements") == 10  # row threshold
        s.put(MeasurementRow(10.0, 0, 0, 0))
        now[0] += 0.049
        s.put(MeasurementRow(11.0, 0, 0, 0))
        assert s.count("measurements") == 10  # 49 ms: not yet
        now[0] += 0.002
        s.put(MeasurementRow(12.0, 0, 0, 0))
        assert s.count("measurements") == 13  # time threshold
        s.put(CorrectionRow(1.0, 1e-4, 0, 0, data={"note": "extra"}))
        assert s.flush() == 1


def test_transitions_outbox_state_and_figures(tmp_path):
    path = tmp_path / "s.db"
    with Store(path, batch_ms=1e9) as s:
        s.put(MeasurementRow(1.0, 0.1, 0.2, 0.3, 1e-4, 0, 0))
        s.put(TTestRow(1.0, 2.5, 9, 0.03, False))
        # a transition commits immediately, together with the evidence rows buffered before it
        s.record_transition("nominal", "suspect", {"window_failures": 5, "cusum": 2.1}, 1.0)
        assert s.count("t_stats") == 1
        a = s.outbox_add("dt/c/r1/maintenance/request", {"uid": "u1", "x": float("nan")})
        b = s.outbox_add("dt/c/r1/maintenance/request", {"uid": "u2"})
        assert [o.id for o in s.outbox_pending()] == [a, b]
        assert s.outbox_pending()[0].payload == {"uid": "u1", "x": None}
        s.outbox_attempted(a)
        assert s.outbox_ack(a) is True
        assert s.outbox_ack(a) is False  # idempotent
        assert [o.id for o in s.outbox_pending()] == [b]
        s.save_state("escalation", {"state": "suspect", "cusum": 2.1})
        s.save_state("escalation", {"state": "out_of_control", "cusum": 4.6})
    with Store(path) as s:  # reopen: everything committed is there
        st = s.load_state()
        assert st["name"] == "escalation" and st["data"]["state"] == "out_of_control"
        assert s.count("state") == 1
        fig = s.last_figures()
        assert fig["counts"]["measurements"] == 1
        assert fig["t_tests"] == {"n": 1, "failed": 1}
        assert fig["last_transition"]["dst"] == "suspect"
        assert fig["last_transition"]["evidence"]["window_failures"] == 5
        assert fig["outbox_pending"] == 1
        assert s._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert s._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    assert Store(tmp_path / "fresh.db").load_state() is None


def test_closed_store_and_bad_path_raise_store_error(tmp_path):
    s = Store(tmp_path / "c.db")
    s.close()
    with pytest.raises(StoreError):
        s.put(TTestRow(0.0, 1.0))
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(StoreError):
        Store(tmp_path / "dir.db")
