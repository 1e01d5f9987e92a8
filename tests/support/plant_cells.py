"""A plant on loopback as processes, for the plant's and the plant page's tests: `dt router` from a
plant config, `dt run` cells on the simulated cell as clients of the router, and their stop.
Waits are generous (wait_until); nothing is timed."""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from dt_runtime.common.paths import CONFIGS
from tests.support.loopback import wait_until

FAULT = "[{at_s: 0, joint_offset_rad: [0, 1.0e-3, 0, 0, 0, 0]}]"  # ~1 mm: pages within a second


def dt(*args: str, log: Path) -> subprocess.Popen:
    """`dt ARGS` as a process of its own session, its stderr appended to `log`."""
    with log.open("ab") as f:
        return subprocess.Popen([sys.executable, "-m", "dt_runtime.cli.main", *args], stdout=subprocess.DEVNULL,
                                stderr=f, start_new_session=True)


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def runtime(tmp: Path, twin_dir: Path, cell: str, port: int, faulty: bool = False,
            endpoint: str | None = None) -> Path:
    """A `dt run` config like test_runtime's daemon_cfg, paced (20 Hz on the wall clock: several
    daemons share two cores with the rest of the test), a client of the router on `port`; `faulty`:
    a joint fault from the first tick (it pages within a second); `endpoint`: the router's, when not
    loopback's `port` (a cell in a network namespace: tests.support.netns)."""
    cfg = tmp / f"{cell}.yaml"
    endpoint = endpoint or f"tcp/127.0.0.1:{port}"
    cfg.write_text(
        f"twin: {twin_dir}\nstore: {tmp / cell}.sqlite\nrate_hz: 20\nrealtime: true\n"
        f"sim: {{scenario: {CONFIGS / 'scenarios' / 'paper_default.yaml'}, cell: {CONFIGS / 'cell.yaml'},"
        f" faults: {FAULT if faulty else '[]'}}}\n"
        f"bus: {{cell: {cell}, robot: r1, mode: client, connect: ['{endpoint}'],"
        f" republish_period_s: 0.3, health_period_s: 0.5}}\n")
    return cfg


def router(cfg: Path, log: Path) -> subprocess.Popen:
    """`dt router --config cfg`, once it listens."""
    p = dt("router", "--config", str(cfg), log=log)
    assert wait_until(lambda: "dt router: listening" in log.read_text() or p.poll() is not None, 60), "no router"
    assert p.poll() is None, log.read_text()[-2000:]
    return p
