"""`python -m benchmarks.dashboard --quick` on the quick demo's twin: dt run, dt dashboard and the
OS's headless Chromium in their own processes for 20 s. Asserts the report's structure and that
the page was fed and measured; no timing or memory thresholds (they are reported, with the goals
met or not: the machine is shared)."""
from __future__ import annotations

from benchmarks.dashboard import GOALS, run


def test_the_quick_dashboard_benchmark_feeds_the_page_and_measures_it(twin_dir):
    r = run(20.0, twin=str(twin_dir))
    assert r["update_hz"] > 0 and r["telemetry_hz"] >= r["update_hz"] * 0.5 and r["daemon_hz"] > 0
    lat = r["latency_ms"]
    assert lat["n"] > 20 and 0 < lat["p50"] <= lat["p95"] <= lat["max"]
    assert r["latency_rx_ms"]["p50"] <= lat["p50"]  # the server's receipt comes after the daemon's tick
    assert 0 < r["page_load_ms"] <= r["first_data_ms"]
    assert 0 < r["page_pss_mb"] <= r["page_rss_mb"] and r["server_rss_mb"]["end"] > 0
    assert r["js_heap_mb"]["end"] > 0 and r["goals"] == GOALS
    assert set(r["goals_met"]) == {"update_hz", "latency_p95", "page_load", "page_memory", "server_memory"}
