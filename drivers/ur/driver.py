"""Universal Robots controller (driver ``ur_rtde``): state over RTDE, moves as URScript on the
script port, set-points streamed through RTDE input registers to a servoj program with a
watchdog. `UrRtdeController` implements drivers.base.RobotController and SetpointStreamer.
The config keys, what it reads and sends, the faults it detects and the streaming contract:
docs/drivers.md ("Universal Robots over RTDE")."""
from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import Field

from drivers.base import Abortable, JointState, Lifecycle, StreamStatus, WatchdogStop, check_move, check_stream_params
from drivers.ur import protocol as rp
from drivers.ur import urscript
from drivers.ur.rtde_link import RtdeLink, RtdeSample
from dt_kernel.config import Frozen, validate
from dt_kernel.errors import ConfigError, DriverError, StateError

# What the driver needs from every package (the guide's names).
OUTPUTS = ("timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_speed", "target_TCP_pose",
           "robot_mode", "safety_mode", "runtime_state")
_MOVABLE_SAFETY = (rp.SAFETY_NORMAL, rp.SAFETY_REDUCED)


class UrLimits(Frozen):
    """Moves refused before anything is sent: ``tcp_abs_m`` (m, bound on |x|, |y|, |z|), ``max_speed_m_s`` (m/s)."""
    tcp_abs_m: float = Field(3.0, gt=0)
    max_speed_m_s: float = Field(1.0, gt=0, le=5.0)


# The servo program's watchdog when `watchdog_cycles` is not set: 0.25 s at any rate, twice the
# longest stall of the streaming process measured without real-time priority beside four busy
# loops on two cores (121 ms at load 9; docs/streaming.md, "Watchdog and time-outs"): the loop
# waits out a stall, the controller does not stop the arm for it; a host that is gone still has
# the arm stopped within 0.25 s (`dt run` resumes a pass a longer stall stopped).
WATCHDOG_S = 0.25
_WATCHDOG_WHY = "the controller's watchdog stopped the arm"  # a refusal that raises WatchdogStop


class UrStream(Frozen):
    """The RTDE registers and watchdog of set-point streaming (docs/drivers.md, the ``stream`` table):
    register numbers 0-47, ``watchdog_cycles`` (control cycles; None: WATCHDOG_S at the stream's
    rate), ``stop_deceleration`` (rad/s^2).
    """
    enabled: bool = True
    double_register: int = Field(24, ge=0, le=rp.N_REGISTERS - 6)
    seq_register: int = Field(24, ge=0, le=rp.N_REGISTERS - 1)
    status_register: int = Field(24, ge=0, le=rp.N_REGISTERS - 2)
    watchdog_cycles: int | None = Field(None, ge=1, le=100_000)
    stop_deceleration: float = Field(4.0, gt=0, le=40.0)

    @property
    def inputs(self) -> tuple[str, ...]:
        """The input registers written, in package order: the sequence number, then the pose."""
        return (f"input_int_register_{self.seq_register}",
                *(f"input_double_register_{self.double_register + i}" for i in range(6)))

    @property
    def outputs(self) -> tuple[str, ...]:
        """The program's state and the sequence it took, and the sequence register read back (the
        controller has the first set-point before the program starts)."""
        return (f"output_int_register_{self.status_register}", f"output_int_register_{self.status_register + 1}",
                f"input_int_register_{self.seq_register}")


class _Stream:
    """The host's side of a running stream."""

    def __init__(self, program: urscript.ServoProgram, rate_hz: float, rot: tuple[float, ...], p0: np.ndarray):
        self.program, self.rate_hz, self.rot = program, rate_hz, rot
        self.seq, self.sent = 1, 0
        self.last_t: float | None = None
        self.last_p = p0
        self.stopped = ""  # why the controller ended it, once known


class UrConfig(Frozen):
    """The ``ur_rtde`` driver's options (ports, Hz, s, m, m/s); the table is in docs/drivers.md."""
    host: str = Field(min_length=1)
    rtde_port: int = Field(30004, ge=1, le=65535)
    script_port: int = Field(30002, ge=1, le=65535)
    frequency_hz: float = Field(125.0, gt=0, le=rp.MAX_FREQUENCY_HZ)
    timeout_s: float = Field(2.0, gt=0, le=60)
    stale_after_s: float = Field(0.5, gt=0, le=60)
    reconnect_interval_s: float = Field(0.2, gt=0, le=60)
    move_timeout_s: float = Field(60.0, gt=0, le=3600)
    arrival_tol_m: float = Field(1e-4, gt=0, le=0.01)
    still_m_s: float = Field(1e-3, gt=0, le=0.1)
    acceleration_m_s2: float = Field(1.2, gt=0, le=20)
    tool_rotvec: tuple[float, float, float] | None = None
    extra_outputs: tuple[str, ...] = ()
    limits: UrLimits = UrLimits()
    stream: UrStream = UrStream()


class UrRtdeController(Abortable, Lifecycle):
    """RobotController for a Universal Robots arm (see the module docstring)."""

    name = "UR controller"
    config_model = UrConfig

    def __init__(self, *, world: Any = None, source: str | None = None):  # world: unused (a real cell)
        self._source = source or "<ur_rtde robot config>"
        self.cfg: UrConfig | None = None
        self.link: RtdeLink | None = None
        self.stats = {"moves_sent": 0, "moves_arrived": 0, "refused": 0, "setpoints_sent": 0, "streams": 0}
        self._stream: _Stream | None = None

    # --- lifecycle hooks ----------------------------------------------------------------
    def _on_configure(self, config: dict[str, Any]) -> None:
        self.cfg = validate(UrConfig, config, self._source)

    def _on_activate(self) -> None:
        cfg = self._cfg
        extra = (*cfg.extra_outputs, *(cfg.stream.outputs if cfg.stream.enabled else ()))
        names = OUTPUTS + tuple(dict.fromkeys(n for n in extra if n not in OUTPUTS))
        self.link = RtdeLink(cfg.host, cfg.rtde_port, names, cfg.frequency_hz, timeout_s=cfg.timeout_s,
                             stale_after_s=cfg.stale_after_s, reconnect_interval_s=cfg.reconnect_interval_s,
                             source=self._source, inputs=cfg.stream.inputs if cfg.stream.enabled else (),
                             input_source_key="stream")
        self._stream = None
        self.link.open()

    def _on_deactivate(self) -> None:
        if self.link is not None:
            self.link.close()

    def _on_close(self) -> None:
        if self.link is not None:
            self.link.close()

    @property
    def _cfg(self) -> UrConfig:
        if self.cfg is None:
            raise StateError(f"{self.name}: used before configure()")
        return self.cfg

    @property
    def _link(self) -> RtdeLink:
        if self.link is None:
            raise StateError(f"{self.name}: used before activate()")
        return self.link

    # --- reading ------------------------------------------------------------------------
    def read_sample(self) -> RtdeSample:
        """The newest data package, at most ``stale_after_s`` old (waits up to ``timeout_s``).

        Returns
        -------
        RtdeSample

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When no fresh package came within ``timeout_s``.
        """
        self._require("active")
        cfg, link = self._cfg, self._link
        fresh = self._await(lambda s: s if s is not None and time.monotonic() - s.t_host <= cfg.stale_after_s
                            else None, time.monotonic() + cfg.timeout_s)
        if fresh is not None:
            return fresh
        s = link.latest
        age = "none received" if s is None else f"the last {time.monotonic() - s.t_host:.2f} s ago"
        state = "connected" if link.connected else f"reconnecting; last error: {link.last_error}"
        raise DriverError(f"{link.where}: no fresh RTDE data package ({age}; {state})")

    def _await(self, ready: Callable[[RtdeSample | None], Any], deadline: float) -> Any:
        """Wait on the link (its condition, at most 50 ms a wait) until `ready(newest package)`
        gives something other than None, and return that; None once `deadline` (monotonic) has
        passed. `ready` may raise (a refusal the controller reported)."""
        link = self._link
        with link.cond:
            while True:
                got = ready(link.latest)
                if got is not None:
                    return got
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                link.cond.wait(min(left, 0.05))

    def _errors_since(self, n_msg: int) -> list:
        """The controller's error messages among those received after the first `n_msg`."""
        link = self._link
        new = link.stats["messages"] - n_msg
        return [m for m in link.messages[-new:] if m.is_error] if new > 0 else []

    def read_joint_state(self) -> JointState:
        """The joint positions (``actual_q``, rad) of the newest package.

        Returns
        -------
        JointState
            ``t`` the controller's ``timestamp`` (s), ``host_time`` the host's receive time.

        Raises
        ------
        StateError, DriverError
            As ``read_sample``.
        """
        s = self.read_sample()
        return JointState(q=np.array(s.values["actual_q"], dtype=float), t=s.t_device, host_time=s.t_host)

    def read_commanded_tcp(self) -> np.ndarray:
        """The controller's TCP (``actual_TCP_pose[:3]``: from its encoders and nominal kinematics).

        Returns
        -------
        ndarray
            (3,) m, base frame.

        Raises
        ------
        StateError, DriverError
            As ``read_sample``.
        """
        return np.array(self.read_sample().values["actual_TCP_pose"][:3], dtype=float)

    def status(self) -> dict[str, Any]:
        """Robot, safety and program state by name, the link's counters and the last error."""
        s = self.read_sample()
        return {"robot_mode": rp.ROBOT_MODES.get(s.values["robot_mode"], str(s.values["robot_mode"])),
                "safety_mode": rp.SAFETY_MODES.get(s.values["safety_mode"], str(s.values["safety_mode"])),
                "runtime_state": rp.RUNTIME_STATES.get(s.values["runtime_state"], str(s.values["runtime_state"])),
                "controller_version": self._link.controller_version, **self._link.stats, **self.stats,
                "last_error": self._link.last_error}

    def counters(self) -> dict[str, int]:
        """The link's and the moves' counters (packages, connects, drops, stale, moves_sent, ...):
        no I/O, for a health report from another thread (`status()` waits for a fresh package)."""
        link = self.link  # None before activate(): the moves' counters alone
        return {**(dict(link.stats) if link is not None else {}), **self.stats}

    # --- moving -------------------------------------------------------------------------
    def _check_move(self, target: Any, speed: Any) -> tuple[np.ndarray, float]:
        lim = self._cfg.limits
        return check_move(target, speed, lim.tcp_abs_m, lim.max_speed_m_s)

    def _movable(self, s: RtdeSample) -> None:
        mode, safety = s.values["robot_mode"], s.values["safety_mode"]
        if safety not in _MOVABLE_SAFETY:
            self.stats["refused"] += 1
            raise DriverError(f"{self.name}: not moving: safety mode {rp.SAFETY_MODES.get(safety, safety)} "
                              "(a protective stop is cleared on the pendant or the dashboard server)")
        if mode != rp.ROBOT_MODE_RUNNING:
            self.stats["refused"] += 1
            raise DriverError(f"{self.name}: not moving: robot mode {rp.ROBOT_MODES.get(mode, mode)}, needs RUNNING")

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Send one ``movel`` and wait on the RTDE stream until the arm has arrived.

        Arrival: TCP within ``arrival_tol_m`` of the target, TCP speed below ``still_m_s`` and the
        program no longer PLAYING. The orientation is the current one, or ``tool_rotvec``. A move is
        sent once and never re-sent.

        Parameters
        ----------
        target : ndarray
            (3,) m, base frame.
        speed : float
            m/s.

        Raises
        ------
        StateError
            When the driver is not ``active`` or a stream is running.
        DriverError
            When the arguments are out of the limits, the robot is not RUNNING in a NORMAL or REDUCED
            safety mode, a safety stop happens during the move, the controller reports a script error,
            the move does not arrive within ``move_timeout_s``, or it is aborted (``stopl`` is sent).
        """
        self._require("active")
        self._check_abort()
        if self._stream is not None and not self._stream.stopped:
            raise StateError(f"{self.name}: a stream is running (its program would be replaced); stop_stream() first")
        target, speed = self._check_move(target, speed)
        cfg, link = self._cfg, self._link
        before = self.read_sample()
        self._movable(before)
        rot = cfg.tool_rotvec if cfg.tool_rotvec is not None else before.values["actual_TCP_pose"][3:]
        script = urscript.movel([*target, *rot], cfg.acceleration_m_s2, speed)
        with link.cond:
            n_msg, t_sent = link.stats["messages"], time.monotonic()
        self._send_script(script, "movel")
        self.stats["moves_sent"] += 1
        self._await_arrival(target, n_msg, t_sent)
        self.stats["moves_arrived"] += 1

    # --- streaming (drivers.base.SetpointStreamer) ---------------------------------------
    def start_stream(self, rate_hz: float, lookahead_s: float = 0.1, gain: float = 300.0) -> None:
        """Start following set-points: hold the current pose, send the servo program, wait until it runs.

        Parameters
        ----------
        rate_hz : float
            Set-points per second (<= 500 Hz); the servoj period is 1/rate_hz.
        lookahead_s : float
            servoj's look-ahead time (s).
        gain : float
            servoj's gain.

        Raises
        ------
        ConfigError
            When ``stream.enabled`` is false.
        StateError
            When the driver is not ``active`` or a stream is running.
        DriverError
            When a parameter is out of range, the robot cannot move, the driver is aborted, or the
            controller refuses the program or does not report it running within ``timeout_s``.
        """
        self._require("active")
        self._check_abort()
        cfg, link = self._cfg, self._link
        if not cfg.stream.enabled:
            raise ConfigError(self._source, "stream.enabled", False, "true to stream set-points (the input "
                              "registers of `stream` are then claimed at activate)")
        if self._stream is not None and not self._stream.stopped:
            raise StateError(f"{self.name}: a stream is running; stop_stream() first")
        rate, la, g = check_stream_params(rate_hz, lookahead_s, gain, rp.MAX_FREQUENCY_HZ)
        s = self.read_sample()
        self._movable(s)
        pose = tuple(float(x) for x in s.values["actual_TCP_pose"])
        rot = tuple(cfg.tool_rotvec) if cfg.tool_rotvec is not None else pose[3:]
        st = cfg.stream
        cycles = st.watchdog_cycles if st.watchdog_cycles is not None else math.ceil(WATCHDOG_S * rate)
        program = urscript.ServoProgram(st.double_register, st.seq_register, st.status_register, 1.0 / rate, la, g,
                                        cycles, st.stop_deceleration)
        stream = _Stream(program, rate, rot, np.array(pose[:3]))
        link.write_inputs([stream.seq, *pose[:3], *rot])  # where the arm is: the first cycle holds it
        self._await_register(f"input_int_register_{st.seq_register}", stream.seq)  # before the program reads it
        with link.cond:
            n_msg, t_sent = link.stats["messages"], time.monotonic()
        self._send_script(urscript.servo_program(program), "servo program")
        self._await_program(n_msg, t_sent)
        self._stream = stream
        self.stats["streams"] += 1

    def _await_register(self, name: str, value: int) -> None:
        """Wait (up to timeout_s) until a package shows the register holding `value`."""
        cfg = self._cfg
        if self._await(lambda s: True if s is not None and s.values.get(name) == value else None,
                       time.monotonic() + cfg.timeout_s):
            return
        s = self._link.latest
        raise DriverError(f"{self.name}: the controller does not show {name} = {value} within "
                          f"{cfg.timeout_s} s (it reads {None if s is None else s.values.get(name)})")

    def _await_program(self, n_msg: int, t_sent: float) -> None:
        """Wait (up to timeout_s) for a package, received after the program was sent, that shows it running."""
        cfg = self._cfg
        reg = f"output_int_register_{cfg.stream.status_register}"

        def running(s: RtdeSample | None) -> bool | None:
            errors = self._errors_since(n_msg)
            if errors:
                raise DriverError(f"{self.name}: the controller refused the servo program: "
                                  f"{errors[0].source}: {errors[0].message}")
            return True if (s is not None and s.t_host > t_sent and s.values.get(reg) == urscript.STREAM_RUNNING
                            and s.values["runtime_state"] == rp.RUNTIME_PLAYING) else None

        if self._await(running, t_sent + cfg.timeout_s):
            return
        s = self._link.latest
        raise DriverError(f"{self.name}: the servo program did not report running ({reg} = "
                          f"{None if s is None else s.values.get(reg)}) within {cfg.timeout_s} s")

    def _stream_refusal(self, stream: _Stream) -> str:
        """Why the controller will not take another set-point now ('' if it will), from the newest package."""
        link = self._link
        if not link.connected:
            return f"the RTDE connection is down ({link.last_error or 'reconnecting'})"
        s = link.latest
        if s is None:
            return "no RTDE package yet"
        v = s.values
        if v["safety_mode"] not in _MOVABLE_SAFETY:
            name = rp.SAFETY_MODES.get(v["safety_mode"], str(v["safety_mode"]))
            what = "protective stop" if v["safety_mode"] == rp.SAFETY_PROTECTIVE_STOP else f"safety stop ({name})"
            return (f"{what}: the arm stopped at {np.round(v['actual_TCP_pose'][:3], 6).tolist()} m (safety mode "
                    f"{name}); clear it and start_stream again")
        state = v.get(f"output_int_register_{stream.program.status_register}")
        if state == urscript.STREAM_WATCHDOG:
            return f"{_WATCHDOG_WHY}: no new set-point for {stream.program.watchdog_cycles} control cycles"
        if state == urscript.STREAM_RUNNING and v["runtime_state"] != rp.RUNTIME_PLAYING:
            return "the servo program is no longer running"
        return ""

    def stream(self, target: np.ndarray, t: float) -> None:
        """Write one set-point (pose and next sequence number) as one RTDE input package; never waits.

        A refusal stops the stream for good: the controller's watchdog stops the arm, and
        ``start_stream`` starts again from where it stands.

        Parameters
        ----------
        target : ndarray
            (3,) m, base frame.
        t : float
            s, increasing.

        Raises
        ------
        StateError
            When the driver is not ``active`` or no stream was started.
        DriverError
            Naming the reason, nothing sent: the set-point is out of the limits, ``t`` does not
            increase, the step exceeds ``limits.max_speed_m_s``, the newest package shows a safety stop
            or the program stopped (watchdog: WatchdogStop, a DriverError) or ended, the RTDE connection
            is down, or the driver is aborted.
        """
        self._require("active")
        self._check_abort()
        stream = self._stream
        if stream is None:
            raise StateError(f"{self.name}: stream() before start_stream()")
        cfg = self._cfg
        target = np.asarray(target, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)) or np.any(np.abs(target) > cfg.limits.tcp_abs_m):
            raise DriverError(f"invalid set-point {target!r}: need 3 finite coordinates within "
                              f"±{cfg.limits.tcp_abs_m} m")
        t = float(t)
        if stream.last_t is not None:
            if not t > stream.last_t:
                raise DriverError(f"set-point time {t} s does not follow the last one ({stream.last_t} s)")
            speed = float(np.linalg.norm(target - stream.last_p)) / (t - stream.last_t)
            if speed > cfg.limits.max_speed_m_s:
                raise DriverError(f"set-point {np.round(target, 6).tolist()} m at {t} s: {speed:.3f} m/s from the "
                                  f"last one exceeds limits.max_speed_m_s {cfg.limits.max_speed_m_s}")
        why = stream.stopped or self._stream_refusal(stream)
        if why:
            stream.stopped = why
            self.stats["refused"] += 1
            err = WatchdogStop if why.startswith(_WATCHDOG_WHY) else DriverError
            raise err(f"{self.name}: set-point {stream.sent + 1} not sent: {why} "
                      f"({stream.sent} sent, the controller took {self._consumed(stream)})")
        try:
            self._link.write_inputs([stream.seq + 1, *target, *stream.rot])
        except DriverError as exc:  # the connection went down since the check: stopped all the same
            stream.stopped = f"the RTDE connection is down ({exc})"
            self.stats["refused"] += 1
            raise DriverError(f"{self.name}: set-point {stream.sent + 1} not sent: {stream.stopped}") from exc
        stream.seq += 1
        stream.sent += 1
        stream.last_t, stream.last_p = t, target
        self.stats["setpoints_sent"] += 1

    def _consumed(self, stream: _Stream) -> int:
        s = self._link.latest
        v = None if s is None else s.values.get(f"output_int_register_{stream.program.echo_register}")
        return -1 if v is None else max(int(v) - 1, 0)  # sequence 1 is start_stream's hold

    def stop_stream(self) -> None:
        """Sequence -1: the program stops the arm and ends; waits (up to timeout_s) until it has."""
        self._require("active")
        stream, self._stream = self._stream, None
        if stream is None:
            return
        cfg, link = self._cfg, self._link
        if stream.stopped or not link.connected:
            return
        t_sent = time.monotonic()
        link.write_inputs([-1, *stream.last_p, *stream.rot])
        reg = f"output_int_register_{stream.program.status_register}"
        if self._await(lambda s: True if s is not None and s.t_host > t_sent and (
                s.values.get(reg) != urscript.STREAM_RUNNING or s.values["runtime_state"] != rp.RUNTIME_PLAYING)
                else None, t_sent + cfg.timeout_s):
            return
        raise DriverError(f"{self.name}: the servo program did not stop within {cfg.timeout_s} s of the host's stop")

    def stream_status(self) -> StreamStatus:
        """What the driver knows of its stream, from the newest package.

        Returns
        -------
        StreamStatus
            ``idle`` when no stream was started (or it was stopped by the host).
        """
        stream = self._stream
        if stream is None:
            return StreamStatus("idle")
        why = stream.stopped or self._stream_refusal(stream)
        p = stream.program
        return StreamStatus("stopped" if why else "streaming", stream.sent, self._consumed(stream), why,
                            stream.rate_hz, p.lookahead_s, p.gain)

    def _send_script(self, script: str, what: str) -> None:
        """One program to the script port on a fresh connection; never retried (it may have arrived)."""
        cfg = self._cfg
        try:
            with socket.create_connection((cfg.host, cfg.script_port), timeout=cfg.timeout_s) as sock:
                sock.sendall(script.encode("ascii"))
                sock.shutdown(socket.SHUT_WR)
        except OSError as exc:
            raise DriverError(f"{self.name} at {cfg.host}:{cfg.script_port}: {what} not sent ({exc}); "
                              "not retried, since part of it may have arrived") from exc

    def _await_arrival(self, target: np.ndarray, n_msg: int, t_sent: float) -> None:
        cfg = self._cfg
        last: RtdeSample | None = None

        def arrived_or_aborted(s: RtdeSample | None) -> str | None:
            nonlocal last
            if self.abort_event.is_set():
                return "aborted"
            errors = self._errors_since(n_msg)
            if errors:
                raise DriverError(f"{self.name}: the controller refused the move to {target.tolist()} m: "
                                  f"{errors[0].source}: {errors[0].message}")
            if s is not None and s.t_host > t_sent:
                last = s
                if self._arrived(s, target):
                    return "arrived"
            return None

        got = self._await(arrived_or_aborted, t_sent + cfg.move_timeout_s)
        if got == "arrived":
            return
        if got is None:
            where = "no package since the move was sent" if last is None else \
                f"TCP at {np.round(last.values['actual_TCP_pose'][:3], 6).tolist()} m"
            raise DriverError(f"{self.name}: movel to {target.tolist()} m did not arrive within "
                              f"{cfg.move_timeout_s} s ({where}); not re-sent")
        # aborted: stop the arm (best effort) outside the lock, then report
        try:
            self._send_script(urscript.stopl(max(cfg.acceleration_m_s2, 1.0)), "stopl")
        except DriverError:
            pass
        self._check_abort()

    def _arrived(self, s: RtdeSample, target: np.ndarray) -> bool:
        v = s.values
        safety = v["safety_mode"]
        if safety not in _MOVABLE_SAFETY:
            name = rp.SAFETY_MODES.get(safety, str(safety))
            what = "protective stop" if safety == rp.SAFETY_PROTECTIVE_STOP else f"safety stop ({name})"
            raise DriverError(f"{self.name}: {what} during movel to {target.tolist()} m: the arm stopped at "
                              f"{np.round(v['actual_TCP_pose'][:3], 6).tolist()} m (safety mode {name}); "
                              "the move is not re-sent")
        cfg = self._cfg
        close = float(np.linalg.norm(np.asarray(v["actual_TCP_pose"][:3]) - target)) <= cfg.arrival_tol_m
        still = float(np.linalg.norm(v["actual_TCP_speed"][:3])) <= cfg.still_m_s
        return close and still and v["runtime_state"] != rp.RUNTIME_PLAYING

