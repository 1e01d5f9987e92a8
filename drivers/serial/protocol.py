"""Line protocol spoken by the serial robot controller and laser tracker: the codec both sides use.

The emulators in `emulators.serial` serve it; the drivers in `drivers.serial.controller` /
`drivers.serial.tracker` speak it through `drivers.serial.link`. The frame format, the requests
and replies, the NAK reasons and the host's discipline: docs/drivers.md ("Serial line protocol")."""
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
    """One decoded frame: ``seq``, ``word`` (the command in a request; ACK or NAK in a reply), ``fields``."""
    seq: int
    word: str  # command in a request; ACK or NAK in a reply
    fields: tuple[str, ...] = ()

    @property
    def is_ack(self) -> bool:
        """True for an ACK reply."""
        return self.word == ACK

    @property
    def is_nak(self) -> bool:
        """True for a NAK reply."""
        return self.word == NAK

    @property
    def nak_reason(self) -> str:
        """A NAK's reason (its first field), or an empty string for any other frame."""
        return self.fields[0] if self.is_nak and self.fields else ""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor.

    Parameters
    ----------
    data : bytes

    Returns
    -------
    int
        0..0xFFFF.
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def next_seq(seq: int) -> int:
    """The sequence number after ``seq`` (wraps 65535 -> 0).

    Parameters
    ----------
    seq : int

    Returns
    -------
    int
    """
    return (seq + 1) % SEQ_MODULO


def fmt_float(x: float) -> str:
    """Shortest text that round-trips the float exactly (``repr``).

    Parameters
    ----------
    x : float

    Returns
    -------
    str
    """
    return repr(float(x))


def encode(seq: int, word: str, *fields: object) -> bytes:
    r"""One frame as the bytes of a line: ``$seq,WORD,fields*CRC\n``.

    Parameters
    ----------
    seq : int
        0..65535.
    word : str
        The command, ACK or NAK.
    *fields : object
        Floats are written with ``fmt_float``, anything else with ``str``.

    Returns
    -------
    bytes

    Raises
    ------
    FrameError
        When ``seq`` is out of range or a field holds ``$ , *`` or an unprintable character.
    """
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
    """Make free text (an exception message) safe to send as one field.

    Parameters
    ----------
    text : str
    limit : int
        Longest result (characters).

    Returns
    -------
    str
        Reserved and unprintable characters replaced by spaces, cut at ``limit``.
    """
    out = "".join(c if (" " <= c <= "~" and c not in "$,*") else " " for c in str(text))
    return out[:limit]


def decode(line: bytes) -> Frame:
    """Decode one line (with or without its newline); resynchronises on the last ``$``.

    Parameters
    ----------
    line : bytes

    Returns
    -------
    Frame

    Raises
    ------
    ChecksumError
        When a frame-shaped line fails its CRC.
    FrameError
        When the line is not a frame (no ``$``, wrong shape, non-ASCII, bad seq, no word).
    """
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
        """Add received bytes; return the lines completed (without their newlines).

        Past ``max_line`` bytes without a newline, the buffer keeps only from the last ``$``.

        Parameters
        ----------
        data : bytes

        Returns
        -------
        list of bytes
        """
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
        """Drop whatever partial line is buffered."""
        self._buf.clear()


def parse_float(text: str, name: str, lo: float = -math.inf, hi: float = math.inf,
                allow_nan: bool = False) -> float:
    """Parse a received number, checking its range.

    Parameters
    ----------
    text : str
        The field.
    name : str
        Names the field in the error.
    lo, hi : float
        The range allowed (inclusive).
    allow_nan : bool
        Return NaN instead of refusing it.

    Returns
    -------
    float

    Raises
    ------
    DriverError
        When the text is not a number, is non-finite (NaN unless allowed) or outside [lo, hi].
    """
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
    """Check a status token (a lower-case identifier of at most 32 characters).

    Parameters
    ----------
    text : str

    Returns
    -------
    str
        The token.

    Raises
    ------
    DriverError
        When it is not such a token.
    """
    if not _STATUS_TOKEN.match(text):
        raise DriverError(f"status token {text!r} is not a lower-case identifier")
    return text
