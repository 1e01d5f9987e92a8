"""`python -m emulators.ur` in its own process on a loopback address whose port 30004 is free,
for third-party RTDE clients: `ur_rtde`'s receive interface always connects to 30004 and its
constructor blocks holding the GIL, so an emulator thread in the test process would never answer."""
from __future__ import annotations

import contextlib
import random
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.loopback import free_port, wait_until

ROOT = Path(__file__).resolve().parents[2]


def loopback_with_rtde_port_free(port: int = 30004, seed: int = 14) -> str:
    """A loopback address (127.0.0.N) whose `port` is free: other work on this machine may hold
    127.0.0.1:30004. Seeded order; the test is skipped if none of 40 is free."""
    rng = random.Random(seed)
    for last in rng.sample(range(2, 255), 40):
        host = f"127.0.0.{last}"
        try:
            with socket.create_server((host, port)):
                return host
        except OSError:
            continue
    pytest.skip(f"no loopback address with port {port} free")


@contextlib.contextmanager
def ur_emulator_process(*args: str, seed: int = 14) -> Iterator[tuple[str, int]]:
    """The emulator serving RTDE on (host, 30004) and its script port, started with `args`;
    yields (host, script_port) once it answers; SIGTERM at the end."""
    host, script_port = loopback_with_rtde_port_free(seed=seed), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "emulators.ur", "--host", host, "--port", "30004",
                             "--script-port", str(script_port), *args],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)

    def serving() -> bool:
        try:
            socket.create_connection((host, script_port), timeout=0.5).close()
            return True
        except OSError:
            return False

    try:
        assert wait_until(lambda: serving() or proc.poll() is not None, 60.0) and proc.poll() is None, \
            proc.stderr.read() if proc.poll() is not None and proc.stderr else "emulator did not start"
        yield host, script_port
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
