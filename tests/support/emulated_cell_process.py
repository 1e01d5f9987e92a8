"""`python -m emulators.emulated_cell` in a subprocess for the tests: its ports (the JSON line it
prints when ready) and a clean stop (SIGTERM, then its final statistics line)."""
from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class CellProcess:
    def __init__(self, proc: subprocess.Popen, ports: dict):
        self.proc, self.ports = proc, ports
        self.final: dict | None = None  # the statistics it printed when stopped

    def robot(self, **over) -> dict:
        """The `ur_rtde` driver's options for this cell."""
        return {"kind": "ur_rtde", "host": self.ports["host"], "rtde_port": self.ports["rtde_port"],
                "script_port": self.ports["script_port"], **over}

    def camera(self, **over) -> dict:
        return {"kind": "natnet", "server": self.ports["host"], "command_port": self.ports["natnet_command_port"],
                **over}

    def tracker(self, **over) -> dict:
        return {"kind": "serial", "url": self.ports["tracker_url"], **over}

    def control(self, line: str) -> dict:
        from emulators.emulated_cell import control

        return control(self.ports["host"], self.ports["control_port"], line)


@contextlib.contextmanager
def cell_process(*args: str, timeout_s: float = 60.0) -> Iterator[CellProcess]:
    """Start the cell on free ports (plus `args`), wait for its ports line, SIGTERM it at the end."""
    cmd = [sys.executable, "-m", "emulators.emulated_cell", "--rtde-port", "0", "--script-port", "0",
           "--natnet-command-port", "0", "--tracker-port", "0", *args]
    # stderr to a file, not a pipe nobody reads while the cell runs (a full pipe would block it)
    err = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True)
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:  # a reader thread: a hung start fails on the timeout, not forever
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            ready.set()
        ready.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        if not ready.wait(timeout_s) or not lines:
            err.seek(0)
            raise RuntimeError(f"emulated cell not ready within {timeout_s} s: {err.read()[-3000:]}")
        cell = CellProcess(proc, json.loads(lines[0]))
        yield cell
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        err.close()
    if len(lines) > 1:
        cell.final = json.loads(lines[-1])


def runtime_yaml(cell: CellProcess, twin: Path | str, tmp: Path, name: str = "runtime.yaml", **over) -> Path:
    """configs/runtime_ur_natnet.yaml pointed at this cell's ports, the twin, a store in `tmp`
    and a free bus port; `over` replaces top-level keys."""
    import yaml

    from tests.support.loopback import free_port

    doc = yaml.safe_load((ROOT / "configs" / "runtime_ur_natnet.yaml").read_text())
    doc.update(twin=str(twin), store=str(tmp / "dt.sqlite"))
    # NatNet max_age_s 0.25 (the driver's default is 0.05): on a loaded test machine the reader
    # may take tens of ms to get to a frame; the stale refusal is tested with 0.5 s late frames
    doc["drivers"] = {"robot": cell.robot(move_timeout_s=30.0), "camera": cell.camera(max_age_s=0.25),
                      "tracker": cell.tracker(timeout_s=1.0)}
    doc["bus"] = {**doc["bus"], "listen": [f"tcp/127.0.0.1:{free_port()}"]}
    doc.update(over)
    path = tmp / name
    path.write_text(yaml.safe_dump(doc))
    return path


def campaign(cell: CellProcess, tmp: Path, doe_rows: int | None = 60) -> tuple[int, dict, Path]:
    """`dt campaign` through the cell's drivers: (exit code, its JSON, the runtime YAML whose
    `twin:` is the twin it made)."""
    import contextlib
    import io

    from dt_runtime.cli.main import main

    out = tmp / "campaign_out"
    cfg = runtime_yaml(cell, out / "model", tmp)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rows = ["--doe-rows", str(doe_rows)] if doe_rows is not None else []  # None: the plan's whole DOE
        rc = main(["campaign", "--config", str(cfg), *rows, "--out", str(out), "--json", "--no-progress"])
    return rc, json.loads(buf.getvalue()), cfg
