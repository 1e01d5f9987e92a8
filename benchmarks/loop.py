"""Loop rate of the twin daemon: `python -m benchmarks.loop [--json] [--seconds S] [--rate HZ]
[--camera sim_point|sim_images] [--robot sim|serial]`.

The full per-command loop (bounded GPR correction, simulated controller move, MVS reading,
Eq. 17, escalation, SQLite logging, Zenoh telemetry and health on loopback) paced at the target
rate on a streamed circular path; the baseline, measured in the same run, is the same loop
unpaced (the rate the code could sustain). `--camera sim_images` reads the MVS from rendered
images of the rig (OpenCV detection and triangulation every tick) instead of the point stand-in:
pick a target rate a camera could deliver (e.g. `--rate 30`). `--robot serial` commands the arm
through the serial controller driver and its emulator on a pseudo-terminal (the line protocol
every tick) instead of the simulated controller. Keys: rate_hz, target_hz, p99_period_error_ms
(DESIGN.md), and the end-to-end latency of the paced run, latency_p50_ms and latency_p99_ms: from
the MVS reading's receipt on the host (its `host_time`) to the Eq. 17 test done.
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


def _config(twin: Path, tmp: Path, rate: float, realtime: bool, camera: str, robot: dict) -> RuntimeConfig:
    return RuntimeConfig.model_validate({
        "twin": str(twin), "store": str(tmp / f"loop_{realtime}.sqlite"), "rate_hz": rate,
        "realtime": realtime, "path": {"kind": "circle", "speeds": [0.25]},
        "drivers": {"camera": camera, "robot": robot},
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml")},
        "bus": {"cell": "bench", "robot": "r1", "listen": [f"tcp/127.0.0.1:{_port()}"]},
    })


@contextlib.contextmanager
def _robot(kind: str):
    """(world to run on or None, the robot driver's section): `serial` speaks to the emulator on
    a pty, which serves the same simulated cell the cameras see."""
    if kind == "sim":
        yield None, {"kind": "sim"}
        return
    from drivers.serial.emulator import ControllerEmulator
    from drivers.simulated.devices import SimWorld

    world = SimWorld(CONFIGS / "scenarios" / "paper_default.yaml", CONFIGS / "cell.yaml")
    try:
        with ControllerEmulator(world.cell.plant) as emu:
            yield world, {"kind": "serial", "url": emu.port, "timeout_s": 2.0}
    finally:
        world.close()


def _run(twin: Path, tmp: Path, rate: float, realtime: bool, camera: str, robot: str,
         seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Tick start times and latencies (s) of one run."""
    with _robot(robot) as (world, section):
        cfg = _config(twin, tmp, rate, realtime, camera, section)
        d = Daemon(cfg, CONFIGS, world=world)
        d.tick_times, d.latencies = [], []
        try:
            if cfg.realtime:
                d.run(duration_s=seconds)
            else:
                d.run(max_ticks=int(seconds * 1000))
        finally:
            d.close()
    return np.array(d.tick_times), np.array(d.latencies)


def measure(seconds: float, rate: float, camera: str = "sim_point", robot: str = "sim") -> dict:
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with contextlib.redirect_stdout(io.StringIO()):
            # The loop reads the MVS every tick, faster than any camera images could come: the
            # point MVS stand-in keeps the benchmark about the loop itself.
            # `--camera sim_images` measures the image pipeline in the loop too.
            dt_main(["demo", "--quick", "--json", "--no-progress", "--camera", camera, "--out", str(tmp / "demo")])
        twin = tmp / "demo" / "model"
        free, _ = _run(twin, tmp, rate, False, camera, robot, min(seconds, 3.0))
        paced, latency = _run(twin, tmp, rate, True, camera, robot, seconds)
    periods = np.diff(paced)[50:]  # skip start-up
    err = np.abs(periods - 1.0 / rate) * 1e3
    free_rate = (len(free) - 1) / (free[-1] - free[0])
    lat = latency[50:] * 1e3 if len(latency) > 100 else latency * 1e3
    return {"camera": camera, "robot": robot, "rate_hz": round(float(1.0 / periods.mean()), 1), "target_hz": rate,
            "p99_period_error_ms": round(float(np.percentile(err, 99)), 3),
            "median_period_error_ms": round(float(np.median(err)), 3),
            "unpaced_rate_hz": round(float(free_rate), 1),
            "headroom": round(float(free_rate / rate), 2), "ticks": int(len(paced)),
            "latency_p50_ms": round(float(np.percentile(lat, 50)), 3),
            "latency_p99_ms": round(float(np.percentile(lat, 99)), 3)}


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__, argv, seconds=10.0, rate=500.0, camera="sim_point", robot="sim")
    if a.camera not in ("sim_point", "sim_images"):
        raise SystemExit(f"--camera {a.camera!r}: allowed sim_point, sim_images")
    if a.robot not in ("sim", "serial"):
        raise SystemExit(f"--robot {a.robot!r}: allowed sim, serial")
    r = measure(a.seconds, a.rate, a.camera, a.robot)
    if a.json:
        print(json.dumps(r))
    else:
        print(f"loop ({r['camera']}): {r['rate_hz']} Hz sustained (target {r['target_hz']} Hz), p99 period error "
              f"{r['p99_period_error_ms']} ms; unpaced {r['unpaced_rate_hz']} Hz ({r['headroom']}x the target); "
              f"latency reading -> t-test p50 {r['latency_p50_ms']} ms, p99 {r['latency_p99_ms']} ms "
              f"(robot {r['robot']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
