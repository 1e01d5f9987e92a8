"""Line protocol spoken by the robot controller and the laser tracker (codec, shared).

Both sides use this codec: the emulators in `emulators.serial` serve it, the drivers in
`drivers.serial.controller` / `drivers.serial.tracker` speak it through `drivers.serial.link`.

Frame
-----
One ASCII line per frame::

    $<seq>,<WORD>[,<field>...]*<CRC>\\n

* `seq` decimal 0..65535; the host numbers its requests and wraps 65535 -> 0. A reply
  carries the seq of the request it answers.
* `WORD` is the command in a request (upper case), `ACK` or `NAK` in a reply.
* fields are printable ASCII without `$ , *` (numbers are Python `repr` of a float, SI units;
  `nan`/`inf` are syntactically valid and rejected by the receiver's range checks).
* `CRC` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over the bytes strictly between `$`
  and `*`, four upper-case hex digits. A trailing `\\r` before `\\n` is tolerated.
* A receiver resynchronises on the last `$` of a line, so a half-written frame followed by a
  whole one is survived; lines with no `$...*XXXX` shape are garbage and ignored.

Requests and replies (robot controller)
---------------------------------------
=====================  ==============================================  =========================
request                meaning                                         ACK fields
=====================  ==============================================  =========================
`PING`                 liveness / handshake                            protocol version, device
`MOVL,x,y,z,v`         linear move of the TCP, m and m/s               (none) -- sent when settled
`SETP,x,y,z,v`         streamed set-point                              (none) -- sent at once
`GETJ`                 encoder joint angles                            t, q1..qn (s, rad)
`GETT`                 controller TCP (nominal kinematics)             t, x, y, z (s, m)
`STATUS`               controller state                                state, moves done
=====================  ==============================================  =========================

Laser tracker: `PING`, `STATUS` as above and `MEAS` -> ACK `t, d, az, el, status` (s, m, rad,
rad, token such as `ok` or `beam_broken`; when status is not `ok` the numbers may be `nan`).

`NAK,<reason>[,<text>]` reasons: `CRC` (request checksum wrong; retry), `BUSY` (retry),
`SYNTAX`, `UNKNOWN` (command), `RANGE` (NaN or out-of-range argument), `UNREACHABLE` (target
outside the workspace), `FAULT` (the device failed).

Host discipline (drivers)
-------------------------
* one request in flight; wait `timeout_s` for its reply (`move_timeout_s` for MOVL);
* replies whose seq differs from the request's are stale and discarded; a reply that looks
  like a frame but fails its CRC triggers an immediate retransmission;
* on time-out, NAK CRC or NAK BUSY the *same* frame (same seq) is retransmitted, up to
  `retries` times; the device keeps its last reply and answers a duplicate (same seq and
  payload) from that cache without executing it again, so a retried MOVL moves once;
* after `reconnect_after` consecutive time-outs the port is closed and reopened;
* after the last retry the driver raises `DriverError`; any value received that is NaN or
  outside the configured limits raises `DriverError` and is never passed on.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from dt_kernel.errors import DriverError

PROTOCOL_VERSION = "1"
SEQ_MODULO = 65536
MAX_LINE = 1024  # bytes; longer lines without a newline are discarded as noise

ACK, NAK = "ACK", "NAK"
NAK_CRC, NAK_BUSY, NAK_SYNTAX, NAK_UNKNOWN = "CRC", "BUSY", "SYNTAX", "UNKNOWN"
NAK_RANGE, NAK_UNREACHABLE, NAK_FAULT = "RANGE", "UNREACHABLE", "FAULT"
RETRYABLE_NAKS = frozenset({NAK_CRC, NAK_BUSY})

_FIELD_OK = re.compile(r"^[\x20-\x7e]*$")
_FRAME = re.compile(rb"^\$([^*$]*)\*([0-9A-Fa-f]{4})$")
_STATUS_TOKEN = re.compile(r"^[a-z][a-z0-9_]{0,31}$")


class FrameError(DriverError):
    """A line is not a valid frame (wrong shape, bad seq, unprintable field)."""


class ChecksumError(FrameError):
    """A frame-shaped line whose CRC does not match; `seq` is set when it could be read."""

    def __init__(self, msg: str, seq: int | None):
        super().__init__(msg)
        self.seq = seq


@dataclass(frozen=True)
class Frame:
    seq: int
    word: str  # command in a request; ACK or NAK in a reply
    fields: tuple[str, ...] = ()

    @property
    def is_ack(self) -> bool:
        return self.word == ACK

    @property
    def is_nak(self) -> bool:
        return self.word == NAK

    @property
    def nak_reason(self) -> str:
        return self.fields[0] if self.is_nak and self.fields else ""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def next_seq(seq: int) -> int:
    return (seq + 1) % SEQ_MODULO


def fmt_float(x: float) -> str:
    """Shortest text that round-trips the float exactly."""
    return repr(float(x))


def encode(seq: int, word: str, *fields: object) -> bytes:
    if not 0 <= int(seq) < SEQ_MODULO:
        raise FrameError(f"seq {seq!r} outside 0..{SEQ_MODULO - 1}")
    parts = [str(int(seq)), str(word)]
    for f in fields:
        s = fmt_float(f) if isinstance(f, float) else str(f)
        if not _FIELD_OK.match(s) or any(c in s for c in "$,*"):
            raise FrameError(f"field {s!r} holds a reserved or unprintable character")
        parts.append(s)
    body = ",".join(parts).encode("ascii")
    return b"$" + body + b"*" + f"{crc16(body):04X}".encode("ascii") + b"\n"


def sanitize(text: str, limit: int = 80) -> str:
    """Make free text (an exception message) safe to send as one field."""
    out = "".join(c if (" " <= c <= "~" and c not in "$,*") else " " for c in str(text))
    return out[:limit]


def decode(line: bytes) -> Frame:
    """Decode one line (with or without its newline); resynchronises on the last `$`."""
    line = line.rstrip(b"\r\n")
    start = line.rfind(b"$")
    if start < 0:
        raise FrameError("no frame start '$'")
    m = _FRAME.match(line[start:])
    if m is None:
        raise FrameError("not a frame: expected $<seq>,<WORD>...*<CRC16>")
    body, crc_txt = m.group(1), m.group(2)
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as exc:
        raise FrameError("non-ASCII frame") from exc
    parts = text.split(",")
    seq: int | None
    try:
        seq = int(parts[0])
        if not 0 <= seq < SEQ_MODULO or not parts[0].isdigit():
            seq = None
    except ValueError:
        seq = None
    if crc16(body) != int(crc_txt, 16):
        raise ChecksumError(f"checksum mismatch in frame {text[:40]!r}", seq)
    if seq is None or len(parts) < 2 or not parts[1]:
        raise FrameError(f"bad seq or missing word in frame {text[:40]!r}")
    if not _FIELD_OK.match(text):
        raise FrameError("unprintable character in frame")
    return Frame(seq=seq, word=parts[1], fields=tuple(parts[2:]))


class LineBuffer:
    """Accumulates received bytes and yields complete lines; bounded against endless noise."""

    def __init__(self, max_line: int = MAX_LINE):
        self._buf = bytearray()
        self._max = max_line

    def feed(self, data: bytes) -> list[bytes]:
        self._buf.extend(data)
        lines = []
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                break
            lines.append(bytes(self._buf[:i]))
            del self._buf[: i + 1]
        if len(self._buf) > self._max:
            # Keep only from the last frame start: a frame may still be arriving.
            j = self._buf.rfind(b"$")
            del self._buf[: j if 0 <= j and len(self._buf) - j <= self._max else len(self._buf)]
        return lines

    def clear(self) -> None:
        self._buf.clear()


def parse_float(text: str, name: str, lo: float = -math.inf, hi: float = math.inf,
                allow_nan: bool = False) -> float:
    """Parse a received number; NaN, inf and out-of-range values raise DriverError."""
    try:
        x = float(text)
    except ValueError as exc:
        raise DriverError(f"{name}: {text!r} is not a number") from exc
    if math.isnan(x) and allow_nan:
        return x
    if not math.isfinite(x):
        raise DriverError(f"{name}: non-finite value {text!r} received")
    if not lo <= x <= hi:
        raise DriverError(f"{name}: value {x!r} outside [{lo}, {hi}]")
    return x


def parse_status(text: str) -> str:
    if not _STATUS_TOKEN.match(text):
        raise DriverError(f"status token {text!r} is not a lower-case identifier")
    return text
