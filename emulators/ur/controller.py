"""A Universal Robots controller on loopback: RTDE (default 30004) and the script port (default
30002) served over a plant, so the real driver (`drivers.ur.driver`) and third-party RTDE clients
talk to it exactly as to a UR. `python -m emulators.ur --port 30004 --script-port 30002` runs it
over the simulated cell. What it emulates, its faults and how it runs the servo program:
docs/drivers.md ("Universal Robots over RTDE", "Run the emulator")."""
from __future__ import annotations

import argparse
import math
import select
import signal
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.ur import protocol as rp
from drivers.ur import urscript
from dt_kernel.errors import ConfigError
from emulators.ur.motion import Motion
from sim.kinematics import TOOL_DOWN
from sim.servo import ServoFollower

CONTROLLER_VERSION = (5, 11, 0, 0)  # an e-Series controller: 500 Hz RTDE
_TICK_S = 0.004  # the emulated controller's bookkeeping period (moves start and end on it)
_MAX_CATCH_UP_S = 0.5  # control cycles later than this are skipped, not caught up (the emulator itself stalled)
_SRC = "URScript"


@dataclass(frozen=True)
class UrFaults:
    """The UR emulator's faults: ``drop_rtde_after`` (data packages, then the RTDE connection is
    closed once), ``protective_stop_on_move`` (this motion, 1-based, ends in a protective stop at
    ``protective_stop_fraction`` of its path), ``taken_inputs`` (input registers a fieldbus adapter
    writes: IN_USE to RTDE clients).

    Raises
    ------
    ConfigError
        For a negative or non-integer count, or a fraction outside (0, 1).
    """
    drop_rtde_after: int | None = None  # data packages, then the RTDE connection is closed (once)
    protective_stop_on_move: int | None = None  # this motion (1 = the first) ends in a protective stop
    protective_stop_fraction: float = 0.5  # of its path
    taken_inputs: tuple[str, ...] = ()  # input registers a fieldbus adapter writes: IN_USE to RTDE clients

    def __post_init__(self) -> None:
        for key in ("drop_rtde_after", "protective_stop_on_move"):
            v = getattr(self, key)
            if v is not None and (not isinstance(v, int) or v < 0):
                raise ConfigError("<UR emulator faults>", key, v, "a count >= 0, or None")
        if not 0.0 < self.protective_stop_fraction < 1.0:
            raise ConfigError("<UR emulator faults>", "protective_stop_fraction", self.protective_stop_fraction,
                              "a fraction of the path in (0, 1)")


class UrEmulator:
    """RTDE and the script port over a plant.

    Parameters
    ----------
    plant : object
        With ``move_linear(target, speed)``, ``servo_step(target, speed, dt)``, ``joint_angles()``
        ((6,) rad) and ``controller_tcp()`` ((3,) m); e.g. sim.plant.SimulatedCobot.
    host : str
        The address both servers bind.
    rtde_port, script_port : int
        0 picks a free port (``.rtde_port``, ``.script_port``).
    plant_lock : threading.Lock or None
        Held around plant calls; pass the one the rest of the simulation uses.
    faults : UrFaults or None
    time_scale : float
        Wall time per second of motion (0.1: ten times faster); streamed set-points run unscaled.
    max_speed_m_s : float
        m/s.
    tool_rotvec : array_like or None
        The orientation reported (rad, rotation vector); tool down by default.
    autostart : bool
        Start the threads at once.

    Raises
    ------
    ConfigError
        For a non-positive ``time_scale`` or a plant without six joints.
    OSError
        When a port cannot be bound.
    """

    def __init__(self, plant: Any, host: str = "127.0.0.1", rtde_port: int = 30004, script_port: int = 30002, *,
                 plant_lock: threading.Lock | None = None, faults: UrFaults | None = None,
                 time_scale: float = 1.0, max_speed_m_s: float = 2.0, tool_rotvec: Any = None,
                 autostart: bool = True):
        if not (math.isfinite(time_scale) and time_scale > 0):
            raise ConfigError("<UR emulator>", "time_scale", time_scale, "a positive number")
        self.plant = plant
        self.plant_lock = plant_lock or threading.Lock()
        self.faults = faults or UrFaults()
        self.time_scale, self.max_speed_m_s = float(time_scale), float(max_speed_m_s)
        # The plant holds the tool pointing down (sim.kinematics.TOOL_DOWN): the orientation reported
        # and the only one a move may ask for.
        down = Rotation.from_matrix(TOOL_DOWN).as_rotvec()
        self.rotvec = np.asarray(tool_rotvec if tool_rotvec is not None else down, dtype=float)
        self._t0 = time.monotonic()
        self._lock = threading.RLock()  # the controller state below
        with self.plant_lock:
            self._q = np.asarray(plant.joint_angles(), dtype=float)
            self._p = np.asarray(plant.controller_tcp(), dtype=float)
        if self._q.shape != (6,):
            raise ConfigError("<UR emulator>", "plant", f"{self._q.size} joints", "a six-joint arm (VECTOR6D)")
        self._motion: Motion | None = None
        self._program: list[urscript.Command] = []
        self._safety = rp.SAFETY_NORMAL
        self._drop_after = self.faults.drop_rtde_after
        self._stop_on_move = self.faults.protective_stop_on_move
        self._motions = 0
        self._clients: list[socket.socket] = []
        self.stats = {"movel": 0, "movej": 0, "stops": 0, "scripts": 0, "script_errors": 0, "moves_done": 0,
                      "protective_stops": 0, "rtde_connections": 0, "packages": 0, "drops": 0,
                      "input_packages": 0, "servo_programs": 0, "servo_cycles": 0, "late_cycles": 0,
                      "watchdog_stops": 0, "host_stops": 0, "skipped_cycles": 0}
        # general purpose registers: what clients wrote (inputs) and what programs wrote (outputs)
        self._inputs: dict[str, float] = {n: 0 for n in rp.INPUT_TYPES}
        self._outputs: dict[str, float] = {}
        self._input_owner: dict[str, int] = {}  # register -> the session whose input recipe holds it
        self._sessions = 0
        self.input_writes: deque[dict[str, Any]] = deque(maxlen=100_000)  # every input package, in order
        # Input packages with their arrival (host monotonic s): a control cycle sees those that had
        # arrived by its scheduled time, also when it runs late (`_cycle_inputs`).
        self._arrivals: deque[tuple[float, dict[str, Any]]] = deque()
        self._cycle_inputs: dict[str, float] = dict(self._inputs)
        self._servo: _Servo | None = None
        self.servo_log: deque[tuple[int, tuple[float, ...]]] = deque(maxlen=100_000)  # (seq taken, position)
        self._qd = np.zeros(6)
        self._v = np.zeros(3)
        self._stop = threading.Event()
        self._rtde_srv = socket.create_server((host, rtde_port), reuse_port=False)
        self._script_srv = socket.create_server((host, script_port), reuse_port=False)
        self.host = host
        self.rtde_port = self._rtde_srv.getsockname()[1]
        self.script_port = self._script_srv.getsockname()[1]
        self._threads = [threading.Thread(target=f, name=f"ur-emulator-{n}", daemon=True)
                         for n, f in (("control", self._control), ("rtde", self._accept_rtde),
                                      ("script", self._accept_script))]
        if autostart:
            self.start()

    # --- public -------------------------------------------------------------------------
    def start(self) -> None:
        """Start the control, RTDE and script threads."""
        for t in self._threads:
            t.start()

    def now(self) -> float:
        """The controller's clock: s since it started (RTDE `timestamp`)."""
        return time.monotonic() - self._t0

    def inject_drop(self, after_packages: int = 0) -> None:
        """Close the RTDE connection after more data packages (once).

        Parameters
        ----------
        after_packages : int
        """
        with self._lock:
            self._drop_after = int(after_packages)

    def inject_protective_stop(self) -> None:
        """The next motion ends part-way in a protective stop; a running servo program stops now."""
        with self._lock:
            if self._servo is not None:
                self._safety = rp.SAFETY_PROTECTIVE_STOP
                self.stats["protective_stops"] += 1
                self._servo_end()
                self._error(f"C153A1 protective stop while servoing: the arm stopped at "
                            f"{np.round(self._p, 6).tolist()} m", rp.WARNING_MESSAGE)
                return
            self._stop_on_move = self._motions + 1

    def unlock_protective_stop(self) -> None:
        """Clear a protective stop (what the dashboard server's 'unlock protective stop' does)."""
        with self._lock:
            if self._safety == rp.SAFETY_PROTECTIVE_STOP:
                self._safety = rp.SAFETY_NORMAL

    def motion_offset(self, now: float | None = None) -> np.ndarray:
        """The reported TCP minus where the move in progress ends (zero when still).

        A camera emulator adds it to the plant's pose, committed at the move's start, to follow the arm
        while it moves; it reads one reference and never takes the controller lock, which the control
        thread holds while the plant moves in PyBullet.

        Parameters
        ----------
        now : float or None
            s, host monotonic clock (now when None).

        Returns
        -------
        ndarray
            (3,) m.
        """
        m = self._motion
        if m is None:
            return np.zeros(3)
        return m.sample(time.monotonic() if now is None else now)[2] - m.p1

    @property
    def safety_mode(self) -> int:
        """The safety mode (protocol.SAFETY_*)."""
        return self._safety

    def stop(self) -> None:
        """Close every socket and stop the threads (once)."""
        if self._stop.is_set():
            return
        self._stop.set()
        for s in (self._rtde_srv, self._script_srv, *list(self._clients)):
            _close(s)
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- controller state ---------------------------------------------------------------
    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """Every output field's value at a wall time.

        Parameters
        ----------
        now : float or None
            s, host monotonic clock (now when None).

        Returns
        -------
        dict
            Output name -> value (vectors as lists).
        """
        now = time.monotonic() if now is None else now
        with self._lock:
            m, safety, playing = self._motion, self._safety, bool(self._motion or self._program or self._servo)
            if m is not None:
                q, qd, p, pd = m.sample(now)
                if m.stop_at is not None and m.done(now):
                    safety = rp.SAFETY_PROTECTIVE_STOP
                target_p = m.p1 if m.stop_at is not None and m.done(now) else m.p_goal
                target_q = m.q1
            else:
                q, qd, p, pd = self._q, self._qd, self._p, self._v
                target_p, target_q = self._p, self._q
        pose = [*p, *self.rotvec]
        speed = [*pd, 0.0, 0.0, 0.0]
        protective = safety == rp.SAFETY_PROTECTIVE_STOP
        runtime = rp.RUNTIME_PLAYING if playing and not protective else rp.RUNTIME_STOPPED
        return {"timestamp": now - self._t0, "actual_q": list(q), "actual_qd": list(qd), "target_q": list(target_q),
                "target_qd": list(qd), "actual_TCP_pose": pose, "actual_TCP_speed": speed,
                "target_TCP_pose": [*target_p, *self.rotvec], "target_TCP_speed": speed,
                "actual_execution_time": 0.1, "robot_mode": rp.ROBOT_MODE_RUNNING, "safety_mode": safety,
                "runtime_state": runtime, "speed_scaling": 1.0, "target_speed_fraction": 1.0,
                # guide: robot status bit 0 power on, bit 1 program running; safety bit 0 normal, 2 protective stop
                "robot_status_bits": 1 | (2 if runtime == rp.RUNTIME_PLAYING else 0),
                "safety_status_bits": 4 if protective else 1}

    def register(self, name: str) -> float:
        """A general purpose register's value (input or output), 0 if never written.

        Parameters
        ----------
        name : str
            E.g. ``output_int_register_24``.

        Returns
        -------
        float
        """
        if name in self._inputs:
            return self._inputs[name]
        return self._outputs.get(name, 0)

    def _control(self) -> None:
        """Runs the servo program's control cycles, or ends finished moves and starts the program's
        next command. A cycle that comes late (this thread was not scheduled in time) is run at
        once, on its own time: it sees the set-points that had arrived by its scheduled time and
        steps the arm by its period, so the arm's motion does not depend on when the emulator ran
        (counted, `late_cycles`); after a stall beyond _MAX_CATCH_UP_S the cycles missed are
        skipped (`skipped_cycles`)."""
        next_t = time.monotonic()
        while True:
            servo = self._servo
            period = servo.program.period_s if servo is not None else _TICK_S
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -_MAX_CATCH_UP_S:
                if servo is not None:
                    self.stats["skipped_cycles"] += int(-delay / period)
                next_t, delay = time.monotonic(), 0.0
            elif delay < -period and servo is not None:
                self.stats["late_cycles"] += 1
            if self._stop.wait(max(delay, 0.0)):
                return
            now = time.monotonic()
            with self._lock:
                self._take_arrivals(next_t)
                if self._servo is not None:
                    self._servo_cycle()
                    continue
                m = self._motion
                if m is not None and m.done(now):
                    self._finish(m)
                if self._motion is None and self._program:
                    cmd = self._program.pop(0)
                    try:
                        self._begin(cmd, now)
                    except urscript.ScriptError as exc:
                        self._program.clear()
                        self._error(str(exc))

    def _take_arrivals(self, until: float) -> None:
        """The input packages that had arrived by `until` join what the control cycle sees."""
        while self._arrivals and self._arrivals[0][0] <= until:
            self._cycle_inputs.update(self._arrivals.popleft()[1])

    def _finish(self, m: Motion) -> None:
        self._q, self._p, self._motion = m.q1.copy(), m.p1.copy(), None
        self.stats["moves_done"] += 1
        if m.stop_at is not None:
            self._safety = rp.SAFETY_PROTECTIVE_STOP
            self.stats["protective_stops"] += 1
            self._program.clear()
            self._error(f"C153A1 protective stop during {m.dist * 1e3:.1f} mm move: the arm stopped at "
                        f"{np.round(m.p1, 6).tolist()} m", rp.WARNING_MESSAGE)

    def _servo_cycle(self) -> None:
        """One control cycle of the servo program (see the module docstring); under self._lock."""
        servo = self._servo
        assert servo is not None
        sp = servo.program
        seq = int(self._cycle_inputs[f"input_int_register_{sp.seq_register}"])
        if seq < 0:
            self._outputs[f"output_int_register_{sp.status_register}"] = urscript.STREAM_HOST_STOP
            self.stats["host_stops"] += 1
            self._servo_end()
            return
        if seq == servo.seen:
            servo.quiet += 1
            if servo.quiet > sp.watchdog_cycles:
                self._outputs[f"output_int_register_{sp.status_register}"] = urscript.STREAM_WATCHDOG
                self.stats["watchdog_stops"] += 1
                self._error(f"cobot-dt stream watchdog: no new set-point for {sp.watchdog_cycles} control cycles",
                            rp.INFO_MESSAGE)
                self._servo_end()
                return
        else:
            servo.seen, servo.quiet = seq, 0
        self._outputs[f"output_int_register_{sp.echo_register}"] = servo.seen
        pose = np.array([self._cycle_inputs[f"input_double_register_{sp.double_register + i}"] for i in range(6)])
        try:
            if not np.allclose(_rot_distance(pose[3:], self.rotvec), 0.0, atol=1e-3):
                raise urscript.ScriptError(f"servoj: orientation {pose[3:].tolist()} is not the tool-down "
                                           f"{np.round(self.rotvec, 6).tolist()} this arm holds")
            x, v = servo.follower.step(pose[:3], sp.period_s)
            with self.plant_lock:
                self.plant.servo_step(x, float(np.linalg.norm(v)), sp.period_s)
                q = np.asarray(self.plant.joint_angles(), dtype=float)
                p = np.asarray(self.plant.controller_tcp(), dtype=float)
        except Exception as exc:  # get_inverse_kin failed, unreachable: the program ends with an error
            self._servo_end()
            self._error(f"servo program ended: get_inverse_kin({np.round(pose[:3], 6).tolist()}): {exc}")
            return
        self._qd, self._q, self._p, self._v = (q - self._q) / sp.period_s, q, p, v
        self.stats["servo_cycles"] += 1
        self.servo_log.append((servo.seen, tuple(x)))

    def _servo_end(self) -> None:
        """stopj: the arm stops where it is and the program ends."""
        if self._servo is not None:
            self._servo.follower.stop()
        self._servo = None
        self._qd, self._v = np.zeros(6), np.zeros(3)
        self.stats["stops"] += 1

    def _begin(self, cmd: urscript.Command, now: float) -> None:
        if cmd.kind in ("stopl", "stopj"):
            return  # nothing moving (a running motion was stopped when the program arrived)
        if cmd.servo is not None:
            sp = cmd.servo
            self._servo = _Servo(sp, ServoFollower(self._p, sp.lookahead_s, sp.gain),
                                 seen=int(self._cycle_inputs[f"input_int_register_{sp.seq_register}"]))
            self._outputs[f"output_int_register_{sp.status_register}"] = urscript.STREAM_RUNNING
            self.stats["servo_programs"] += 1
            return
        if cmd.pose is not None:
            goal, rot = np.array(cmd.pose[:3]), np.array(cmd.pose[3:])
            if not np.allclose(_rot_distance(rot, self.rotvec), 0.0, atol=1e-3):
                raise urscript.ScriptError(f"{cmd.kind}: orientation {rot.tolist()} is not the tool-down "
                                           f"{np.round(self.rotvec, 6).tolist()} this arm holds")
        else:
            fk = getattr(getattr(self.plant, "nominal", None), "fk", None)
            if fk is None:
                raise urscript.ScriptError(f"{cmd.kind} to joint positions: the plant has no forward kinematics")
            with self.plant_lock:
                goal = np.asarray(fk(np.asarray(cmd.q))[0], dtype=float)
        # movej speeds are rad/s; the plant only moves the TCP linearly: its speed stands in as m/s.
        v = min(cmd.v, self.max_speed_m_s)
        self._motions += 1
        stop_at = None
        end = goal
        dist = float(np.linalg.norm(goal - self._p))
        if self._stop_on_move is not None and self._motions >= self._stop_on_move:
            self._stop_on_move = None
            stop_at = self.faults.protective_stop_fraction * dist
            end = self._p + (goal - self._p) * self.faults.protective_stop_fraction
        q0 = self._q.copy()
        try:
            with self.plant_lock:
                self.plant.move_linear(end, v)  # the plant settles where the arm ends: its errors are real
                q1 = np.asarray(self.plant.joint_angles(), dtype=float)
                p1 = np.asarray(self.plant.controller_tcp(), dtype=float)
        except Exception as exc:  # unreachable, IK failure: the controller refuses the move
            raise urscript.ScriptError(f"{cmd.kind} to {np.round(goal, 6).tolist()}: {exc}") from exc
        self._motion = Motion(q0=q0, p0=self._p.copy(), q1=q1, p1=p1, p_goal=goal, v=v, a=cmd.a, t_start=now,
                              time_scale=self.time_scale, stop_at=stop_at)

    def _halt(self, now: float) -> None:
        """Stop a running motion where it is (a new program, stopl/stopj): the plant follows."""
        m = self._motion
        if m is None or m.done(now):
            return
        q, _, p, _ = m.sample(now)
        with self.plant_lock:
            self.plant.move_linear(p, m.v)
            self._q = np.asarray(self.plant.joint_angles(), dtype=float)
            self._p = np.asarray(self.plant.controller_tcp(), dtype=float)
        self._motion = None
        self.stats["stops"] += 1

    def _error(self, text: str, level: int = rp.ERROR_MESSAGE) -> None:
        pkg = rp.text_message(text, _SRC, level)
        for c in list(self._clients):
            try:
                c.sendall(pkg)
            except OSError:
                pass  # the streaming thread notices the dead connection

    def run_program(self, text: str) -> None:
        """A program arrives on the script port (also callable directly).

        A program that does not parse, or any program during a protective stop, is refused with an
        RTDE text message (level ERROR); otherwise it replaces the running one.

        Parameters
        ----------
        text : str
            URScript.
        """
        self.stats["scripts"] += 1
        try:
            cmds = urscript.parse(text)
        except urscript.ScriptError as exc:
            self.stats["script_errors"] += 1
            self._error(f"script refused: {exc}")
            return
        with self._lock:
            for c in cmds:
                if c.kind in self.stats:
                    self.stats[c.kind] += 1
            now = time.monotonic()
            if self._motion is not None and self._motion.done(now):
                self._finish(self._motion)  # first: a motion that ended in a protective stop sets it
            if self._safety == rp.SAFETY_PROTECTIVE_STOP:
                self.stats["script_errors"] += 1
                self._error("program not started: the robot is in protective stop")
                return
            self._halt(now)  # a new program replaces the running one
            if self._servo is not None:
                self._servo_end()
            self._program = cmds

    # --- script port --------------------------------------------------------------------
    def _accept_script(self) -> None:
        for conn in _accepted(self._script_srv, self._stop):
            threading.Thread(target=self._serve_script, args=(conn,), daemon=True).start()

    def _serve_script(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            conn.settimeout(0.2)
            while not self._stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not data:
                    break
                buf += data
                buf = self._programs(buf)
        if buf.strip():
            self.run_program(buf.decode("utf-8", "replace"))  # an unfinished program: refused by the parser

    def _programs(self, buf: bytes) -> bytes:
        """Runs every complete program in `buf`; returns the unfinished rest."""
        while b"\n" in buf:
            text = buf.decode("utf-8", "replace")
            if text.lstrip().startswith("def "):
                lines = text.split("\n")
                end = urscript.program_end(lines)
                if end is None:
                    return buf
                prog = "\n".join(lines[:end + 1]) + "\n"
            else:
                prog = text[:text.index("\n") + 1]
            buf = buf[len(prog.encode("utf-8")):]
            if prog.strip():
                self.run_program(prog)
        return buf

    # --- RTDE ---------------------------------------------------------------------------
    def _accept_rtde(self) -> None:
        for conn in _accepted(self._rtde_srv, self._stop):
            self.stats["rtde_connections"] += 1
            threading.Thread(target=self._serve_rtde, args=(conn,), daemon=True).start()

    def _serve_rtde(self, conn: socket.socket) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._sessions += 1
            reader, ses = rp.PackageReader(), _Session(self._sessions)
        next_t, sent = 0.0, 0
        self._clients.append(conn)
        try:
            while not self._stop.is_set():
                wait = max(0.0, next_t - time.monotonic()) if ses.started else 0.1
                r, _, _ = select.select([conn], [], [], wait)
                if r:
                    data = conn.recv(65536)
                    if not data:
                        return
                    for ptype, payload in reader.feed(data):
                        was = ses.started
                        reply = self._rtde_request(ptype, payload, ses)
                        if reply:
                            conn.sendall(reply)
                        if ses.started and not was:
                            next_t = time.monotonic()
                now = time.monotonic()
                if ses.started and ses.recipe is not None and now >= next_t:
                    snap = self.snapshot(now)
                    values = [snap[n] if n in snap else self.register(n) for n in ses.recipe.names]
                    conn.sendall(ses.recipe.pack(values))
                    sent += 1
                    self.stats["packages"] += 1
                    # a late package is skipped, not caught up (the guide: the controller sends the newest)
                    next_t = max(next_t + 1.0 / ses.freq, now)
                    with self._lock:
                        if self._drop_after is not None and sent >= self._drop_after:
                            self._drop_after = None
                            self.stats["drops"] += 1
                            return
        except (OSError, rp.ProtocolError):
            return
        finally:
            if conn in self._clients:
                self._clients.remove(conn)
            with self._lock:  # its input registers are free again
                for name in [n for n, owner in self._input_owner.items() if owner == ses.id]:
                    del self._input_owner[name]
            _close(conn)

    def _rtde_request(self, ptype: int, payload: bytes, ses: _Session) -> bytes:
        """The reply to one client package (b"" when none is due); updates the session."""
        if ptype == rp.REQUEST_PROTOCOL_VERSION:
            ok = rp.parse_protocol_version_request(payload) == rp.PROTOCOL_VERSION
            return rp.pack(ptype, rp.u8(ok))
        if ptype == rp.GET_URCONTROL_VERSION:
            return rp.urcontrol_version_reply(*CONTROLLER_VERSION)
        if ptype == rp.SETUP_OUTPUTS:
            freq, names = rp.parse_setup_outputs_request(payload)
            types = [rp.OUTPUT_TYPES.get(n, rp.NOT_FOUND) for n in names]
            if rp.NOT_FOUND in types or not rp.check_frequency(freq) or ses.started:
                return rp.setup_reply(ptype, 0, types)
            ses.recipe, ses.freq = rp.Recipe(1, tuple(names), tuple(types)), freq
            return rp.setup_reply(ptype, 1, types)
        if ptype == rp.SETUP_INPUTS:
            names = rp.split_names(payload)
            with self._lock:
                types = [rp.INPUT_TYPES.get(n, rp.NOT_FOUND) for n in names]
                types = [rp.IN_USE if t != rp.NOT_FOUND and (n in self.faults.taken_inputs or self._input_owner.get(
                    n, ses.id) != ses.id) else t for n, t in zip(names, types)]
                if rp.NOT_FOUND in types or rp.IN_USE in types or ses.started:
                    return rp.setup_reply(ptype, 0, types)
                rid = ses.next_id
                ses.next_id += 1
                ses.inputs[rid] = rp.Recipe(rid, tuple(names), tuple(types))
                for n in names:
                    self._input_owner[n] = ses.id
            return rp.setup_reply(ptype, rid, types)
        if ptype == rp.DATA_PACKAGE:
            recipe = ses.inputs.get(rp.data_recipe_id(payload))
            if recipe is None:
                return b""  # the controller ignores a package of no input recipe of this client
            values = recipe.unpack(payload)
            with self._lock:
                self._inputs.update(values)  # type: ignore[arg-type]
                self._arrivals.append((time.monotonic(), values))
                self.input_writes.append(values)
                self.stats["input_packages"] += 1
            return b""
        if ptype == rp.START:
            ses.started = ses.recipe is not None
            return rp.pack(ptype, rp.u8(ses.started))
        if ptype == rp.PAUSE:
            ses.started = False
            return rp.pack(ptype, rp.u8(1))
        return b""  # text messages and input data from the client: nothing to answer


@dataclass
class _Session:
    """One RTDE client's setup: its output recipe, frequency, input recipes and whether it is streaming."""

    id: int
    recipe: rp.Recipe | None = None
    freq: float = 125.0
    started: bool = False
    inputs: dict[int, rp.Recipe] = field(default_factory=dict)
    next_id: int = 2  # the output recipe is 1


@dataclass
class _Servo:
    """The servo program running: its parameters, the follower, the sequence number last taken and
    the control cycles since it changed."""

    program: urscript.ServoProgram
    follower: ServoFollower
    seen: int
    quiet: int = 0


def _rot_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float((Rotation.from_rotvec(a).inv() * Rotation.from_rotvec(b)).magnitude())


def _accepted(srv: socket.socket, stop: threading.Event):
    srv.settimeout(0.2)
    while not stop.is_set():
        try:
            conn, _ = srv.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        conn.settimeout(None)
        yield conn


def _close(s: socket.socket) -> None:
    try:
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        s.close()
    except OSError:
        pass


def main(argv: list[str] | None = None) -> int:
    """The ``python -m emulators.ur`` command: serve over the simulated cell until Ctrl-C.

    Parameters
    ----------
    argv : list of str or None
        The arguments (sys.argv[1:] when None).

    Returns
    -------
    int
        Exit status.
    """
    from pathlib import Path

    from drivers.simulated.devices import SimWorld

    configs = Path(__file__).resolve().parents[2] / "configs"
    ap = argparse.ArgumentParser(prog="python -m emulators.ur",
                                 description="A UR controller (RTDE + script port) over the simulated cell.")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=30004, help="RTDE port (default 30004)")
    ap.add_argument("--script-port", type=int, default=30002, help="URScript port (default 30002)")
    ap.add_argument("--scenario", default=str(configs / "scenarios/paper_default.yaml"))
    ap.add_argument("--cell", default=str(configs / "cell.yaml"))
    ap.add_argument("--seed", type=int, default=None, help="the scenario's seed unless given")
    ap.add_argument("--time-scale", type=float, default=1.0, help="wall time per second of motion (0.1: 10x faster)")
    ap.add_argument("--drop-rtde-after", type=int, default=None, help="fault: close RTDE after N data packages")
    ap.add_argument("--protective-stop-on-move", type=int, default=None, help="fault: motion N stops half-way")
    ap.add_argument("--taken-inputs", nargs="*", default=(), metavar="REGISTER",
                    help="fault: input registers a fieldbus writes (IN_USE), e.g. input_double_register_24")
    args = ap.parse_args(argv)
    world = SimWorld(args.scenario, args.cell, args.seed)
    faults = UrFaults(drop_rtde_after=args.drop_rtde_after, protective_stop_on_move=args.protective_stop_on_move,
                      taken_inputs=tuple(args.taken_inputs))
    emu = UrEmulator(world.cell.plant, args.host, args.port, args.script_port, faults=faults,
                     time_scale=args.time_scale)
    print(f"UR emulator ({world.scenario_name}): RTDE on {emu.host}:{emu.rtde_port}, script port "
          f"{emu.host}:{emu.script_port}; Ctrl-C stops it", file=sys.stderr, flush=True)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        done.wait()
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
        world.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
