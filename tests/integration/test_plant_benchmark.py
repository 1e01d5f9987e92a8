"""`python -m benchmarks.plant --quick`'s run, short: the router, the inbox and a fleet of light
cells as processes on loopback; every request sent is recorded (none lost), and the contract's
keys are there; and `--netns`, across network namespaces. No speed is asserted (a shared, loaded
machine)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_plant_benchmark_quick_run_loses_no_request():
    out = subprocess.run([sys.executable, "-m", "benchmarks.plant", "--quick", "--json"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout)
    assert {"cells", "msgs_per_s", "request_latency_ms", "lost", "consumer_rss_mb"} <= r.keys()
    assert set(r["request_latency_ms"]) >= {"p50", "p99"}
    assert r["cells"] == 5 and r["lost"] == 0
    assert r["requests"]["sent"] >= 1 and r["requests"]["recorded"] == r["requests"]["sent"]
    assert r["requests"]["unacked"] == 0  # the inbox's acks reached the cells
    assert r["msgs_per_s"] > 0 and 0 < r["delivered_ratio"] <= 1.0
    assert r["consumer_rss_mb"] > 0 and r["request_latency_ms"]["p50"] > 0


def test_the_plant_benchmark_across_namespaces_loses_no_request():
    """`--quick --netns`: the same run with the router, the inbox and the fleet processes in network
    namespaces of their own, links of 5-20 ms (tests.support.netns), after the loopback reference."""
    from tests.support.netns import unavailable

    why = unavailable()
    if why:
        pytest.skip(f"benchmarks.plant --netns needs network namespaces: {why}")
    out = subprocess.run([sys.executable, "-m", "benchmarks.plant", "--quick", "--netns", "--delay-ms", "5-20",
                          "--json"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout)
    assert r["cells"] == 5 and r["lost"] == 0 and r["loopback"]["lost"] == 0
    assert r["requests"]["sent"] >= 1 and r["requests"]["recorded"] == r["requests"]["sent"]
    assert r["requests"]["unacked"] == 0
    delay = r["netns"]["link_delay_ms"]
    assert r["netns"]["links"] == 5 and 5.0 <= delay["min"] <= delay["max"] <= 20.0
    assert r["netns"]["delay_mode"] in ("netem", "relay")
    # two links, each at least 5 ms one way, between a light cell and the inbox: the latency shows it
    assert r["request_latency_ms"]["p50"] >= 10.0
