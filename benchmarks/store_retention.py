"""Store size under the daemon's row stream, with and without retention:
`python -m benchmarks.store_retention [--json] [--hours H] [--rate HZ] [--max-age-h A]`.

Writes what `dt run` writes per tick (a command, a correction, a measurement and a t-test row,
the typed rows of `dt_runtime.service.rows`, with the t-test's JSON data) for H simulated hours at
HZ through the real `Store` (batched commits, WAL, synchronous=FULL), pruning every simulated
minute as the daemon's housekeeping does (`Store.prune(before_t=now - A)`, the `retention`
section of the runtime YAML). The baseline, in the same run, is the same stream without
retention. Keys: sim_hours, rate_hz, max_age_s, size_mb, size_mb_without_retention, ratio,
rows_kept, rows_written, seconds.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import cli, emit
from dt_runtime.service.rows import CommandRow, CorrectionRow, MeasurementRow, TTestRow
from dt_runtime.service.store import Store

PRUNE_EVERY_S = 60.0


def stream(path: Path, hours: float, rate: float, max_age_s: float | None) -> dict:
    rng = np.random.default_rng(0)
    n = int(hours * 3600 * rate)
    t0 = time.perf_counter()
    with Store(path, batch_rows=4000, batch_ms=1e9) as st:
        next_prune = PRUNE_EVERY_S
        for i in range(n):
            t = i / rate
            x, y, z = rng.uniform(-1, 1, 3)
            tv = rng.standard_normal(3)
            st.put(CommandRow(t, x, y, z, speed=0.5))
            st.put(CorrectionRow(t, 1e-4, -2e-4, 5e-5, 1e-5, 1e-5, 1e-5))
            st.put(MeasurementRow(t, x, y, z, 1e-5, 2e-5, -1e-5))
            st.put(TTestRow(t, float(tv[0]), None, 0.3, True, data={"t": tv.round(4).tolist()}))
            if max_age_s is not None and t >= next_prune:
                next_prune += PRUNE_EVERY_S
                st.flush()
                st.prune(before_t=t - max_age_s)
        st.flush()
        kept = st.count("t_stats")
        size = st.size_bytes()
    return {"size_mb": size / 1e6, "rows_kept": kept, "rows_written": n, "seconds": time.perf_counter() - t0}


def measure(hours: float, rate: float, max_age_h: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        on = stream(Path(tmp) / "retained.sqlite", hours, rate, max_age_h * 3600)
        off = stream(Path(tmp) / "all.sqlite", hours, rate, None)
    return {"sim_hours": hours, "rate_hz": rate, "max_age_s": max_age_h * 3600,
            "size_mb": round(on["size_mb"], 2), "size_mb_without_retention": round(off["size_mb"], 2),
            "ratio": round(on["size_mb"] / off["size_mb"], 4), "rows_kept": on["rows_kept"],
            "rows_written": on["rows_written"], "seconds": round(on["seconds"], 1),
            "seconds_without_retention": round(off["seconds"], 1)}


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__, argv, hours=24.0, rate=10.0, max_age_h=1.0)
    emit(measure(a.hours, a.rate, a.max_age_h), a.json, "store retention (per-tick rows of dt run)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
