"""Robot controller over a serial line (pyserial), speaking `drivers.serial.protocol`.

The same code talks to a real port (`/dev/ttyUSB0`), a pseudo-terminal served by
`sim.controller_emulator.ControllerEmulator` (`/dev/pts/N`) or a TCP bridge
(`socket://host:port`), since the port is opened with `serial.serial_for_url`.

`SerialLink` is the host side of the protocol (sequence numbers, acknowledgements, retries,
stale-reply discard, reconnection); `drivers.serial_tracker` reuses it.

Config keys (validated once into frozen objects; errors name key, value and what is allowed):
`url` (required), `baudrate` (115200), `timeout_s` (0.5, per reply), `move_timeout_s` (30, a
MOVL reply comes when the arm has settled), `retries` (3, retransmissions after the first
try), `reconnect_after` (2, consecutive time-outs before the port is closed and reopened),
`limits`: `tcp_abs_m` (3.0, |x|,|y|,|z| bound for targets and received TCPs),
`max_speed_m_s` (2.0), `joint_abs_rad` (2 pi), `n_joints` (6).
"""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Mapping

import numpy as np
import serial
from pydantic import Field

from drivers.base import JointState, Lifecycle
from drivers.serial import protocol as lp
from dt_kernel.config import Frozen, validate
from dt_kernel.errors import DriverError, UnreachableError

_POLL_S = 0.02  # pyserial read granularity while waiting for a reply


class LinkConfig(Frozen):
    url: str = Field(min_length=1)
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0, le=60)
    move_timeout_s: float = Field(30.0, gt=0, le=3600)
    retries: int = Field(3, ge=0, le=100)
    reconnect_after: int = Field(2, ge=1, le=100)


class ControllerLimits(Frozen):
    tcp_abs_m: float = Field(3.0, gt=0)
    max_speed_m_s: float = Field(2.0, gt=0)
    joint_abs_rad: float = Field(2 * math.pi, gt=0)
    n_joints: int = Field(6, ge=1, le=32)


class ControllerConfig(LinkConfig):
    limits: ControllerLimits = ControllerLimits()


class SerialLink:
    """Host side of the line protocol: one request in flight, retried until acknowledged."""

    def __init__(self, cfg: LinkConfig, device: str = "device"):
        self.cfg, self.device = cfg, device
        self._port: serial.SerialBase | None = None
        self._lines = lp.LineBuffer()
        self._seq = 0
        self._lock = threading.Lock()
        self.stats = {k: 0 for k in ("requests", "retries", "timeouts", "reconnects", "stale",
                                     "corrupt", "garbage", "naks")}

    # --- port ---------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        if self.is_open:
            return
        try:
            port = serial.serial_for_url(self.cfg.url, baudrate=self.cfg.baudrate,
                                         timeout=_POLL_S, write_timeout=max(self.cfg.timeout_s, 0.5))
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"{self.device}: cannot open {self.cfg.url!r}: {exc}") from exc
        self._port = port
        self._lines.clear()

    def close(self) -> None:
        port, self._port = self._port, None
        self._lines.clear()
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # closing a dead port: nothing left to release

    def reconnect(self) -> None:
        self.stats["reconnects"] += 1
        self.close()
        self.open()

    # --- transactions -------------------------------------------------------------------
    def request(self, word: str, *fields: Any, timeout_s: float | None = None) -> lp.Frame:
        """Send one request and return its ACK or non-retryable NAK frame.

        Raises DriverError when no valid reply came after `1 + retries` attempts.
        """
        with self._lock:
            seq, self._seq = self._seq, lp.next_seq(self._seq)
            frame = lp.encode(seq, word, *fields)
            wait = self.cfg.timeout_s if timeout_s is None else timeout_s
            self.stats["requests"] += 1
            timeouts_in_row, problem, cause = 0, "", None
            for attempt in range(1 + self.cfg.retries):
                if attempt:
                    self.stats["retries"] += 1
                try:
                    if not self.is_open:
                        self.open()
                    self._write(frame)
                    reply = self._await(seq, time.monotonic() + wait)
                except DriverError as exc:  # port vanished or I/O failed: reopen next attempt
                    problem, cause = str(exc), exc
                    self.close()
                    time.sleep(min(wait, 0.1))
                    continue
                if reply is None:
                    self.stats["timeouts"] += 1
                    timeouts_in_row += 1
                    problem = f"no reply within {wait} s"
                    if timeouts_in_row >= self.cfg.reconnect_after:
                        timeouts_in_row = 0
                        try:
                            self.reconnect()
                        except DriverError as exc:
                            problem, cause = str(exc), exc
                    continue
                timeouts_in_row = 0
                if reply == "corrupt":
                    problem = "reply failed its checksum"
                    continue
                if reply.is_nak:
                    self.stats["naks"] += 1
                    if reply.nak_reason in lp.RETRYABLE_NAKS:
                        problem = f"NAK {reply.nak_reason}"
                        continue
                return reply
            raise DriverError(f"{self.device} at {self.cfg.url}: {word} (seq {seq}) failed after "
                              f"{1 + self.cfg.retries} attempts; last problem: {problem}") from cause

    def _write(self, frame: bytes) -> None:
        try:
            self._port.write(frame)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"{self.device}: write failed: {exc}") from exc

    def _await(self, seq: int, deadline: float) -> lp.Frame | str | None:
        """The reply to `seq`, 'corrupt' for a frame that failed its CRC, None on time-out."""
        while True:
            try:
                data = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError) as exc:
                raise DriverError(f"{self.device}: read failed: {exc}") from exc
            for line in self._lines.feed(data) if data else ():
                try:
                    frame = lp.decode(line)
                except lp.ChecksumError:
                    self.stats["corrupt"] += 1
                    return "corrupt"  # retransmit at once; the device answers duplicates from cache
                except lp.FrameError:
                    self.stats["garbage"] += 1
                    continue
                if frame.seq != seq or frame.word not in (lp.ACK, lp.NAK):
                    self.stats["stale"] += 1  # answer to an earlier, abandoned request
                    continue
                return frame
            if time.monotonic() >= deadline:
                return None


def refused(device: str, word: str, reply: lp.Frame) -> DriverError:
    text = ",".join(reply.fields[1:])
    if reply.nak_reason == lp.NAK_UNREACHABLE:
        return UnreachableError(f"{device}: {word} refused, target unreachable: {text}")
    return DriverError(f"{device}: {word} refused with NAK {reply.nak_reason}: {text}")


def ack_fields(device: str, word: str, reply: lp.Frame, n: int | None = None) -> tuple[str, ...]:
    if not reply.is_ack:
        raise refused(device, word, reply)
    if n is not None and len(reply.fields) != n:
        raise DriverError(f"{device}: {word} reply has {len(reply.fields)} fields, expected {n}")
    return reply.fields


class SerialController(Lifecycle):
    """RobotController over the line protocol (see module docstring for the config keys)."""

    name = "serial controller"

    def __init__(self, config: Mapping[str, Any] | None = None, source: str = "<serial controller config>"):
        self._source = source
        self.cfg: ControllerConfig | None = None
        self.link: SerialLink | None = None
        if config is not None:
            self.configure(config)

    # --- lifecycle hooks ----------------------------------------------------------------
    def _on_configure(self, config: dict[str, Any]) -> None:
        self.cfg = validate(ControllerConfig, config, self._source)
        self.link = SerialLink(self.cfg, self.name)

    def _on_activate(self) -> None:
        self.link.open()
        try:
            self.ping()
        except DriverError:
            self.link.close()
            raise

    def _on_deactivate(self) -> None:
        self.link.close()

    def _on_close(self) -> None:
        if self.link is not None:
            self.link.close()

    # --- protocol -----------------------------------------------------------------------
    def ping(self) -> str:
        """Handshake; returns the device name. Checks the protocol version."""
        reply = self.link.request("PING")
        f = ack_fields(self.name, "PING", reply)
        if not f or f[0] != lp.PROTOCOL_VERSION:
            raise DriverError(f"{self.name}: protocol version {f[:1]} not supported (need {lp.PROTOCOL_VERSION})")
        return f[1] if len(f) > 1 else ""

    def _check_move(self, target, speed) -> tuple[np.ndarray, float]:
        lim = self.cfg.limits
        target = np.asarray(target, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)) or np.any(np.abs(target) > lim.tcp_abs_m):
            raise DriverError(f"invalid move target {target!r}: need 3 finite coordinates within ±{lim.tcp_abs_m} m")
        speed = float(speed)
        if not (math.isfinite(speed) and 0.0 < speed <= lim.max_speed_m_s):
            raise DriverError(f"invalid speed {speed!r}: need 0 < speed <= {lim.max_speed_m_s} m/s")
        return target, speed

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        self._require("active")
        target, speed = self._check_move(target, speed)
        reply = self.link.request("MOVL", *map(float, target), speed, timeout_s=self.cfg.move_timeout_s)
        ack_fields(self.name, "MOVL", reply, 0)

    def stream_setpoint(self, target: np.ndarray, speed: float) -> None:
        self._require("active")
        target, speed = self._check_move(target, speed)
        ack_fields(self.name, "SETP", self.link.request("SETP", *map(float, target), speed), 0)

    def read_joint_state(self) -> JointState:
        self._require("active")
        lim = self.cfg.limits
        f = ack_fields(self.name, "GETJ", self.link.request("GETJ"), 1 + lim.n_joints)
        t = lp.parse_float(f[0], "GETJ t")
        q = np.array([lp.parse_float(v, f"GETJ q{i + 1}", -lim.joint_abs_rad, lim.joint_abs_rad)
                      for i, v in enumerate(f[1:])])
        return JointState(q=q, t=t)

    def read_commanded_tcp(self) -> np.ndarray:
        self._require("active")
        b = self.cfg.limits.tcp_abs_m
        f = ack_fields(self.name, "GETT", self.link.request("GETT"), 4)
        lp.parse_float(f[0], "GETT t")
        return np.array([lp.parse_float(v, f"GETT {a}", -b, b) for a, v in zip("xyz", f[1:])])

    def status(self) -> dict[str, Any]:
        """The controller's state ('idle', 'moving', 'fault') and its count of finished moves."""
        self._require("active")
        f = ack_fields(self.name, "STATUS", self.link.request("STATUS"), 2)
        return {"state": lp.parse_status(f[0]), "moves": int(lp.parse_float(f[1], "STATUS moves", 0))}
