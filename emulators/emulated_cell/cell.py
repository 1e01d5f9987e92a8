"""A whole emulated cell in one process: the UR controller, the NatNet server and the serial
laser tracker over ONE simulated plant, with a control port for statistics and fault injection
(one text line in, one JSON line out). `python -m emulators.emulated_cell --help`; the ports,
the control commands and how the threads share the plant: docs/drivers.md ("The emulated cell")."""
from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from drivers.simulated.devices import SimWorld
from dt_kernel.errors import ConfigError, DriverError
from emulators.natnet import NatNetEmulator, SimRigMarkers
from emulators.serial import TrackerEmulator
from emulators.ur import UrEmulator, UrFaults

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


class _PublishingPlant:
    """The plant as the UR emulator sees it: every motion step also publishes the true tool pose
    and the controller's TCP as one snapshot (called under the plant lock, on the UR thread)."""

    def __init__(self, plant: Any, publish):
        self._plant, self._publish = plant, publish
        publish(plant)

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        try:
            self._plant.move_linear(target, speed)
        finally:  # a failed move may still have moved the arm: publish where it is
            self._publish(self._plant)

    def servo_step(self, target: np.ndarray, speed: float, dt: float) -> None:
        try:
            self._plant.servo_step(target, speed, dt)
        finally:
            self._publish(self._plant)

    def __getattr__(self, name: str) -> Any:  # joint_angles, controller_tcp, nominal, ...
        return getattr(self._plant, name)


class EmulatedCell:
    """The emulators over one SimWorld; a context manager. Ports 0 pick free ones.

    Parameters
    ----------
    scenario : str or Path
        The scenario YAML (configs/scenarios/paper_default.yaml by default).
    cell : str or Path
        The cell config YAML.
    host : str
        The address every server binds.
    rtde_port, script_port : int
        The UR emulator's ports.
    natnet_command_port, natnet_data_port : int
        The NatNet server's ports.
    tracker_port : int
        The laser tracker's TCP port (``socket://`` URL).
    seed : int or None
        Overrides the scenario's seed.
    time_scale : float
        Wall time per second of motion (0.1: ten times faster).
    natnet_rate_hz : float
        NatNet frames per second.
    natnet_seed : int
        Seeds the NatNet markers' noise.
    ur_faults : UrFaults or None
        The UR emulator's faults.

    Raises
    ------
    ConfigError
        When a config does not validate.
    OSError
        When a port cannot be bound.
    """

    def __init__(self, scenario: str | Path = CONFIGS / "scenarios" / "paper_default.yaml",
                 cell: str | Path = CONFIGS / "cell.yaml", *, host: str = "127.0.0.1", rtde_port: int = 0,
                 script_port: int = 0, natnet_command_port: int = 0, tracker_port: int = 0,
                 seed: int | None = None, time_scale: float = 1.0, natnet_rate_hz: float = 120.0,
                 natnet_seed: int = 0, ur_faults: UrFaults | None = None, natnet_data_port: int = 0):
        self.host = host
        self.world = SimWorld(scenario, cell, seed, source=str(scenario))
        self.plant_lock = threading.Lock()  # PyBullet: the UR thread and the tracker thread
        self._snap_lock = threading.Lock()  # the pose snapshot: the NatNet thread reads it
        self._snap: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._opened: list[Any] = []
        try:
            plant = _PublishingPlant(self.world.cell.plant, self._publish)
            self.ur = UrEmulator(plant, host, rtde_port, script_port, plant_lock=self.plant_lock,
                                 faults=ur_faults, time_scale=time_scale)
            self._opened.append(self.ur.stop)
            self.tracker = TrackerEmulator(self.world.cell.tracker.measure_spherical, f"tcp://{host}:{tracker_port}",
                                           lock=self.plant_lock)
            self._opened.append(self.tracker.stop)
            src = SimRigMarkers(self.tool_pose, seed=natnet_seed)
            # The NatNet server holds its data port too (emulators.natnet): a client trusts it
            self.natnet = NatNetEmulator(src, {"host": host, "command_port": natnet_command_port,
                                               "data_port": natnet_data_port, "rate_hz": natnet_rate_hz},
                                         "<emulated cell natnet>").start()
            self._opened.append(self.natnet.close)
        except BaseException:
            self.close()
            raise
        self._control: _ControlServer | None = None

    def _publish(self, plant: Any) -> None:
        R, p = plant.tool_pose()
        snap = (np.asarray(R, float), np.asarray(p, float), np.asarray(plant.controller_tcp(), float))
        with self._snap_lock:
            self._snap = snap

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The arm's actual tool pose now (world frame), without PyBullet: the snapshot taken when
        the plant was committed to the current move, moved along the move's progress."""
        with self._snap_lock:
            snap = self._snap
        assert snap is not None  # published when the plant was wrapped
        R, p, _ = snap
        return R, p + self.ur.motion_offset()

    def ports(self) -> dict[str, Any]:
        """What a client needs: the JSON line the command prints."""
        out = {"host": self.host, "rtde_port": self.ur.rtde_port, "script_port": self.ur.script_port,
               "natnet_command_port": self.natnet.command_port, "natnet_data_port": self.natnet.data_port,
               "tracker_url": self.tracker.port}
        if self._control is not None:
            out["control_port"] = self._control.port
        return out

    def stats(self) -> dict[str, Any]:
        """Every emulator's counters: ``ur``, ``safety_mode``, ``natnet`` and ``tracker``.

        Returns
        -------
        dict
        """
        nat = dataclasses.asdict(self.natnet.stats)
        nat.pop("dropped")
        return {"ur": dict(self.ur.stats), "safety_mode": self.ur.safety_mode, "natnet": nat,
                "tracker": dict(self.tracker.stats)}

    def command(self, line: str) -> dict[str, Any]:
        """Run one control command; errors are replies, not exceptions.

        Commands: ``stats``, ``drop_rtde [N]``, ``protective_stop``, ``unlock``, ``natnet KEY=VALUE ...``
        (NatNetEmulator.set_faults, values in JSON).

        Parameters
        ----------
        line : str

        Returns
        -------
        dict
            ``{"ok": True, ...}``, or ``{"ok": False, "error": ...}`` for an unknown command.

        Raises
        ------
        ValueError, IndexError, ConfigError
            For malformed arguments (the control port turns them into error replies).
        """
        word, *args = line.split()
        if word == "stats":
            return {"ok": True, **self.stats()}
        if word == "drop_rtde":
            self.ur.inject_drop(int(args[0]) if args else 0)
        elif word == "protective_stop":
            self.ur.inject_protective_stop()
        elif word == "unlock":
            self.ur.unlock_protective_stop()
        elif word == "natnet":
            changes = {k: json.loads(v) for k, _, v in (a.partition("=") for a in args)}
            self.natnet.set_faults(**changes)
        else:
            return {"ok": False, "error": f"unknown command {word!r}: stats, drop_rtde [N], protective_stop, "
                                          "unlock, natnet KEY=VALUE ..."}
        return {"ok": True}

    def serve_control(self, port: int = 0) -> int:
        """Start the control port on the cell's host.

        Parameters
        ----------
        port : int
            0 picks a free one.

        Returns
        -------
        int
            The port.
        """
        self._control = _ControlServer(self, self.host, port)
        self._opened.append(self._control.stop)
        return self._control.port

    def close(self) -> None:
        """Stop every server (errors are printed, the rest still closed) and close the world."""
        while self._opened:
            try:
                self._opened.pop()()
            except Exception as exc:  # noqa: BLE001 - keep closing the rest
                print(f"emulated cell: while closing: {exc}", file=sys.stderr)
        self.world.close()

    def __enter__(self) -> EmulatedCell:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class _ControlServer:
    """Line-based control port: one command per line, one JSON reply per line."""

    def __init__(self, cell: EmulatedCell, host: str, port: int):
        self._cell = cell
        self._srv = socket.create_server((host, port))
        self._srv.settimeout(0.2)
        self.port = self._srv.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name="emulated-cell-control", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rwb") as f:
            for raw in f:
                line = raw.decode("utf-8", "replace").strip()
                if not line:
                    continue
                try:
                    reply = self._cell.command(line)
                except (ValueError, IndexError, ConfigError, DriverError) as exc:
                    reply = {"ok": False, "error": f"{line!r}: {exc}"}
                f.write((json.dumps(reply) + "\n").encode())
                f.flush()

    def stop(self) -> None:
        self._stop.set()
        self._srv.close()
        self._thread.join(timeout=2.0)


def control(host: str, port: int, line: str, timeout_s: float = 10.0) -> dict[str, Any]:
    """Send one control command to a running cell.

    Parameters
    ----------
    host : str
    port : int
        The control port.
    line : str
        The command.
    timeout_s : float
        s.

    Returns
    -------
    dict
        The cell's JSON reply.

    Raises
    ------
    DriverError
        When the cell closes without a reply.
    OSError
        When the cell cannot be reached.
    """
    with socket.create_connection((host, port), timeout=timeout_s) as s, s.makefile("rwb") as f:
        f.write(line.encode() + b"\n")
        f.flush()
        reply = f.readline()
    if not reply:
        raise DriverError(f"emulated cell control {host}:{port}: no reply to {line!r}")
    return json.loads(reply)


def main(argv: list[str] | None = None) -> int:
    """The ``python -m emulators.emulated_cell`` command: serve until SIGTERM or SIGINT.

    Prints one JSON line with the ports once every server listens, and the final statistics at
    the end.

    Parameters
    ----------
    argv : list of str or None
        The arguments (sys.argv[1:] when None).

    Returns
    -------
    int
        Exit status 0.
    """
    ap = argparse.ArgumentParser(prog="python -m emulators.emulated_cell",
                                 description="UR (RTDE), NatNet and serial laser tracker emulators "
                                             "over one simulated cell.")
    ap.add_argument("--scenario", default=str(CONFIGS / "scenarios" / "paper_default.yaml"))
    ap.add_argument("--cell", default=str(CONFIGS / "cell.yaml"))
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--rtde-port", type=int, default=30004, help="RTDE (0: a free port)")
    ap.add_argument("--script-port", type=int, default=30002, help="URScript port (0: a free port)")
    ap.add_argument("--natnet-command-port", type=int, default=1510, help="NatNet command port (0: a free port)")
    ap.add_argument("--natnet-data-port", type=int, default=None,
                    help="NatNet data port, held by the server (default: the command port + 1, as Motive's"
                         " 1510/1511; a free port when the command port is 0)")
    ap.add_argument("--tracker-port", type=int, default=4000, help="laser tracker, socket:// (0: a free port)")
    ap.add_argument("--control-port", type=int, default=0, help="statistics and faults (0: a free port)")
    ap.add_argument("--seed", type=int, default=None, help="the scenario's seed unless given")
    ap.add_argument("--time-scale", type=float, default=1.0, help="wall time per second of motion (0.1: 10x faster)")
    ap.add_argument("--natnet-rate", type=float, default=120.0, help="NatNet frames per second")
    a = ap.parse_args(argv)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    cell = EmulatedCell(a.scenario, a.cell, host=a.host, rtde_port=a.rtde_port, script_port=a.script_port,
                        natnet_command_port=a.natnet_command_port, tracker_port=a.tracker_port, seed=a.seed,
                        time_scale=a.time_scale, natnet_rate_hz=a.natnet_rate,
                        natnet_data_port=(a.natnet_data_port if a.natnet_data_port is not None else
                                          a.natnet_command_port + 1 if a.natnet_command_port else 0))
    try:
        cell.serve_control(a.control_port)
        print(json.dumps(cell.ports()), flush=True)
        while not done.wait(0.5):
            pass
        print(json.dumps({"stopped": True, **cell.stats()}), flush=True)
    finally:
        cell.close()
    return 0

