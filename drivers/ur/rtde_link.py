"""Host side of RTDE: `RtdeLink` connects, negotiates protocol version 2, sets up the output (and
optionally input) recipe and starts, then reads data packages on a background thread that
reconnects when the stream is lost. Setup errors of the first connection fail the caller (an
unknown output or a register IN_USE is a ConfigError naming it); socket errors become DriverError
here and only here. Behaviour and faults: docs/drivers.md ("Universal Robots over RTDE")."""
from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.ur import protocol as rp
from dt_kernel.errors import ConfigError, DriverError


@dataclass(frozen=True)
class RtdeSample:
    """One data package: `values` by field name (vectors as tuples), device and host times (s)."""

    values: dict[str, Any]
    t_device: float  # RTDE `timestamp`: the controller's clock
    t_host: float  # time.monotonic() when the package was read
    seq: int  # count of packages read by this link (across reconnections)


class RtdeLink:
    """One RTDE connection to a controller, kept alive by a reader thread.

    The newest package is ``latest`` (an RtdeSample; ``cond`` is notified on every package, text
    message and (dis)connection), the controller's text messages are ``messages`` (the newest 100),
    and ``stats`` counts packages, connects, drops, stale streams, messages and input packages sent.

    Parameters
    ----------
    host : str
        The controller's address.
    port : int
        The RTDE port (30004).
    names : sequence of str
        The output recipe's fields.
    frequency_hz : float
        The output frequency (Hz).
    timeout_s : float
        Connect and each setup reply (s).
    stale_after_s : float
        A stream without a data package this long is dropped and reconnected (s).
    reconnect_interval_s : float
        Between reconnection attempts (s).
    source : str
        Names the config in ConfigErrors.
    device : str
        Names the device in errors.
    inputs : sequence of str
        Input registers the host writes (an input recipe is set up when given).
    input_source_key : str
        The config key named when an input register is refused.
    """
    def __init__(self, host: str, port: int, names: Sequence[str], frequency_hz: float, *, timeout_s: float,
                 stale_after_s: float, reconnect_interval_s: float, source: str, device: str = "UR RTDE",
                 inputs: Sequence[str] = (), input_source_key: str = "inputs"):
        self.host, self.port, self.names = host, int(port), tuple(names)
        self.frequency_hz, self.timeout_s = float(frequency_hz), float(timeout_s)
        self.stale_after_s, self.reconnect_interval_s = float(stale_after_s), float(reconnect_interval_s)
        self.source, self.device = source, device
        self.inputs, self.input_source_key = tuple(inputs), input_source_key
        self._input_recipe: rp.Recipe | None = None
        self._send_lock = threading.Lock()  # one writer of input packages at a time
        self.cond = threading.Condition()
        self.latest: RtdeSample | None = None
        self.messages: list[rp.TextMessage] = []  # text messages from the controller, oldest first
        self.connected = False
        self.last_error = ""
        self.controller_version: tuple[int, int, int, int] | None = None
        self.stats = {"packages": 0, "connects": 0, "drops": 0, "stale": 0, "messages": 0, "inputs_sent": 0}
        self._sock: socket.socket | None = None
        self._recipe: rp.Recipe | None = None
        self._reader = rp.PackageReader()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._alive_at = 0.0  # monotonic time of the connection or its last package

    @property
    def where(self) -> str:
        """The device and its address, for messages."""
        return f"{self.device} at {self.host}:{self.port}"

    # --- lifecycle ----------------------------------------------------------------------
    def open(self) -> None:
        """Connect in the caller's thread (so a setup error fails it), then start the reader thread.

        Raises
        ------
        DriverError
            When the controller cannot be reached or refuses the version, a recipe or the start.
        ConfigError
            When an output is NOT_FOUND or an input register is IN_USE or NOT_FOUND.
        """
        self._stop.clear()
        self._connect()
        self._thread = threading.Thread(target=self._run, name="ur-rtde-reader", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the reader thread and close the connection (not counted as a drop)."""
        self._stop.set()
        self._drop(count=False)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=max(2.0, 2 * self.timeout_s))
        self._thread = None
        with self.cond:
            self.cond.notify_all()

    # --- setup --------------------------------------------------------------------------
    def _connect(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            raise DriverError(f"{self.where}: cannot connect: {exc}") from exc
        self._reader.clear()
        try:
            self._handshake(sock)
        except BaseException:
            _close(sock)
            raise
        with self.cond:
            self._sock, self.connected, self._alive_at = sock, True, time.monotonic()
            self.stats["connects"] += 1
            self.cond.notify_all()

    def _handshake(self, sock: socket.socket) -> None:
        reply = self._ask(sock, rp.protocol_version_request(rp.PROTOCOL_VERSION), rp.REQUEST_PROTOCOL_VERSION)
        if not rp.parse_u8(reply, "REQUEST_PROTOCOL_VERSION"):
            raise DriverError(f"{self.where}: the controller refused RTDE protocol version {rp.PROTOCOL_VERSION}")
        self.controller_version = rp.parse_urcontrol_version(
            self._ask(sock, rp.pack(rp.GET_URCONTROL_VERSION), rp.GET_URCONTROL_VERSION))
        rid, types = rp.parse_setup_reply(
            self._ask(sock, rp.setup_outputs_request(self.names, self.frequency_hz), rp.SETUP_OUTPUTS))
        if len(types) != len(self.names):
            raise DriverError(f"{self.where}: output setup answered {len(types)} types for {len(self.names)} names")
        unknown = [n for n, t in zip(self.names, types) if t == rp.NOT_FOUND]
        if unknown:
            raise ConfigError(self.source, "outputs", unknown[0],
                              f"an RTDE output the controller at {self.host}:{self.port} knows (it answered "
                              f"NOT_FOUND for {', '.join(unknown)})")
        if rid == 0:
            raise DriverError(f"{self.where}: output recipe refused (frequency {self.frequency_hz} Hz?)")
        self._recipe = rp.Recipe(rid, self.names, tuple(types))
        if self.inputs:
            self._setup_inputs(sock)
        if not rp.parse_u8(self._ask(sock, rp.pack(rp.START), rp.START), "START"):
            raise DriverError(f"{self.where}: the controller refused to start the data synchronisation")

    def _setup_inputs(self, sock: socket.socket) -> None:
        rid, types = rp.parse_setup_reply(self._ask(sock, rp.setup_inputs_request(self.inputs), rp.SETUP_INPUTS))
        if len(types) != len(self.inputs):
            raise DriverError(f"{self.where}: input setup answered {len(types)} types for {len(self.inputs)} names")
        taken = [n for n, t in zip(self.inputs, types) if t == rp.IN_USE]
        if taken:
            raise ConfigError(self.source, self.input_source_key, ", ".join(taken),
                              f"input registers no other RTDE client or fieldbus adapter (EtherNet/IP, PROFINET, "
                              f"MODBUS) writes: the controller at {self.host}:{self.port} answered IN_USE for "
                              f"{', '.join(taken)}; choose another range (24-47 is the upper one)")
        unknown = [n for n, t in zip(self.inputs, types) if t == rp.NOT_FOUND]
        if unknown:
            raise ConfigError(self.source, self.input_source_key, ", ".join(unknown),
                              f"input registers the controller at {self.host}:{self.port} knows "
                              "(input_int_register_N / input_double_register_N, N 0-47; it answered NOT_FOUND)")
        if rid == 0:
            raise DriverError(f"{self.where}: input recipe refused")
        self._input_recipe = rp.Recipe(rid, self.inputs, tuple(types))

    def write_inputs(self, values: Sequence[object]) -> None:
        """Send one data package of the input recipe; never waits for a reply. Callable from any thread.

        Parameters
        ----------
        values : sequence
            One value per input, in ``inputs`` order.

        Raises
        ------
        DriverError
            When no input recipe was set up, the link is not connected (the reader thread reconnects)
            or the send fails.
        ProtocolError
            When a value does not fit its type.
        """
        recipe = self._input_recipe
        if recipe is None:
            raise DriverError(f"{self.where}: no input recipe set up")
        pkg = recipe.pack(values)
        with self._send_lock:
            sock = self._sock
            if sock is None:
                raise DriverError(f"{self.where}: not connected (reconnecting; last error: {self.last_error})")
            try:
                sock.sendall(pkg)
            except OSError as exc:
                raise DriverError(f"{self.where}: input package not sent: {exc}") from exc
        self.stats["inputs_sent"] += 1

    def _ask(self, sock: socket.socket, request: bytes, reply_type: int) -> bytes:
        """Send a setup request and return the payload of its reply (text messages are kept)."""
        deadline = time.monotonic() + self.timeout_s
        late = f"{self.where}: no {rp.PACKAGE_TYPES[reply_type]} reply within {self.timeout_s} s"
        try:
            sock.sendall(request)
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DriverError(late)
                sock.settimeout(left)
                data = sock.recv(65536)
                if not data:
                    raise DriverError(f"{self.where}: connection closed during setup")
                for ptype, payload in self._reader.feed(data):
                    if ptype == reply_type:
                        return payload
                    if ptype == rp.TEXT_MESSAGE:
                        self._message(rp.parse_text_message(payload))
        except TimeoutError as exc:
            raise DriverError(late) from exc
        except OSError as exc:
            raise DriverError(f"{self.where}: setup failed: {exc}") from exc

    # --- streaming ----------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            if self._sock is None:
                if self._stop.wait(self.reconnect_interval_s):
                    return
                try:
                    self._connect()
                except (DriverError, ConfigError) as exc:
                    self.last_error = str(exc)
                continue
            try:
                self._read_once()
            except (OSError, DriverError) as exc:  # rp.ProtocolError is a DriverError
                self.last_error = f"{type(exc).__name__}: {exc}"
                self._drop()

    def _read_once(self) -> None:
        sock, recipe = self._sock, self._recipe
        if sock is None or recipe is None:
            return
        r, _, _ = select.select([sock], [], [], min(0.1, self.stale_after_s))
        if not r:
            if time.monotonic() - self._alive_at > self.stale_after_s:
                self.stats["stale"] += 1
                raise DriverError(f"{self.where}: no data package for {self.stale_after_s} s")
            return
        data = sock.recv(65536)
        t_host = self._alive_at = time.monotonic()
        if not data:
            raise DriverError(f"{self.where}: the controller closed the connection")
        for ptype, payload in self._reader.feed(data):
            if ptype == rp.DATA_PACKAGE:
                values = recipe.unpack(payload)
                with self.cond:
                    self.stats["packages"] += 1
                    ts = values.get("timestamp", float("nan"))
                    self.latest = RtdeSample(values, float(ts), t_host, self.stats["packages"])  # type: ignore[arg-type]
                    self.cond.notify_all()
            elif ptype == rp.TEXT_MESSAGE:
                self._message(rp.parse_text_message(payload))

    def _message(self, msg: rp.TextMessage) -> None:
        with self.cond:
            self.messages.append(msg)
            del self.messages[:-100]  # keep the newest
            self.stats["messages"] += 1
            self.cond.notify_all()

    def _drop(self, count: bool = True) -> None:
        with self.cond:
            sock, self._sock = self._sock, None
            if sock is not None and count:
                self.stats["drops"] += 1
            self.connected = False
            self.cond.notify_all()
        if sock is not None:
            _close(sock)


def _close(s: socket.socket) -> None:
    try:
        s.close()
    except OSError:
        pass
