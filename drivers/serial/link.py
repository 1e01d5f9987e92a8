"""Host side of the serial line protocol (`drivers.serial.protocol`) over pyserial: `SerialLink`.

One request in flight, sequence numbers, acknowledgements, retries, stale-reply discard and
reconnection; the controller and tracker drivers both talk through it. pyserial and OS errors
become DriverError here and only here (`port_errors`). The discipline and the options
(`LinkConfig`): docs/drivers.md ("Serial line protocol")."""
from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import serial
from pydantic import Field

from drivers.serial import protocol as lp
from dt_kernel.config import Frozen
from dt_kernel.errors import DriverError, UnreachableError

_POLL_S = 0.02  # pyserial read granularity while waiting for a reply


@contextmanager
def port_errors(device: str, what: str) -> Iterator[None]:
    """The serial boundary: a pyserial or OS error becomes DriverError naming the device and what failed.

    A context manager; ValueError (a malformed URL or setting) is converted too.

    Parameters
    ----------
    device : str
        Names the device in the error.
    what : str
        What was being done (e.g. ``write failed``).

    Raises
    ------
    DriverError
        Chained from the pyserial, OS or value error.
    """
    try:
        yield
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DriverError(f"{device}: {what}: {exc}") from exc


class LinkConfig(Frozen):
    """The line's options: ``url`` (required), ``baudrate``, ``timeout_s`` (s, per reply),
    ``move_timeout_s`` (s, a MOVL reply), ``retries`` (after the first try), ``reconnect_after``
    (consecutive time-outs before the port is reopened).
    """
    url: str = Field(min_length=1)
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0, le=60)
    move_timeout_s: float = Field(30.0, gt=0, le=3600)
    retries: int = Field(3, ge=0, le=100)
    reconnect_after: int = Field(2, ge=1, le=100)


class SerialLink:
    """Host side of the line protocol: one request in flight, retried until acknowledged."""

    def __init__(self, cfg: LinkConfig, device: str = "device", abort: threading.Event | None = None):
        self.cfg, self.device = cfg, device
        # Set by the device's `abort()`: the request in flight ends at the next poll (_POLL_S).
        self.abort = abort if abort is not None else threading.Event()
        self._port: serial.SerialBase | None = None
        self._lines = lp.LineBuffer()
        self._seq = 0
        self._lock = threading.Lock()
        self.stats = {k: 0 for k in ("requests", "retries", "timeouts", "reconnects", "stale",
                                     "corrupt", "garbage", "naks")}

    # --- port ---------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        """Open the port (``serial.serial_for_url``) and drop stale input; does nothing when open.

        Raises
        ------
        DriverError
            When the port cannot be opened.
        """
        if self.is_open:
            return
        with port_errors(self.device, f"cannot open {self.cfg.url!r}"):
            port = serial.serial_for_url(self.cfg.url, baudrate=self.cfg.baudrate,
                                         timeout=_POLL_S, write_timeout=max(self.cfg.timeout_s, 0.5))
            port.reset_input_buffer()
        self._port = port
        self._lines.clear()

    def close(self) -> None:
        """Close the port; errors closing a dead port are ignored."""
        port, self._port = self._port, None
        self._lines.clear()
        if port is not None:
            try:
                with port_errors(self.device, "close"):
                    port.close()
            except DriverError:
                pass  # closing a dead port: nothing left to release

    def reconnect(self) -> None:
        """Close and reopen the port (counted in ``stats["reconnects"]``).

        Raises
        ------
        DriverError
            When the port cannot be opened again.
        """
        self.stats["reconnects"] += 1
        self.close()
        self.open()

    # --- transactions -------------------------------------------------------------------
    def request(self, word: str, *fields: Any, timeout_s: float | None = None) -> lp.Frame:
        """Send one request and return its ACK or non-retryable NAK frame.

        Time-outs, corrupt replies and retryable NAKs (CRC, BUSY) retransmit the same frame, up to
        ``retries`` times; the port is reopened after ``reconnect_after`` time-outs in a row.

        Parameters
        ----------
        word : str
            The command.
        *fields : object
            Its fields.
        timeout_s : float or None
            Wait per attempt (s); ``cfg.timeout_s`` when None.

        Returns
        -------
        Frame
            An ACK, or a NAK whose reason is not retryable.

        Raises
        ------
        DriverError
            When no valid reply came after ``1 + retries`` attempts, or the device's abort was set.
        """
        with self._lock:
            seq, self._seq = self._seq, lp.next_seq(self._seq)
            frame = lp.encode(seq, word, *fields)
            wait = self.cfg.timeout_s if timeout_s is None else timeout_s
            self.stats["requests"] += 1
            timeouts_in_row, problem, cause = 0, "", None
            for attempt in range(1 + self.cfg.retries):
                self._check_abort(word, seq)
                if attempt:
                    self.stats["retries"] += 1
                try:
                    if not self.is_open:
                        self.open()
                    self._write(frame)
                    reply = self._await(seq, time.monotonic() + wait)
                except DriverError as exc:  # port vanished or I/O failed: reopen next attempt
                    problem, cause = str(exc), exc
                    self._check_abort(word, seq)
                    self.close()
                    self.abort.wait(min(wait, 0.1))
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
                if isinstance(reply, str):  # "corrupt"
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

    def _check_abort(self, word: str, seq: int) -> None:
        if self.abort.is_set():
            raise DriverError(f"{self.device} at {self.cfg.url}: {word} (seq {seq}) aborted: the host is stopping")

    def _open_port(self) -> serial.SerialBase:
        """The open port; DriverError if it was closed meanwhile (`close` does not take the
        request lock), which `request` treats like any I/O failure: reopen on the next attempt."""
        port = self._port
        if port is None:
            raise DriverError(f"{self.device}: port {self.cfg.url!r} is not open")
        return port

    def _write(self, frame: bytes) -> None:
        port = self._open_port()
        with port_errors(self.device, "write failed"):
            port.write(frame)
            port.flush()

    def _await(self, seq: int, deadline: float) -> lp.Frame | str | None:
        """The reply to `seq`, 'corrupt' for a frame that failed its CRC, None on time-out."""
        while True:
            port = self._open_port()
            with port_errors(self.device, "read failed"):
                data = port.read(max(1, port.in_waiting))
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
            if time.monotonic() >= deadline or self.abort.is_set():
                return None


def refused(device: str, word: str, reply: lp.Frame) -> DriverError | UnreachableError:
    """The error for a NAK reply.

    Parameters
    ----------
    device : str
        Names the device.
    word : str
        The command refused.
    reply : Frame
        The NAK.

    Returns
    -------
    DriverError or UnreachableError
        UnreachableError for NAK UNREACHABLE, DriverError naming the reason otherwise.
    """
    text = ",".join(reply.fields[1:])
    if reply.nak_reason == lp.NAK_UNREACHABLE:
        return UnreachableError(f"{device}: {word} refused, target unreachable: {text}")
    return DriverError(f"{device}: {word} refused with NAK {reply.nak_reason}: {text}")


def ack_fields(device: str, word: str, reply: lp.Frame, n: int | None = None) -> tuple[str, ...]:
    """The fields of an ACK reply.

    Parameters
    ----------
    device : str
        Names the device in errors.
    word : str
        The command answered.
    reply : Frame
        The reply.
    n : int or None
        The number of fields expected (not checked when None).

    Returns
    -------
    tuple of str

    Raises
    ------
    DriverError or UnreachableError
        When the reply is a NAK (see ``refused``), or has another number of fields than ``n``.
    """
    if not reply.is_ack:
        raise refused(device, word, reply)
    if n is not None and len(reply.fields) != n:
        raise DriverError(f"{device}: {word} reply has {len(reply.fields)} fields, expected {n}")
    return reply.fields
