"""Loop rate of the twin daemon: `python -m benchmarks.loop [--json] [--seconds S] [--rate HZ]
[--camera sim_point|sim_images|natnet] [--robot sim|serial|ur_rtde] [--cell-time-scale F]
[--natnet-rate HZ]`.

The full per-command loop (bounded GPR correction, simulated controller move, MVS reading,
Eq. 17, escalation, SQLite logging, Zenoh telemetry and health on loopback) paced at the target
rate on a streamed circular path; the baseline, measured in the same run, is the same loop
unpaced (the rate the code could sustain). `--camera sim_images` reads the MVS from rendered
images of the rig (OpenCV detection and triangulation every tick) instead of the point stand-in:
pick a target rate a camera could deliver (e.g. `--rate 30`). `--robot serial` commands the arm
through the serial controller driver and its emulator on a pseudo-terminal (the line protocol
every tick) instead of the simulated controller. Keys: rate_hz, target_hz, p99_period_error_ms
(docs/results.md, Real time), and the end-to-end latency of the paced run, latency_p50_ms and latency_p99_ms: from
the MVS reading's receipt on the host (its `host_time`) to the Eq. 17 test done.

`--robot ur_rtde --camera natnet` runs the loop through the Universal Robots RTDE driver and the
OptiTrack NatNet driver against the emulated cell it starts itself (`python -m
emulators.emulated_cell` in a subprocess, as a controller and Motive are other machines; moves
`--cell-time-scale` times real time, NatNet at `--natnet-rate` frames/s), with a twin it
calibrates there first (`dt campaign`, 60 DOE rows); RTDE at 125 Hz (a CB3) for `--rate` up to
125, 500 Hz (an e-Series) above. The simulated drivers (`sim`, `sim_point`) are measured in the
same run at the same target as the baseline (`baseline`, and the ratio `rate_vs_baseline`).
Extra keys: `exposure_latency_p50_ms`, `exposure_latency_p99_ms` (from the frame's
mid-exposure on the host clock to the test done) and `mvs_refused`. Every move is a blocking
`movel` waited for on the RTDE stream (this point loop does not use the driver's set-point
streaming, docs/drivers.md), so the loop's rate is bounded by the move, the arrival seen at the
RTDE rate and a NatNet frame exposed after it.
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
from tests.support.emulated_cell_process import cell_process


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(twin: Path, tmp: Path, rate: float, realtime: bool, camera: str | dict, robot: dict,
            tracker: str | dict = "sim") -> RuntimeConfig:
    return RuntimeConfig.model_validate({
        "twin": str(twin), "store": str(tmp / f"loop_{realtime}.sqlite"), "rate_hz": rate,
        "realtime": realtime, "path": {"kind": "circle", "speeds": [0.25]},
        "drivers": {"camera": camera, "robot": robot, "tracker": tracker},
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
    from drivers.simulated.devices import SimWorld
    from emulators.serial import ControllerEmulator

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


def _percentiles(x: np.ndarray, prefix: str) -> dict:
    ms = (x[50:] if len(x) > 100 else x) * 1e3
    if not len(ms):
        return {f"{prefix}_p50_ms": None, f"{prefix}_p99_ms": None}
    return {f"{prefix}_p50_ms": round(float(np.percentile(ms, 50)), 3),
            f"{prefix}_p99_ms": round(float(np.percentile(ms, 99)), 3)}


def measure_cell(seconds: float, rate: float, time_scale: float = 1.0, natnet_rate: float = 240.0) -> dict:
    """The loop through ur_rtde and natnet against the emulated cell, and the simulated drivers'
    loop at the same target as the baseline, in one run."""
    baseline = measure(seconds, rate)
    logging.disable(logging.WARNING)
    freq = 125.0 if rate <= 125 else 500.0  # a CB3 streams RTDE at 125 Hz, an e-Series at 500 Hz
    cell_args = ("--time-scale", str(time_scale), "--natnet-rate", str(natnet_rate))
    with tempfile.TemporaryDirectory() as tmp, cell_process(*cell_args) as cell:
        tmp = Path(tmp)
        robot = cell.robot(frequency_hz=freq, move_timeout_s=30.0)
        camera = cell.camera()
        tracker = cell.tracker(timeout_s=1.0)
        cfg = _config(tmp / "twin" / "model", tmp, rate, True, camera, robot, tracker)
        runtime = tmp / "runtime.yaml"
        runtime.write_text(json.dumps(cfg.model_dump(mode="json")))  # YAML reads JSON
        with contextlib.redirect_stdout(io.StringIO()):
            rc = dt_main(["campaign", "--config", str(runtime), "--doe-rows", "60", "--out", str(tmp / "twin"),
                          "--json", "--no-progress"])
        if rc != 0:
            raise SystemExit(f"dt campaign against the emulated cell failed (exit {rc})")
        runs = {}
        for realtime in (False, True):
            d = Daemon(_config(tmp / "twin" / "model", tmp, rate, realtime, camera, robot, tracker), CONFIGS)
            d.tick_times, d.latencies, d.exposure_latencies = [], [], []
            try:
                s = d.run(duration_s=min(seconds, 3.0) if not realtime else seconds)
            finally:
                d.close()
            runs[realtime] = (np.array(d.tick_times), np.array(d.latencies), np.array(d.exposure_latencies), s)
    free, _, _, _ = runs[False]
    paced, latency, exposure, summary = runs[True]
    periods = np.diff(paced)[10:]  # skip start-up
    err = np.abs(periods - 1.0 / rate) * 1e3
    free_rate = (len(free) - 1) / (free[-1] - free[0])
    out = {"camera": "natnet", "robot": "ur_rtde", "rate_hz": round(float(1.0 / periods.mean()), 1),
           "target_hz": rate, "rtde_hz": freq, "natnet_rate_hz": natnet_rate, "cell_time_scale": time_scale,
           "p99_period_error_ms": round(float(np.percentile(err, 99)), 3),
           "median_period_error_ms": round(float(np.median(err)), 3),
           "unpaced_rate_hz": round(float(free_rate), 1), "headroom": round(float(free_rate / rate), 2),
           "ticks": int(len(paced)), "mvs_refused": summary["mvs_refused"],
           **_percentiles(latency, "latency"), **_percentiles(exposure, "exposure_latency")}
    out["baseline"] = baseline
    out["rate_vs_baseline"] = round(out["rate_hz"] / baseline["rate_hz"], 3)
    return out


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
    a = cli(__doc__, argv, seconds=10.0, rate=500.0, camera="sim_point", robot="sim", cell_time_scale=1.0,
            natnet_rate=240.0)
    if (a.robot == "ur_rtde") != (a.camera == "natnet"):
        raise SystemExit("--robot ur_rtde and --camera natnet go together (both from the emulated cell)")
    if a.camera not in ("sim_point", "sim_images", "natnet"):
        raise SystemExit(f"--camera {a.camera!r}: allowed sim_point, sim_images, natnet")
    if a.robot not in ("sim", "serial", "ur_rtde"):
        raise SystemExit(f"--robot {a.robot!r}: allowed sim, serial, ur_rtde")
    if a.robot == "ur_rtde":
        r = measure_cell(a.seconds, a.rate, a.cell_time_scale, a.natnet_rate)
    else:
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
