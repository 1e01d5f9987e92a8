"""`python -m benchmarks.stream --quick` on the quick demo's twin: the path streamed at 125 Hz,
500 mm/s, through the UR driver against its emulator and through the simulated driver, each pass in
its own process. Asserts the report's structure, that every set-point was sent and scored against
the plant's truth, and that the twin's lag compensation lowers the true path error; no timing
thresholds (the rates and jitters are reported, not asserted: the machine is shared)."""
from __future__ import annotations

import math

from benchmarks.stream import PASSES, run


def test_the_quick_stream_benchmark_lowers_the_path_error_by_lag_compensation(twin_dir):
    r = run(quick=True, twin=str(twin_dir))
    assert r["quick"] and r["static_corrected_rms_mm"] > 0 and r["cores"] >= 1
    assert set(r["drivers"]) == {"ur_rtde", "sim"}
    for name, rates in r["drivers"].items():
        assert list(rates) == ["125"]
        e = rates["125"]
        assert e["target_hz"] == 125.0 and e["passes"] == 3
        assert math.isfinite(e["rate_hz"]) and math.isfinite(e["p99_jitter_ms"])
        assert e["correction_us_mean"] > 0 and e["correction_us_p99"] > 0  # the corrected passes corrected
        s = e["speeds"]["500"]
        assert set(s["path_rms_mm"]) == set(s["path_max_mm"]) == set(s["path_rms_cruise_mm"]) == set(PASSES)
        assert 0 < s["n_cruise_planned"] < s["n_planned"] == 154  # the S-curve: 1.22 s at 125 Hz
        g = e["goals_met"]
        assert set(g) == {"rate", "jitter", "correction", "corrected_vs_static", "lag_compensated_vs_static",
                          "lag_compensated_better"}
        assert g["jitter"] is None and g["corrected_vs_static"] is False  # 125 Hz; 15 mm of lag vs 0.06 mm
        rms, n = s["path_rms_mm"], s["n"]
        for p in PASSES:
            assert 0 < rms[p] <= s["path_max_mm"][p]
        assert all(0 < n[p] <= s["n_planned"] for p in PASSES), (name, n)
        # The UR emulator runs in wall time beside the host: a loaded machine without real-time
        # priority may stall it (late cycles, its watchdog) or bunch the host's sends (two set-points
        # within one control cycle: the controller takes the newer, the other is not scored); then
        # only the structure is checked. The simulated driver runs in simulated time: always checked.
        clean = name == "sim" or (e["emulator"]["late_cycles"] == 0 and not e["stopped"]
                                  and all(n[p] >= 0.9 * s["n_planned"] for p in PASSES))
        if not clean:
            continue
        assert e["stopped"] == [] and all(0.9 * s["n_planned"] <= n[p] for p in PASSES), (name, n)
        # 500 mm/s behind a servo lag of ~30 ms (look-ahead 0.03 s): ~15 mm whether corrected or not
        assert 28 < s["lag_ms"] < 33, (name, s["lag_ms"])
        assert rms["corrected"] > 10.0 and rms["uncorrected"] > 10.0
        # the lag learnt from the corrected pass and fed forward removes most of it
        assert rms["lag_compensated"] < 0.1 * rms["corrected"], (name, rms)
        assert s["lag_compensated_better"]
        assert s["path_rms_cruise_mm"]["lag_compensated"] < 0.1 * s["path_rms_cruise_mm"]["corrected"]
    # the simulated driver runs in simulated time: its truth is the same on every machine (seeded)
    s = r["drivers"]["sim"]["125"]["speeds"]["500"]
    assert s["n"] == dict.fromkeys(PASSES, 154)
    assert abs(s["lag_ms"] - 30.08) < 0.05
    assert abs(s["path_rms_mm"]["corrected"] - 13.45) < 0.05
    # the follower identified from the corrected pass (look-ahead 30 ms, 1 / gain 833 us^2) and
    # inverted on the S-curve: the path as good as the static error (0.055 mm), where the series
    # fit on a trapezoid left 0.35 mm (its acceleration steps' transients)
    assert s["path_rms_mm"]["lag_compensated"] < 1.5 * r["static_corrected_rms_mm"], s["path_rms_mm"]
    assert abs(s["servo"]["T_ms"] + s["servo"]["delay_ms"] - 30.0) < 0.5 and abs(s["servo"]["w_ms2"] - 833) < 40
