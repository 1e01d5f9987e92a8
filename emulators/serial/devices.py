"""Serial device emulators: a robot controller and a laser tracker serving `drivers.serial.protocol`
on a pseudo-terminal or a loopback TCP port, answering from a background thread so the real
drivers talk to them exactly as to hardware; faults are injected by probability or one-shot.
The plant interface, the faults and the protocol: docs/drivers.md ("Serial line protocol")."""
from __future__ import annotations

import math
import os
import select
import socket
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.serial import protocol as lp
from dt_kernel.errors import ConfigError, UnreachableError

FAULT_KINDS = ("garbage", "half_frame", "drop", "stale", "corrupt_reply", "corrupt_request", "nan")


@dataclass(frozen=True)
class Faults:
    """Per-reply probabilities of each fault (0 = never); drawn from one seeded generator."""

    garbage: float = 0.0
    half_frame: float = 0.0
    drop: float = 0.0
    stale: float = 0.0
    corrupt_reply: float = 0.0
    corrupt_request: float = 0.0
    nan: float = 0.0
    seed: int = 0

    def __post_init__(self):
        for k in FAULT_KINDS:
            p = getattr(self, k)
            if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
                raise ConfigError("<emulator faults>", k, p, "a probability in [0, 1]")


class _PtyEndpoint:
    """Master side of a pseudo-terminal; the emulator keeps the slave open so the device
    survives the driver closing and reopening it (reconnection)."""

    def __init__(self):
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self.master)
        self.port = os.ttyname(self._slave)

    def wait_readable(self, timeout: float) -> bool:
        r, _, _ = select.select([self.master], [], [], timeout)
        return bool(r)

    def read(self) -> bytes:
        try:
            return os.read(self.master, 4096)
        except OSError:  # EIO while no slave is open: nothing to read
            time.sleep(0.01)
            return b""

    def write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except OSError:
            pass  # nobody listening: the bytes are lost, as on a wire

    def close(self) -> None:
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class _TcpEndpoint:
    """One-client-at-a-time TCP server on loopback, reached with pyserial's socket:// URL."""

    def __init__(self, host: str, port: int):
        self._srv = socket.create_server((host, port))
        self._srv.setblocking(False)
        self._conn: socket.socket | None = None
        h, p = self._srv.getsockname()[:2]
        self.port = f"socket://{h}:{p}"

    def wait_readable(self, timeout: float) -> bool:
        sock = self._conn or self._srv
        r, _, _ = select.select([sock], [], [], timeout)
        if r and self._conn is None:
            try:
                self._conn, _ = self._srv.accept()
                self._conn.setblocking(True)
                self._conn.settimeout(1.0)
            except OSError:
                pass
            return False
        return bool(r)

    def read(self) -> bytes:
        if self._conn is None:
            return b""
        try:
            data = self._conn.recv(4096)
        except OSError:
            data = b""
        if not data:  # client hung up; wait for the next one
            self._drop()
        return data

    def write(self, data: bytes) -> None:
        if self._conn is not None:
            try:
                self._conn.sendall(data)
            except OSError:
                self._drop()

    def _drop(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
        self._conn = None

    def close(self) -> None:
        self._drop()
        self._srv.close()


def _open_endpoint(spec: str | None):
    if spec in (None, "pty"):
        return _PtyEndpoint()
    if isinstance(spec, str) and spec.startswith("tcp://"):
        host, _, port = spec[len("tcp://"):].rpartition(":")
        try:
            return _TcpEndpoint(host or "127.0.0.1", int(port))
        except (ValueError, OSError) as exc:
            raise ConfigError("<emulator>", "port_path_or_pty", spec, "tcp://HOST:PORT") from exc
    raise ConfigError("<emulator>", "port_path_or_pty", spec, "None or 'pty' (new pseudo-terminal), or 'tcp://HOST:PORT'")


class LineServer:
    """Protocol server core: framing, duplicate cache, fault injection, background thread.

    Subclasses implement ``handle(frame) -> (fields, after)``: the ACK fields and an optional
    callable to run after the ACK went out (streamed set-points).

    Parameters
    ----------
    port_path_or_pty : str or None
        None or ``"pty"``: a new pseudo-terminal; ``"tcp://HOST:PORT"``: a loopback TCP port.
    faults : Faults or None
        Per-reply fault probabilities (none by default).
    clock : callable or None
        () -> s, the device's clock (s since construction by default).
    autostart : bool
        Start serving at once.

    Raises
    ------
    ConfigError
        When ``port_path_or_pty`` is none of those forms or the port cannot be opened.
    """

    device = "line-device"

    def __init__(self, port_path_or_pty: str | None = None, faults: Faults | None = None,
                 clock: Callable[[], float] | None = None, autostart: bool = True):
        self.faults = faults or Faults()
        self._rng = np.random.default_rng([self.faults.seed, 7301])
        self._t0 = time.monotonic()
        self._clock = clock or (lambda: time.monotonic() - self._t0)
        self._ep = _open_endpoint(port_path_or_pty)
        self._lines = lp.LineBuffer()
        self._oneshot: dict[str, int] = {k: 0 for k in FAULT_KINDS}
        self._lock = threading.Lock()
        self._paused_until = 0.0
        self._stop = threading.Event()
        self._last: tuple[int, bytes, bytes] | None = None  # seq, request body, reply frame
        self._history: deque[bytes] = deque(maxlen=8)
        self.stats = {"requests": 0, "replies": 0, "garbage_in": 0, "nak_crc": 0, "duplicates": 0}
        self._thread = threading.Thread(target=self._serve, name=type(self).__name__, daemon=True)
        if autostart:
            self._thread.start()

    # --- public -------------------------------------------------------------------------
    @property
    def port(self) -> str:
        """What pyserial opens: the pseudo-terminal's path (``/dev/pts/N``) or a ``socket://`` URL."""
        return self._ep.port

    def pause(self, seconds: float) -> None:
        """Stop answering (and drop whatever arrives) for a while, then come back.

        Parameters
        ----------
        seconds : float
        """
        self._paused_until = time.monotonic() + float(seconds)

    def inject(self, kind: str, count: int = 1) -> None:
        """Inject a fault into the next replies (one-shot, on top of the probabilities).

        Parameters
        ----------
        kind : str
            One of FAULT_KINDS.
        count : int
            How many replies it hits.

        Raises
        ------
        ConfigError
            When ``kind`` is not a fault kind.
        """
        if kind not in FAULT_KINDS:
            raise ConfigError("<emulator>", "fault", kind, "one of " + ", ".join(FAULT_KINDS))
        with self._lock:
            self._oneshot[kind] += int(count)

    def stop(self) -> None:
        """Stop serving and close the port (once)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._ep.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def now(self) -> float:
        """The device's clock (s)."""
        return float(self._clock())

    # --- fault decisions ----------------------------------------------------------------
    def _fault(self, kind: str) -> bool:
        with self._lock:
            if self._oneshot[kind] > 0:
                self._oneshot[kind] -= 1
                return True
        p = getattr(self.faults, kind)
        return p > 0 and self._rng.random() < p

    # --- serving ------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._ep.wait_readable(0.02):
                continue
            data = self._ep.read()
            if not data:
                continue
            if time.monotonic() < self._paused_until:
                self._lines.clear()
                continue
            for line in self._lines.feed(data):
                self._on_line(line)

    def _on_line(self, line: bytes) -> None:
        try:
            req = lp.decode(line)
            if self._fault("corrupt_request"):
                raise lp.ChecksumError("injected request corruption", req.seq)
        except lp.ChecksumError as exc:
            if exc.seq is not None:
                self.stats["nak_crc"] += 1
                self._send(lp.encode(exc.seq, lp.NAK, lp.NAK_CRC), cache=None)
            else:
                self.stats["garbage_in"] += 1
            return
        except lp.FrameError:
            self.stats["garbage_in"] += 1  # noise on the line: ignored, the host will retry
            return
        self.stats["requests"] += 1
        body = line[line.rfind(b"$"):].rstrip(b"\r\n")
        if self._last is not None and self._last[0] == req.seq and self._last[1] == body:
            self.stats["duplicates"] += 1  # retransmission: answer again, do not execute again
            self._send(self._last[2], cache=None)
            return
        after = None
        try:
            fields, after = self.handle(req)
            reply = lp.encode(req.seq, lp.ACK, *fields)
        except _Nak as nak:
            reply = lp.encode(req.seq, lp.NAK, nak.reason, lp.sanitize(nak.text))
        except UnreachableError as exc:
            reply = lp.encode(req.seq, lp.NAK, lp.NAK_UNREACHABLE, lp.sanitize(str(exc)))
        except Exception as exc:  # the plant failed: report it, keep serving
            reply = lp.encode(req.seq, lp.NAK, lp.NAK_FAULT, lp.sanitize(f"{type(exc).__name__}: {exc}"))
        self._send(reply, cache=(req.seq, body))
        if after is not None:
            try:
                after()
            except Exception:
                pass  # a streamed set-point that fails shows up in STATUS as 'fault'

    def _send(self, reply: bytes, cache: tuple[int, bytes] | None) -> None:
        if cache is not None:
            self._last = (cache[0], cache[1], reply)
        if self._fault("garbage"):
            noise = bytes(self._rng.integers(33, 127, 12, dtype=np.uint8)).replace(b"$", b"#")
            self._ep.write(b"\x00\xff" + noise + b"\n")
        if self._fault("stale") and self._history:
            self._ep.write(self._history[0])
        if self._fault("half_frame"):
            self._ep.write(reply[: len(reply) // 2])
        self._history.append(reply)
        if self._fault("drop"):
            return
        if self._fault("corrupt_reply"):
            b = bytearray(reply)
            i = 2 if len(b) > 4 else 0
            b[i] = ord("9") if b[i] != ord("9") else ord("8")
            reply = bytes(b)
        self.stats["replies"] += 1
        self._ep.write(reply)

    def _numbers(self, values) -> list[float]:
        out = [float(v) for v in values]
        if out and self._fault("nan"):
            out[-1] = math.nan
        return out

    # --- to override --------------------------------------------------------------------
    def handle(self, req: lp.Frame) -> tuple[list[Any], Callable[[], None] | None]:
        """Answer one request: PING here; subclasses add their commands.

        Parameters
        ----------
        req : Frame
            The decoded request.

        Returns
        -------
        fields : list
            The ACK's fields.
        after : callable or None
            Run after the ACK went out.
        """
        if req.word == "PING":
            return [lp.PROTOCOL_VERSION, self.device], None
        raise _Nak(lp.NAK_UNKNOWN, req.word)


class _Nak(Exception):
    def __init__(self, reason: str, text: str = ""):
        super().__init__(reason)
        self.reason, self.text = reason, text


def _args(req: lp.Frame, n: int) -> list[float]:
    if len(req.fields) != n:
        raise _Nak(lp.NAK_SYNTAX, f"{req.word} takes {n} fields")
    try:
        vals = [float(f) for f in req.fields]
    except ValueError:
        raise _Nak(lp.NAK_SYNTAX, "field is not a number") from None
    if not all(math.isfinite(v) for v in vals):
        raise _Nak(lp.NAK_RANGE, "non-finite argument")
    return vals


class ControllerEmulator(LineServer):
    """Robot controller serving MOVL, SETP, GETJ, GETT, STATUS and PING over a plant.

    Parameters
    ----------
    plant : object
        With ``move_linear(target, speed)``, ``joint_angles()`` and ``controller_tcp()``
        (m, m/s, rad; e.g. sim.plant.SimulatedCobot).
    port_path_or_pty, faults, clock, autostart
        As LineServer.
    plant_lock : threading.Lock or None
        Held around every plant call; pass the one the rest of the simulation uses.
    workspace_m : float
        Largest |coordinate| of a target (m); beyond it, NAK RANGE.
    max_speed_m_s : float
        Fastest speed (m/s); beyond it, NAK RANGE.
    """

    device = "cobot-controller-emulator"

    def __init__(self, plant, port_path_or_pty: str | None = None, faults: Faults | None = None,
                 clock: Callable[[], float] | None = None, plant_lock: threading.Lock | None = None,
                 workspace_m: float = 3.0, max_speed_m_s: float = 2.0, autostart: bool = True):
        self.plant = plant
        self.plant_lock = plant_lock or threading.Lock()
        self.workspace_m, self.max_speed_m_s = float(workspace_m), float(max_speed_m_s)
        self._mode, self._moves = "idle", 0
        super().__init__(port_path_or_pty, faults, clock, autostart)

    def _move(self, target: np.ndarray, speed: float) -> None:
        self._mode = "moving"
        try:
            with self.plant_lock:
                self.plant.move_linear(target, speed)
        except Exception:
            self._mode = "fault"
            raise
        self._moves += 1
        self._mode = "idle"

    def handle(self, req: lp.Frame):
        """Answer MOVL (move, then ACK), SETP (ACK, then move), GETJ, GETT, STATUS or PING.

        Parameters
        ----------
        req : Frame

        Returns
        -------
        fields : list
        after : callable or None
            For SETP, the move.
        """
        w = req.word
        if w in ("MOVL", "SETP"):
            x, y, z, v = _args(req, 4)
            target = np.array([x, y, z])
            if np.any(np.abs(target) > self.workspace_m) or not 0.0 < v <= self.max_speed_m_s:
                raise _Nak(lp.NAK_RANGE, "target or speed outside the controller limits")
            if w == "MOVL":
                self._move(target, v)
                return [], None
            return [], lambda: self._move(target, v)
        if w == "GETJ":
            _args(req, 0)
            with self.plant_lock:
                q = np.asarray(self.plant.joint_angles(), dtype=float)
            return [self.now(), *self._numbers(q)], None
        if w == "GETT":
            _args(req, 0)
            with self.plant_lock:
                p = np.asarray(self.plant.controller_tcp(), dtype=float)
            return [self.now(), *self._numbers(p)], None
        if w == "STATUS":
            return [self._mode, self._moves], None
        return super().handle(req)


class TrackerEmulator(LineServer):
    """Laser tracker serving MEAS, STATUS and PING.

    Parameters
    ----------
    measure_fn : callable
        () -> (d m, azimuth rad, elevation rad, status).
    port_path_or_pty, faults, clock, autostart
        As LineServer.
    lock : threading.Lock or None
        Held around every ``measure_fn`` call.
    """

    device = "laser-tracker-emulator"

    def __init__(self, measure_fn: Callable[[], tuple[float, float, float, str]],
                 port_path_or_pty: str | None = None, faults: Faults | None = None,
                 clock: Callable[[], float] | None = None, lock: threading.Lock | None = None,
                 autostart: bool = True):
        self.measure_fn = measure_fn
        self.lock = lock or threading.Lock()
        self._n = 0
        super().__init__(port_path_or_pty, faults, clock, autostart)

    def handle(self, req: lp.Frame):
        """Answer MEAS (t, d, az, el, status), STATUS (ready, measurements) or PING.

        Parameters
        ----------
        req : Frame

        Returns
        -------
        fields : list
        after : None
        """
        if req.word == "MEAS":
            _args(req, 0)
            with self.lock:
                d, az, el, status = self.measure_fn()
            self._n += 1
            return [self.now(), *self._numbers([d, az, el]), lp.sanitize(status, 32)], None
        if req.word == "STATUS":
            return ["ready", self._n], None
        return super().handle(req)


__all__ = ["ControllerEmulator", "TrackerEmulator", "Faults", "LineServer", "FAULT_KINDS"]
