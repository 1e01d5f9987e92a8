"""One corrected command over the bus (`dt/<cell>/<robot>/correct`, request-reply between two Zenoh
peers on loopback TCP) against the same correction in process, measured in the same run.

The twin is a quick demo's (trained into a temporary directory, ~12 s) unless --twin names one.
Keys: bus_median_ms, bus_p99_ms, inproc_median_ms, ratio (bus / in process), n. Target: bus
median < 2 ms.
"""
from __future__ import annotations

import contextlib
import io
import socket
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import cli, emit
from dt_runtime.fabric import BusConfig
from dt_runtime.fabric.correction_client import request_correction
from dt_runtime.fabric.session import close_session, open_session
from dt_runtime.service.correction_server import CorrectionServer
from dt_runtime.twin.bounds import Guard, Limits
from dt_runtime.twin.twin import Twin


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _twin(path: str) -> tuple[Twin, tempfile.TemporaryDirectory | None]:
    if path:
        return Twin.load(path), None
    from dt_runtime.workflows.demo import run_demo

    tmp = tempfile.TemporaryDirectory()
    with contextlib.redirect_stdout(io.StringIO()):
        run_demo(Path(tmp.name), quick=True)
    return Twin.load(Path(tmp.name) / "model"), tmp


def run(n: int = 500, twin_dir: str = "") -> dict:
    twin, tmp = _twin(twin_dir)
    rng = np.random.default_rng(0)
    # Targets along a path inside the DOE volume (the Corrector bounds the step between commands).
    s = np.linspace(0, 2 * np.pi, n)
    targets = np.column_stack([0.9 + 0.1 * np.cos(s), 0.1 * np.sin(s), 0.55 + 0.02 * rng.standard_normal(n)])
    inproc = Guard(twin, Limits())
    t_in = []
    for x in targets:
        t0 = time.perf_counter()
        inproc(x, 0.5)
        t_in.append(time.perf_counter() - t0)
    port = _free_port()
    cfg = BusConfig(cell="bench", robot="r1", listen=[f"tcp/127.0.0.1:{port}"])
    server = CorrectionServer(Guard(twin, Limits()), cfg)
    client = open_session(BusConfig(cell="bench", robot="prog", listen=[f"tcp/127.0.0.1:{_free_port()}"],
                                    connect=[f"tcp/127.0.0.1:{port}"]))
    key = cfg.key("correct")
    try:
        for _ in range(50):  # the peers meet, then warm up
            with contextlib.suppress(Exception):
                request_correction(client, key, targets[0] * 1e3, 500.0, timeout_s=1.0)
        t_bus = []
        for x in targets:
            t0 = time.perf_counter()
            request_correction(client, key, x * 1e3, 500.0, timeout_s=2.0)
            t_bus.append(time.perf_counter() - t0)
    finally:
        close_session(client, 3.0)
        server.close(3.0)
        if tmp is not None:
            tmp.cleanup()
    bus_ms, in_ms = np.median(t_bus) * 1e3, np.median(t_in) * 1e3
    return {"n": n, "bus_median_ms": round(float(bus_ms), 4),
            "bus_p99_ms": round(float(np.percentile(t_bus, 99)) * 1e3, 4),
            "inproc_median_ms": round(float(in_ms), 4), "ratio": round(float(bus_ms / in_ms), 2),
            "target_bus_median_ms": 2.0}


def main(argv: list[str] | None = None) -> int:
    a = cli(__doc__.splitlines()[0], argv, n=500, twin="")
    emit(run(a.n, a.twin), a.json, "correct: one corrected command over the bus vs in process")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
