"""Soak of the twin daemon on simulated time: `python -m benchmarks.soak [--json] [--hours H]`.

A fault-free run of H simulated hours counts false maintenance requests (reported per simulated
day, next to the escalation's computed bound as the baseline); then each injected fault runs on
a fresh cell and its detection delay (simulated seconds from injection to the maintenance
request, or to the offer to re-reference for a shift of the camera set-up: `detected_as`) is
measured. Keys: sim_hours, false_requests_per_day, detection_delay_s (docs/results.md).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import sys
import tempfile
from pathlib import Path

from dt_runtime.cli.main import main as dt_main
from dt_runtime.service.escalation import EscalationConfig, false_alarm_rates
from dt_runtime.common.paths import CONFIGS
from dt_runtime.service.daemon import Daemon, RuntimeConfig

FAULTS = {
    "joint2_offset_0.5mrad": {"joint_offset_rad": [0, 5e-4, 0, 0, 0, 0]},
    "joint3_offset_0.2mrad": {"joint_offset_rad": [0, 0, 2e-4, 0, 0, 0]},
    "joint1_offset_0.3mrad": {"joint_offset_rad": [3e-4, 0, 0, 0, 0, 0]},
    "camera_bumped_1mm": {"camera_shift_m": [1e-3, 0, 0]},
}
FAULT_AT_S = 1800.0


def _cfg(twin: Path, tmp: Path, name: str, faults=()) -> RuntimeConfig:
    return RuntimeConfig.model_validate({
        "twin": str(twin), "store": str(tmp / f"{name}.sqlite"), "realtime": False, "publish": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"),
                "cell": str(CONFIGS / "cell.yaml"), "faults": list(faults)},
    })


def soak(hours: float, fault_hours: float = 2.0, twin: Path | None = None) -> dict:
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if twin is None:
            with contextlib.redirect_stdout(io.StringIO()):
                dt_main(["demo", "--json", "--no-progress", "--out", str(tmp / "demo")])
            twin = tmp / "demo" / "model"
        d = Daemon(_cfg(twin, tmp, "free"), CONFIGS)
        try:
            s = d.run(duration_s=hours * 3600)
        finally:
            d.close()
        free = {"ticks": s["ticks"], "requests": s["maintenance_requests"],
                "t_test_failure_rate": round(s["t_test_failures"] / max(s["ticks"], 1), 4)}
        delays, detected_as = {}, {}
        for name, f in FAULTS.items():
            d = Daemon(_cfg(twin, tmp, name, [{"at_s": FAULT_AT_S, **f}]), CONFIGS)
            try:
                d.run(duration_s=FAULT_AT_S + fault_hours * 3600)
                # a page, or (a rigid shift of the camera set-up) the offer to re-reference
                first = next((tr for tr in d.store.transitions(10_000) if tr["t"] >= FAULT_AT_S
                              and tr["dst"] in ("maintenance_requested", "rereference_offered")), None)
                delays[name] = round(first["t"] - FAULT_AT_S, 1) if first else None
                detected_as[name] = first["dst"] if first else None
            finally:
                d.close()
    tests_per_day = free["ticks"] / hours * 24
    bound = false_alarm_rates(EscalationConfig().model_copy(update={"tests_per_day": tests_per_day}))
    return {"sim_hours": hours, "false_requests_per_day": round(free["requests"] / hours * 24, 4),
            "fault_free": free, "computed_false_requests_per_day_bound": bound,
            "detection_delay_s": delays, "detected_as": detected_as, "fault_injected_at_s": FAULT_AT_S,
            "tests_per_sim_day": round(tests_per_day)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--hours", type=float, default=24.0, help="fault-free simulated hours")
    a = ap.parse_args(argv)
    r = soak(a.hours)
    if a.json:
        print(json.dumps(r))
    else:
        print(f"fault-free: {r['sim_hours']} simulated h, {r['fault_free']['requests']} maintenance requests "
              f"({r['false_requests_per_day']} per day; computed bound {r['computed_false_requests_per_day_bound']})")
        for k, v in r["detection_delay_s"].items():
            print(f"  {k}: detected after {v} s ({r['detected_as'][k]})" if v is not None else f"  {k}: NOT detected")
    return 0


if __name__ == "__main__":
    sys.exit(main())
