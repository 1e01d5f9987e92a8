"""RTDE (Real-Time Data Exchange, Universal Robots, TCP 30004): the package codec, pure functions.

Both sides use it: the driver (`drivers.ur.driver`) and the emulator (`emulators.ur`). Packages
are `uint16 size | uint8 type | payload`, big-endian, protocol version 2 only; the types and
payloads are tabled in docs/drivers.md ("The wire formats: RTDE packages and URScript")."""
from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from dt_kernel.errors import DriverError

PROTOCOL_VERSION = 2
MAX_FREQUENCY_HZ = 500.0  # e-Series control loop; CB3 is 125 Hz

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")
PACKAGE_TYPES = {REQUEST_PROTOCOL_VERSION: "REQUEST_PROTOCOL_VERSION", GET_URCONTROL_VERSION: "GET_URCONTROL_VERSION",
                 TEXT_MESSAGE: "TEXT_MESSAGE", DATA_PACKAGE: "DATA_PACKAGE", SETUP_OUTPUTS: "SETUP_OUTPUTS",
                 SETUP_INPUTS: "SETUP_INPUTS", START: "START", PAUSE: "PAUSE"}

HEADER = struct.Struct(">HB")
MAX_PACKAGE = 0xFFFF

# Wire formats of the field types (the guide's "Data types" table).
TYPE_FORMATS = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
                "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}
NOT_FOUND, IN_USE = "NOT_FOUND", "IN_USE"

# Output fields the emulator serves, with the type the guide gives them (a real controller knows
# many more; the driver takes the types from the controller's reply, not from this table).
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",  # s since the controller started
    "target_q": "VECTOR6D", "target_qd": "VECTOR6D",  # rad, rad/s
    "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",  # x, y, z (m), rotation vector rx, ry, rz (rad), base frame
    "actual_TCP_speed": "VECTOR6D",  # m/s, rad/s
    "target_TCP_pose": "VECTOR6D", "target_TCP_speed": "VECTOR6D",
    "actual_execution_time": "DOUBLE",  # ms of the controller's real-time thread
    "robot_mode": "INT32", "safety_mode": "INT32", "runtime_state": "UINT32",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE",
    "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    **{f"output_int_register_{i}": "INT32" for i in range(48)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(48)},
    # the guide: the general purpose input registers can also be read as outputs (what was written)
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
}

# Inputs a client may write (SETUP_INPUTS): the general purpose registers, 0-23 the lower range
# (often taken by a fieldbus: EtherNet/IP, PROFINET, MODBUS), 24-47 the upper range. A register
# another client or a fieldbus adapter already writes comes back IN_USE.
INPUT_TYPES: dict[str, str] = {
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
}
N_REGISTERS = 48

# robot_mode (guide: ROBOT_MODE_*)
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
ROBOT_MODE_RUNNING = 7
# safety_mode (guide: SAFETY_MODE_*)
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
SAFETY_NORMAL, SAFETY_REDUCED, SAFETY_PROTECTIVE_STOP = 1, 2, 3
# runtime_state (guide: the program's state)
RUNTIME_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
# text message levels
EXCEPTION_MESSAGE, ERROR_MESSAGE, WARNING_MESSAGE, INFO_MESSAGE = 0, 1, 2, 3


class ProtocolError(DriverError):
    """A package that breaks the RTDE format (size, type, payload length, field types)."""


# --- framing ----------------------------------------------------------------------------
def pack(ptype: int, payload: bytes = b"") -> bytes:
    """One package: the header (size, type) and the payload.

    Parameters
    ----------
    ptype : int
        The package type (e.g. ``DATA_PACKAGE``).
    payload : bytes

    Returns
    -------
    bytes

    Raises
    ------
    ProtocolError
        When the package exceeds the uint16 size field.
    """
    size = HEADER.size + len(payload)
    if size > MAX_PACKAGE:
        raise ProtocolError(f"RTDE package of {size} bytes exceeds the uint16 size field")
    return HEADER.pack(size, ptype) + payload


class PackageReader:
    """Splits a byte stream into (type, payload) packages; keeps an incomplete tail."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def clear(self) -> None:
        """Drop any incomplete package buffered."""
        self._buf.clear()

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        """Add received bytes; yield every package completed, keeping an incomplete tail.

        Parameters
        ----------
        data : bytes

        Yields
        ------
        tuple of (int, bytes)
            The package's type and payload.

        Raises
        ------
        ProtocolError
            When a package states a size smaller than its header (the buffer is cleared: a binary
            stream cannot be resynchronised).
        """
        self._buf += data
        while len(self._buf) >= HEADER.size:
            size, ptype = HEADER.unpack_from(self._buf)
            if size < HEADER.size:
                self._buf.clear()  # cannot resynchronise inside a binary stream
                raise ProtocolError(f"RTDE package size {size} is smaller than its header")
            if len(self._buf) < size:
                return
            payload = bytes(self._buf[HEADER.size:size])
            del self._buf[:size]
            yield ptype, payload


# --- requests and replies ---------------------------------------------------------------
def u8(value: int) -> bytes:
    """A uint8 payload.

    Parameters
    ----------
    value : int
        0..255.

    Returns
    -------
    bytes
    """
    return struct.pack(">B", int(value))


def parse_u8(payload: bytes, what: str) -> int:
    """The first byte of a payload as an int.

    Parameters
    ----------
    payload : bytes
    what : str
        Names the package in the error.

    Returns
    -------
    int

    Raises
    ------
    ProtocolError
        When the payload is empty.
    """
    if len(payload) < 1:
        raise ProtocolError(f"RTDE {what}: empty payload, expected uint8")
    return payload[0]


def protocol_version_request(version: int = PROTOCOL_VERSION) -> bytes:
    """The REQUEST_PROTOCOL_VERSION package.

    Parameters
    ----------
    version : int

    Returns
    -------
    bytes
    """
    return pack(REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))


def parse_protocol_version_request(payload: bytes) -> int:
    """The version a REQUEST_PROTOCOL_VERSION payload asks for.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    int

    Raises
    ------
    ProtocolError
        When the payload is not 2 bytes.
    """
    if len(payload) != 2:
        raise ProtocolError(f"RTDE REQUEST_PROTOCOL_VERSION: payload of {len(payload)} bytes, expected 2")
    return struct.unpack(">H", payload)[0]


def urcontrol_version_reply(major: int, minor: int, bugfix: int, build: int) -> bytes:
    """The GET_URCONTROL_VERSION reply package.

    Parameters
    ----------
    major, minor, bugfix, build : int

    Returns
    -------
    bytes
    """
    return pack(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def parse_urcontrol_version(payload: bytes) -> tuple[int, int, int, int]:
    """The controller's version from a GET_URCONTROL_VERSION reply payload.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    tuple of int
        (major, minor, bugfix, build).

    Raises
    ------
    ProtocolError
        When the payload is not 16 bytes.
    """
    if len(payload) != 16:
        raise ProtocolError(f"RTDE GET_URCONTROL_VERSION: payload of {len(payload)} bytes, expected 16")
    major, minor, bugfix, build = struct.unpack(">IIII", payload)
    return major, minor, bugfix, build


@dataclass(frozen=True)
class TextMessage:
    """A TEXT_MESSAGE from the controller: ``message``, ``source`` and ``level`` (EXCEPTION_MESSAGE .. INFO_MESSAGE)."""
    message: str
    source: str
    level: int  # EXCEPTION_MESSAGE .. INFO_MESSAGE

    @property
    def is_error(self) -> bool:
        """True for an exception or error message (level <= ERROR_MESSAGE)."""
        return self.level <= ERROR_MESSAGE


def text_message(message: str, source: str, level: int) -> bytes:
    """A TEXT_MESSAGE package (message and source cut at 255 bytes of UTF-8).

    Parameters
    ----------
    message : str
    source : str
    level : int
        EXCEPTION_MESSAGE .. INFO_MESSAGE.

    Returns
    -------
    bytes
    """
    m, s = message.encode("utf-8")[:255], source.encode("utf-8")[:255]
    return pack(TEXT_MESSAGE, u8(len(m)) + m + u8(len(s)) + s + u8(level))


def parse_text_message(payload: bytes) -> TextMessage:
    """Decode a TEXT_MESSAGE payload (undecodable bytes replaced).

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    TextMessage

    Raises
    ------
    ProtocolError
        When the payload is truncated.
    """
    try:
        n = payload[0]
        msg = payload[1:1 + n]
        m = payload[1 + n]
        src = payload[2 + n:2 + n + m]
        level = payload[2 + n + m]
    except IndexError:
        raise ProtocolError(f"RTDE TEXT_MESSAGE: truncated payload of {len(payload)} bytes") from None
    return TextMessage(msg.decode("utf-8", "replace"), src.decode("utf-8", "replace"), level)


def setup_outputs_request(names: Sequence[str], frequency_hz: float) -> bytes:
    """The SETUP_OUTPUTS package: the output recipe's frequency and field names.

    Parameters
    ----------
    names : sequence of str
        RTDE output names.
    frequency_hz : float
        Hz.

    Returns
    -------
    bytes
    """
    return pack(SETUP_OUTPUTS, struct.pack(">d", float(frequency_hz)) + ",".join(names).encode("ascii"))


def parse_setup_outputs_request(payload: bytes) -> tuple[float, list[str]]:
    """The frequency and names of a SETUP_OUTPUTS payload.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    frequency_hz : float
    names : list of str

    Raises
    ------
    ProtocolError
        When the payload holds no frequency and name.
    """
    if len(payload) < 9:
        raise ProtocolError("RTDE SETUP_OUTPUTS: expected a double frequency and at least one name")
    (freq,) = struct.unpack_from(">d", payload)
    return freq, split_names(payload[8:])


def setup_inputs_request(names: Sequence[str]) -> bytes:
    """The SETUP_INPUTS package: the input recipe's field names.

    Parameters
    ----------
    names : sequence of str
        RTDE input names (e.g. ``input_int_register_24``).

    Returns
    -------
    bytes
    """
    return pack(SETUP_INPUTS, ",".join(names).encode("ascii"))


def split_names(raw: bytes) -> list[str]:
    """Comma-separated variable names; a trailing comma is tolerated, as the controller does
    (the ``ur_rtde`` client ends its list with one).

    Parameters
    ----------
    raw : bytes

    Returns
    -------
    list of str
    """
    names = raw.decode("ascii", "replace").split(",")
    return names[:-1] if len(names) > 1 and names[-1] == "" else names


def setup_reply(ptype: int, recipe_id: int, types: Sequence[str]) -> bytes:
    """A SETUP_OUTPUTS or SETUP_INPUTS reply package.

    Parameters
    ----------
    ptype : int
        ``SETUP_OUTPUTS`` or ``SETUP_INPUTS``.
    recipe_id : int
        0 refuses the recipe.
    types : sequence of str
        One type per name asked for (``NOT_FOUND`` / ``IN_USE`` for those refused).

    Returns
    -------
    bytes
    """
    return pack(ptype, u8(recipe_id) + ",".join(types).encode("ascii"))


def parse_setup_reply(payload: bytes) -> tuple[int, list[str]]:
    """The recipe id and field types of a setup reply payload.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    recipe_id : int
    types : list of str

    Raises
    ------
    ProtocolError
        When the payload is shorter than a recipe id and one type.
    """
    if len(payload) < 2:
        raise ProtocolError("RTDE setup reply: expected a recipe id and the variable types")
    return payload[0], payload[1:].decode("ascii", "replace").split(",")


# --- recipes and data packages ----------------------------------------------------------
@dataclass(frozen=True)
class Recipe:
    """An output (or input) recipe: the fields of every data package with this id, in order."""

    id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    def __post_init__(self) -> None:
        if len(self.names) != len(self.types):
            raise ProtocolError(f"recipe {self.id}: {len(self.names)} names but {len(self.types)} types")
        bad = [f"{n}={t}" for n, t in zip(self.names, self.types) if t not in TYPE_FORMATS]
        if bad:
            raise ProtocolError(f"recipe {self.id}: fields without a data type: {', '.join(bad)}")
        object.__setattr__(self, "_struct", struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types)))

    @property
    def struct(self) -> struct.Struct:
        """The struct of a DATA_PACKAGE payload of this recipe (the id, then the fields)."""
        return self.__dict__["_struct"]

    def pack(self, values: Sequence[object]) -> bytes:
        """A DATA_PACKAGE with ``values`` in recipe order (vectors as sequences).

        Parameters
        ----------
        values : sequence
            One value per field.

        Returns
        -------
        bytes

        Raises
        ------
        ProtocolError
            When a vector has the wrong length or a value does not fit its type.
        ValueError
            When there are not as many values as fields.
        """
        flat: list[object] = [self.id]
        for name, typ, v in zip(self.names, self.types, values, strict=True):
            if typ.startswith("VECTOR"):
                n = int(TYPE_FORMATS[typ][0])
                seq = list(v)  # type: ignore[call-overload]
                if len(seq) != n:
                    raise ProtocolError(f"field {name} ({typ}) needs {n} values, got {len(seq)}")
                flat.extend(seq)
            else:
                flat.append(v)
        try:
            return pack(DATA_PACKAGE, self.struct.pack(*flat))
        except struct.error as exc:
            raise ProtocolError(f"recipe {self.id}: cannot pack {list(self.names)}: {exc}") from exc

    def unpack(self, payload: bytes) -> dict[str, object]:
        """Field name -> value (a tuple for vectors) of a DATA_PACKAGE payload of this recipe.

        Parameters
        ----------
        payload : bytes

        Returns
        -------
        dict

        Raises
        ------
        ProtocolError
            When the payload's size or recipe id is not this recipe's.
        """
        if len(payload) != self.struct.size:
            raise ProtocolError(f"RTDE DATA_PACKAGE of recipe {self.id}: {len(payload)} bytes, "
                                f"expected {self.struct.size} for {','.join(self.types)}")
        flat = self.struct.unpack(payload)
        if flat[0] != self.id:
            raise ProtocolError(f"RTDE DATA_PACKAGE for recipe {flat[0]}, expected {self.id}")
        out: dict[str, object] = {}
        i = 1
        for name, typ in zip(self.names, self.types):
            fmt = TYPE_FORMATS[typ]
            if fmt[0].isdigit():
                n = int(fmt[0])
                out[name] = tuple(flat[i:i + n])
                i += n
            else:
                out[name] = flat[i]
                i += 1
        return out


def data_recipe_id(payload: bytes) -> int:
    """The recipe id of a DATA_PACKAGE payload.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    int

    Raises
    ------
    ProtocolError
        When the payload is empty.
    """
    return parse_u8(payload, "DATA_PACKAGE")


def check_frequency(freq: float) -> bool:
    """True for an allowed output frequency: 0 < frequency <= 500 Hz (the guide; the controller's loop).

    Parameters
    ----------
    freq : float
        Hz.

    Returns
    -------
    bool
    """
    return math.isfinite(freq) and 0.0 < freq <= MAX_FREQUENCY_HZ
