"""`python -m benchmarks.dashboard [--json] [--quick] [--seconds S] [--rate-hz R] [--twin DIR]
[--screenshots DIR]`: `dt dashboard` open in a headless browser beside a `dt run` at 125 Hz
(issue 24, "Speed and stamina").

Three processes, as in a cell: `dt run` (the simulated cell, paced at `--rate-hz`, 125 by default:
a CB3's rate; its bus on a loopback port), `dt dashboard` joined to it (the runtime YAML's bus
section), and the OS's Chromium (headless, driven by Playwright; never a downloaded browser) with
the page open for `--seconds` (600 by default; `--quick`: 20 s, the test's run). Every few
seconds the benchmark reads the page's counters (`window.dtStats`) and the memory of the browser's
processes and of the server.

Keys: `update_hz` (batches the page received and drew per second: each one a DOM update),
`telemetry_hz` (telemetry messages reaching the page per second), `daemon_hz` (the daemon's ticks
per second over the run, from its health), `latency_ms` {`p50`, `p95`, `max`, `n`} from the
daemon's time stamp `t` of a telemetry message (realtime: the wall clock at the tick) to the frame
that showed it (the page's `requestAnimationFrame` after the batch arrived: bus to screen, the
daemon's own publishing included), `latency_rx_ms` {`p50`, `p95`} from the server's receipt to that
frame, `skipped` (telemetry the server's ring dropped before the page got it), `page_load_ms` (the
navigation's load event), `first_data_ms` (navigation start to the first frame with telemetry),
`page_rss_mb` and `page_rss_mb_start` (RSS of all the browser's processes summed, at the end and
after the first `SAMPLE_S`: shared pages counted once per process), `page_pss_mb` and
`page_pss_mb_start` (the same as PSS: shared pages shared out, the browser's real cost),
`js_heap_mb` {`start`, `end`} (the page's used JS heap, Chrome DevTools Protocol),
`server_rss_mb` {`start`, `end`}, `seconds`, `rate_hz`, `quick`, `load` {`start`, `end`}, `cores`,
and `goals` / `goals_met` (the issue's: updates >= 20 Hz, latency p95 < 200 ms, load < 2 s; memory
bounded: the page's heap and the server's RSS at the end within 1.5x and +20 MB of the start).
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import cli

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_S = 5.0
GOALS = {"update_hz": 20.0, "latency_p95_ms": 200.0, "page_load_ms": 2000.0, "memory_growth_ratio": 1.5,
         "memory_growth_mb": 20.0}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _quick_twin(tmp: Path) -> Path:
    from dt_runtime.cli.main import main

    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["demo", "--quick", "--json", "--no-progress", "--out", str(tmp / "demo")])
    if rc != 0:
        raise SystemExit("dt demo --quick failed")
    return tmp / "demo" / "model"


def _wait_listening(url: str, proc: subprocess.Popen, timeout: float) -> None:
    import urllib.request

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise SystemExit(f"dt dashboard exited ({proc.returncode})")
        try:
            with urllib.request.urlopen(url + "api/snapshot", timeout=2) as r:
                if json.loads(r.read()).get("health"):
                    return
        except OSError:
            pass
        time.sleep(0.2)
    raise SystemExit("dt dashboard did not show the daemon's health in time")


def _pct(a: list[float]) -> dict:
    if not a:
        return {"p50": None, "p95": None, "max": None, "n": 0}
    x = np.asarray(a)
    return {"p50": round(float(np.percentile(x, 50)), 2), "p95": round(float(np.percentile(x, 95)), 2),
            "max": round(float(x.max()), 2), "n": len(a)}


def run(seconds: float, rate_hz: float = 125.0, twin: str = "", screenshots: str = "",
        progress=None) -> dict:
    from playwright.sync_api import sync_playwright

    from tests.support import browser

    say = progress or (lambda _m: None)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-dashboard-") as tmpname:
        tmp = Path(tmpname)
        twin_dir = Path(twin) if twin else _quick_twin(tmp)
        env = dict(os.environ, XDG_CONFIG_HOME=str(tmp / "xdg"), MPLBACKEND="Agg")  # the key of this run only
        bus_port, http_port = _free_port(), _free_port()
        cfg = tmp / "runtime.yaml"
        cfg.write_text(f"twin: {twin_dir.resolve()}\nstore: {tmp / 'dt.sqlite'}\nrate_hz: {rate_hz}\nrealtime: true\n"
                       f"sim: {{scenario: {ROOT / 'configs/scenarios/paper_default.yaml'}, "
                       f"cell: {ROOT / 'configs/cell.yaml'}}}\n"
                       f"bus: {{cell: bench, robot: r1, listen: [tcp/127.0.0.1:{bus_port}]}}\n")
        total = seconds + 60
        py = sys.executable
        daemon = subprocess.Popen([py, "-m", "dt_runtime.cli.main", "run", "--config", str(cfg), "--duration",
                                   str(total), "--quiet", "--json"], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL)
        dash = None
        try:
            time.sleep(1.0)
            dash = subprocess.Popen([py, "-m", "dt_runtime.cli.main", "dashboard", "--config", str(cfg), "--port",
                                     str(http_port), "--duration", str(total)], env=env, cwd=ROOT,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            url = f"http://127.0.0.1:{http_port}/"
            _wait_listening(url, dash, 120)
            say(f"dt run at {rate_hz:g} Hz and dt dashboard up; the page open for {seconds:g} s")
            with sync_playwright() as pw:
                profile = tmp / "chromium-profile"
                ctx = pw.chromium.launch_persistent_context(str(profile), executable_path=browser.chromium_path(),
                                                            headless=True, viewport={"width": 1400, "height": 1100},
                                                            bypass_csp=True)
                page = ctx.new_page()
                cdp = ctx.new_cdp_session(page)
                cdp.send("Performance.enable")
                page.goto(url)
                page.wait_for_function("dtStats.firstDataMs != null", timeout=60_000)
                nav = page.evaluate("(() => { const n = performance.getEntriesByType('navigation')[0]; "
                                    "return [n.loadEventEnd, dtStats.firstDataMs]; })()")

                def heap_mb() -> float:
                    m = {x["name"]: x["value"] for x in cdp.send("Performance.getMetrics")["metrics"]}
                    return m.get("JSHeapUsedSize", float("nan")) / 2**20

                lat_t: list[float] = []
                lat_rx: list[float] = []

                def drain() -> dict:
                    d = page.evaluate("(() => { const s = dtStats; const r = {latT: s.latT.splice(0), "
                                      "latRx: s.latRx.splice(0), batches: s.batches, messages: s.messages, "
                                      "skipped: s.skipped}; return r; })()")
                    lat_t.extend(d["latT"])
                    lat_rx.extend(d["latRx"])
                    return d

                def ticks() -> int:
                    return int(page.evaluate("S.health ? S.health.ticks : 0"))

                time.sleep(min(SAMPLE_S, seconds / 4))
                lat_t.clear()
                first = drain()
                lat_t.clear()
                lat_rx.clear()
                t0, ticks0 = time.monotonic(), ticks()
                start = {"page": browser.processes_memory_mb(str(profile)), "heap": heap_mb(),
                         "server": _rss_mb(dash.pid)}
                while time.monotonic() - t0 < seconds:
                    time.sleep(min(SAMPLE_S, max(0.0, seconds - (time.monotonic() - t0))))
                    drain()
                last = drain()
                elapsed = time.monotonic() - t0
                ticks1 = ticks()
                end = {"page": browser.processes_memory_mb(str(profile)), "heap": heap_mb(),
                       "server": _rss_mb(dash.pid)}
                if screenshots:
                    Path(screenshots).mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(Path(screenshots) / "dashboard_benchmark.png"), full_page=True)
                ctx.close()
        finally:
            for p in (dash, daemon):
                if p is not None and p.poll() is None:
                    p.terminate()
            for p in (dash, daemon):
                if p is not None:
                    try:
                        p.wait(30)
                    except subprocess.TimeoutExpired:
                        p.kill()
    update_hz = (last["batches"] - first["batches"]) / elapsed
    latency = _pct(lat_t)
    out = {"update_hz": round(update_hz, 2), "telemetry_hz": round((last["messages"] - first["messages"]) / elapsed, 2),
           "daemon_hz": round((ticks1 - ticks0) / elapsed, 2), "latency_ms": latency,
           "latency_rx_ms": _pct(lat_rx), "skipped": last["skipped"] - first["skipped"],
           "page_load_ms": round(float(nav[0]), 1), "first_data_ms": round(float(nav[1]), 1),
           "page_rss_mb": round(end["page"]["rss"], 1), "page_rss_mb_start": round(start["page"]["rss"], 1),
           "page_pss_mb": round(end["page"]["pss"], 1), "page_pss_mb_start": round(start["page"]["pss"], 1),
           "js_heap_mb": {"start": round(start["heap"], 2), "end": round(end["heap"], 2)},
           "server_rss_mb": {"start": round(start["server"], 1), "end": round(end["server"], 1)},
           "seconds": round(elapsed, 1), "rate_hz": rate_hz, "load": {"start": load0, "end": os.getloadavg()[0]},
           "cores": os.cpu_count(), "goals": GOALS}

    def bounded(a: float, b: float) -> bool:
        return b <= max(a * GOALS["memory_growth_ratio"], a + GOALS["memory_growth_mb"])

    out["goals_met"] = {"update_hz": update_hz >= GOALS["update_hz"],
                        "latency_p95": latency["p95"] is not None and latency["p95"] < GOALS["latency_p95_ms"],
                        "page_load": float(nav[0]) < GOALS["page_load_ms"],
                        "page_memory": bounded(start["heap"], end["heap"]),
                        "server_memory": bounded(start["server"], end["server"])}
    return out


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__, argv, quick=False, seconds=600.0, rate_hz=125.0, twin="", screenshots="")
    seconds = 20.0 if a.quick else a.seconds
    r = run(seconds, a.rate_hz, a.twin, a.screenshots,
            progress=None if a.json else lambda m: print(m, file=sys.stderr, flush=True))
    r["quick"] = a.quick
    if a.json:
        print(json.dumps(r))
    else:
        for k, v in r.items():
            print(f"  {k:<18} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
