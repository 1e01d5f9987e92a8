"""`python -m benchmarks.stream_load [--json] [--passes 10] [--hogs 4] [--rate 125] [--twin DIR/model]`:
a streamed path on a loaded host without real-time privileges (docs/streaming.md, "Under load").

`--hogs` busy loops (`while 1: pass`, nice 0) run beside the benchmark; `--passes` passes of
benchmarks.stream's path at 250 mm/s (the S-curve), corrected by the quick demo's twin in the loop,
each in a `StreamProcess` with `rt_priority` 0, through the UR driver over RTDE to the emulator
(the controller: another machine with a real-time kernel on a real cell, so its threads keep
SCHED_FIFO when the user may have it, as in benchmarks.stream). The parent sends the heartbeat
every 20 ms, as the daemon does while it monitors a pass.

Keys: `passes` (run), `completed` (every set-point passed), `degraded` (completed with the path
waiting or set-points skipped), `stopped` (ended early; `host_stalled` of them by a host stall the
report names), `causes` (the reports' `degraded` and `stopped`, distinct), per pass `reports`
(n_sent, n_planned, pauses, pause_max_ms, skipped, lateness_p99_ms, lateness_max_ms,
jitter_p99_ms, overruns, correction_us_p99, host_gap_max_ms, stopped, degraded), `lateness_ms`
{p99_worst_pass, max} (send minus the schedule; a tick later than 2 periods is a wait instead),
`pause_max_ms` (the longest wait), `host_gap_max_ms` (the longest silence of the parent seen),
`emulator` (servo, late and skipped cycles, watchdog and host stops,
realtime), `watchdog_s` (the UR driver's default), `host_timeout_s` (dt run's default), `load`
{start, end} (1-min averages), `cores`, `rate_hz`, `hogs`, `seconds`.
"""
from __future__ import annotations

import contextlib
import functools
import io
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import cli
from benchmarks.stream import GAIN, LOOKAHEAD_S, _first_command, _path, _UrCell

SPEED = 250.0  # mm/s


def _pass(cell: _UrCell, twin_dir: str, sp, rate: float, host_timeout_s: float):
    from dt_runtime.service.path_run import path_corrector
    from dt_runtime.service.stream import StreamProcess

    start = _first_command(twin_dir, sp, sp.p, True)
    proc = StreamProcess(functools.partial(path_corrector, twin_dir, sp.t, sp.programmed, True),
                         cell.driver(rate, start), sp.t, sp.p, rate, LOOKAHEAD_S, GAIN, rt_priority=0,
                         host_timeout_s=host_timeout_s)
    try:
        proc.heartbeat()
        deadline = time.monotonic() + 120.0 + 3 * float(sp.t[-1])
        while not proc.done(0.02) and time.monotonic() < deadline:
            proc.heartbeat()
        return proc.result(timeout=max(deadline - time.monotonic(), 1.0))
    finally:
        proc.kill()


def run(passes: int = 10, hogs: int = 4, rate: float = 125.0, twin: str = "", progress=None) -> dict:
    from drivers.ur.driver import WATCHDOG_S
    from dt_runtime.service.runtime_config import StreamSection

    say = progress or (lambda msg: None)
    t_start = time.perf_counter()
    host_timeout_s = StreamSection().host_timeout_s
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if twin:
            twin_dir = Path(twin)
        else:
            from dt_runtime.workflows.demo import run_demo

            say("dt demo --quick (the twin) ...")
            with contextlib.redirect_stdout(io.StringIO()):
                run_demo(tmp / "demo", quick=True, camera="sim_point")
            twin_dir = tmp / "demo" / "model"
        sp = _path(SPEED, rate, tmp)
        cell = _UrCell()
        procs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(hogs)]
        reports = []
        try:
            time.sleep(2.0)  # the load average starts to show the hogs
            load0 = os.getloadavg()[0]
            emu0 = dict(cell.emu.stats)
            for i in range(passes):
                say(f"pass {i + 1} of {passes} ({hogs} hogs, load {os.getloadavg()[0]:.1f})")
                reports.append(_pass(cell, str(twin_dir), sp, rate, host_timeout_s))
            load1 = os.getloadavg()[0]
            emu = {k: int(cell.emu.stats.get(k, 0) - emu0.get(k, 0))
                   for k in ("servo_cycles", "late_cycles", "skipped_cycles", "watchdog_stops", "host_stops")}
        finally:
            for p in procs:
                p.kill()
                p.wait()
            cell.close()
    keys = ("n_sent", "n_planned", "pauses", "pause_max_ms", "skipped", "lateness_p99_ms", "lateness_max_ms",
            "jitter_p99_ms", "overruns", "correction_us_p99", "host_gap_max_ms", "stopped", "degraded")
    return {"passes": passes, "completed": sum(not r.stopped for r in reports),
            "degraded": sum(not r.stopped and bool(r.degraded) for r in reports),
            "stopped": sum(bool(r.stopped) for r in reports), "host_stalled": sum(r.host_stalled for r in reports),
            "causes": sorted({c for r in reports for c in (r.stopped, r.degraded) if c}),
            "reports": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.to_dict().items() if k in keys}
                        for r in reports],
            "lateness_ms": {"p99_worst_pass": round(max(r.lateness_p99_ms for r in reports), 3),
                            "max": round(max(r.lateness_max_ms for r in reports), 3)},
            "pause_max_ms": round(max(r.pause_max_ms for r in reports), 1),
            "host_gap_max_ms": round(max((r.host_gap_max_ms for r in reports if np.isfinite(r.host_gap_max_ms)),
                                         default=float("nan")), 1),
            "emulator": {**emu, "realtime": cell.realtime}, "watchdog_s": WATCHDOG_S,
            "host_timeout_s": host_timeout_s, "load": {"start": round(load0, 2), "end": round(load1, 2)},
            "cores": os.cpu_count(), "rate_hz": rate, "speed_mm_s": SPEED, "hogs": hogs,
            "realtime": any(r.realtime for r in reports), "seconds": round(time.perf_counter() - t_start, 1)}


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__, argv, passes=10, hogs=4, rate=125.0, twin="")
    logging.disable(logging.WARNING)
    r = run(a.passes, a.hogs, a.rate, a.twin, progress=None if a.json else lambda m: print(m, file=sys.stderr))
    if a.json:
        print(json.dumps(r))
        return 0
    print(f"stream_load: {r['completed']} of {r['passes']} passes to the end ({r['degraded']} degraded), "
          f"{r['stopped']} stopped ({r['host_stalled']} by a host stall); load {r['load']['start']} -> "
          f"{r['load']['end']} on {r['cores']} cores, {r['hogs']} hogs, {r['rate_hz']:g} Hz, no real-time priority")
    print(f"  lateness (ms): {r['lateness_ms']}; the parent's longest silence {r['host_gap_max_ms']} ms "
          f"(host_timeout_s {r['host_timeout_s']}); emulator {r['emulator']}")
    for c in r["causes"]:
        print(f"  - {c}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
