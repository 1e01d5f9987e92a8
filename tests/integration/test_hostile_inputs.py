"""Hostile or oversized input files are refused in bounded memory with a named cause, never a
traceback or a panic (issue 33, item 4): an .xlsx whose sheet inflates to 2.4 GB (was a Rust
out-of-memory abort, exit 134 at 2.2 GB), a full 1,048,576-row sheet (was 327 s and 1.13 GB), a
10^7-row CSV (was no answer in 300 s, memory growing 10 MB/s). Each runs `dt fit` in a child of
a small wrapper process that reports the child's peak memory (ru_maxrss); no timing is asserted."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.support.hostile_files import HEADER, inflating_xlsx, long_csv, long_xlsx

ROOT = Path(__file__).resolve().parents[2]
GB_KIB = 1024 * 1024  # ru_maxrss is in KiB on Linux
_WRAPPER = """
import json, resource, subprocess, sys
r = subprocess.run(sys.argv[1:], capture_output=True, text=True)
print(json.dumps({"rc": r.returncode, "out": r.stdout, "err": r.stderr,
                  "maxrss_kib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
"""


def _dt_measured(*args: str, env: dict | None = None) -> dict:
    cmd = [sys.executable, "-c", _WRAPPER, sys.executable, "-m", "dt_runtime.cli", *args]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, check=True)
    return json.loads(r.stdout)


def _mapping(tmp_path: Path) -> Path:
    m = tmp_path / "mapping.yaml"
    m.write_text(yaml.safe_dump({"sheet": "Messung", "columns": dict(zip(HEADER, HEADER))}))
    return m


def _refused(res: dict, *words: str) -> str:
    err = res["err"]
    assert res["rc"] == 2, err[-2000:]
    assert "Traceback" not in err and "panicked" not in err
    for w in words:
        assert w in err, err
    assert res["maxrss_kib"] < GB_KIB, res["maxrss_kib"]
    return err


def test_an_xlsx_whose_sheet_inflates_to_2_4_gb_is_refused_by_its_unpacked_size(tmp_path):
    bomb = inflating_xlsx(tmp_path / "bomb.xlsx", 2.4)
    assert bomb.stat().st_size < 20_000_000  # a small file ...
    res = _dt_measured("fit", "--data", str(bomb), "--mapping", str(_mapping(tmp_path)), "--out", str(tmp_path / "m"))
    err = _refused(res, "unpacks to 2,400 MB", "DT_MAX_SHEET_MB", "more than the limit of 256 MB")
    assert "xl/worksheets/sheet1.xml" in err
    assert not (tmp_path / "m").exists()


def test_a_full_1048576_row_sheet_is_refused_by_the_row_limit(tmp_path):
    big = long_xlsx(tmp_path / "long.xlsx", 1_048_576)
    res = _dt_measured("fit", "--data", str(big), "--mapping", str(_mapping(tmp_path)), "--out", str(tmp_path / "m"))
    _refused(res, "rows, over the limit of 200,000 rows (DT_MAX_ROWS)", "DT_MAX_ROWS=")


def test_a_10_million_row_csv_is_refused_by_the_row_limit(tmp_path):
    big = long_csv(tmp_path / "long.csv", 10_000_000)
    res = _dt_measured("fit", "--data", str(big), "--out", str(tmp_path / "m"))
    _refused(res, "rows, over the limit of 200,000 rows (DT_MAX_ROWS)", "DT_MAX_ROWS=")


@pytest.mark.parametrize("limit", ["0", "many"])
def test_a_bad_limit_in_the_environment_is_named(tmp_path, limit):
    import os

    small = long_csv(tmp_path / "s.csv", 20)
    res = _dt_measured("fit", "--data", str(small), "--out", str(tmp_path / "m"), env={**os.environ,
                                                                                       "DT_MAX_ROWS": limit})
    _refused(res, "DT_MAX_ROWS", "a whole number >= 1")
