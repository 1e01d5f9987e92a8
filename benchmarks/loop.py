"""Loop rate of the twin daemon: `python -m benchmarks.loop [--json] [--seconds S] [--rate HZ]
[--camera sim_point|sim_images]`.

The full per-command loop (bounded GPR correction, simulated controller move, MVS reading,
Eq. 17, escalation, SQLite logging, Zenoh telemetry and health on loopback) paced at the target
rate on a streamed circular path; the baseline, measured in the same run, is the same loop
unpaced (the rate the code could sustain). `--camera sim_images` reads the MVS from rendered
images of the rig (OpenCV detection and triangulation every tick) instead of the point stand-in:
pick a target rate a camera could deliver (e.g. `--rate 30`). Keys: rate_hz, target_hz,
p99_period_error_ms (DESIGN.md).
"""
from __future__ import annotations

import contextlib
import io
import json
import logging
import socket
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks._common import cli
from dt_runtime.cli.main import main as dt_main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.service.daemon import Daemon, RuntimeConfig


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(twin: Path, tmp: Path, rate: float, realtime: bool, camera: str) -> RuntimeConfig:
    return RuntimeConfig.model_validate({
        "twin": str(twin), "store": str(tmp / f"loop_{realtime}.sqlite"), "rate_hz": rate,
        "realtime": realtime, "path": {"kind": "circle", "speeds": [0.25]}, "drivers": {"camera": camera},
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml")},
        "bus": {"cell": "bench", "robot": "r1", "listen": [f"tcp/127.0.0.1:{_port()}"]},
    })


def _run(cfg: RuntimeConfig, seconds: float) -> np.ndarray:
    d = Daemon(cfg, CONFIGS)
    d.tick_times = []
    try:
        if cfg.realtime:
            d.run(duration_s=seconds)
        else:
            d.run(max_ticks=int(seconds * 1000))
    finally:
        d.close()
    return np.array(d.tick_times)


def measure(seconds: float, rate: float, camera: str = "sim_point") -> dict:
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with contextlib.redirect_stdout(io.StringIO()):
            # The loop reads the MVS every tick, faster than any camera images could come: the
            # point MVS stand-in keeps the benchmark about the loop itself.
            # `--camera sim_images` measures the image pipeline in the loop too.
            dt_main(["demo", "--quick", "--json", "--no-progress", "--camera", camera, "--out", str(tmp / "demo")])
        twin = tmp / "demo" / "model"
        free = _run(_config(twin, tmp, rate, False, camera), min(seconds, 3.0))
        paced = _run(_config(twin, tmp, rate, True, camera), seconds)
    periods = np.diff(paced)[50:]  # skip start-up
    err = np.abs(periods - 1.0 / rate) * 1e3
    free_rate = (len(free) - 1) / (free[-1] - free[0])
    return {"camera": camera, "rate_hz": round(float(1.0 / periods.mean()), 1), "target_hz": rate,
            "p99_period_error_ms": round(float(np.percentile(err, 99)), 3),
            "median_period_error_ms": round(float(np.median(err)), 3),
            "unpaced_rate_hz": round(float(free_rate), 1),
            "headroom": round(float(free_rate / rate), 2), "ticks": int(len(paced))}


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__, argv, seconds=10.0, rate=500.0, camera="sim_point")
    if a.camera not in ("sim_point", "sim_images"):
        raise SystemExit(f"--camera {a.camera!r}: allowed sim_point, sim_images")
    r = measure(a.seconds, a.rate, a.camera)
    if a.json:
        print(json.dumps(r))
    else:
        print(f"loop ({r['camera']}): {r['rate_hz']} Hz sustained (target {r['target_hz']} Hz), p99 period error "
              f"{r['p99_period_error_ms']} ms; unpaced {r['unpaced_rate_hz']} Hz ({r['headroom']}x the target)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
