"""NatNet 4.1 wire format: pack and unpack of the messages this driver and its emulator use.

OptiTrack's NatNet streaming protocol over UDP, little-endian throughout. Every datagram is

    uint16 message id | uint16 byte count of the payload | payload

Message ids (NatNet SDK, NatNetTypes.h): NAT_CONNECT 0, NAT_SERVERINFO 1, NAT_REQUEST 2,
NAT_RESPONSE 3, NAT_REQUEST_MODELDEF 4, NAT_MODELDEF 5, NAT_REQUEST_FRAMEOFDATA 6,
NAT_FRAMEOFDATA 7, NAT_MESSAGESTRING 8, NAT_DISCONNECT 9, NAT_KEEPALIVE 10,
NAT_UNRECOGNIZED_REQUEST 100.

One version is implemented exactly: bitstream 4.1 (Motive 3.x), in which every section of a
frame of data and every data description carries its byte size after its count, so a reader can
skip what it does not decode (skeletons, assets, force plates, devices are skipped that way).
Positions are metres in the server's (calibrated rig's) frame; quaternions are (qx, qy, qz, qw).

Pure functions: bytes in, dataclasses out and back; no sockets here.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

from dt_kernel.errors import DriverError

NAT_CONNECT, NAT_SERVERINFO, NAT_REQUEST, NAT_RESPONSE = 0, 1, 2, 3
NAT_REQUEST_MODELDEF, NAT_MODELDEF, NAT_REQUEST_FRAMEOFDATA, NAT_FRAMEOFDATA = 4, 5, 6, 7
NAT_MESSAGESTRING, NAT_DISCONNECT, NAT_KEEPALIVE, NAT_UNRECOGNIZED_REQUEST = 8, 9, 10, 100

VERSION = (4, 1, 0, 0)  # the one NatNet bitstream version implemented here
MAX_NAME = 256  # sSender.szName (MAX_NAMELENGTH)
MAX_PAYLOAD = 0xFFFF  # the byte count is a uint16

# Parameter bits (NatNetTypes.h).
RB_TRACKING_VALID = 0x01  # sRigidBodyData.params
MARKER_OCCLUDED, MARKER_PC_SOLVED, MARKER_MODEL_SOLVED = 0x01, 0x02, 0x04  # sMarker.params
MARKER_HAS_MODEL, MARKER_UNLABELED, MARKER_ACTIVE = 0x08, 0x10, 0x20
FRAME_RECORDING, FRAME_MODELS_CHANGED = 0x01, 0x02  # sFrameOfMocapData.params

# Data description types (NAT_MODELDEF).
DESC_MARKERSET, DESC_RIGIDBODY, DESC_SKELETON, DESC_FORCEPLATE = 0, 1, 2, 3
DESC_DEVICE, DESC_CAMERA, DESC_ASSET = 4, 5, 6

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class NatNetProtocolError(DriverError):
    """A datagram does not follow the NatNet 4.1 layout (truncated, inconsistent counts)."""


# ----------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class ServerInfo:
    """NAT_SERVERINFO payload (sSender_Server): the answer to NAT_CONNECT."""

    app_name: str = "Motive"
    app_version: tuple[int, int, int, int] = (3, 1, 0, 0)
    natnet_version: tuple[int, int, int, int] = VERSION
    clock_hz: int = 10_000_000  # HighResClockFrequency: ticks per second of the uint64 stamps
    data_port: int = 1511
    multicast: bool = False
    multicast_group: tuple[int, int, int, int] = (239, 255, 42, 99)


@dataclass(frozen=True)
class ConnectRequest:
    """NAT_CONNECT payload: sSender ("Ping", client versions) + sConnectionOptions."""

    app_name: str = "Ping"
    app_version: tuple[int, int, int, int] = (0, 0, 0, 0)
    natnet_version: tuple[int, int, int, int] = VERSION
    subscribed_only: bool = False
    bitstream_version: tuple[int, int, int, int] = VERSION


@dataclass(frozen=True)
class MarkerSet:
    """A named marker set of a frame: its markers' positions (m, server frame)."""
    name: str
    markers: tuple[Vec3, ...] = ()


@dataclass(frozen=True)
class RigidBody:
    """A rigid body of a frame (sRigidBodyData): ``pos`` (m, server frame), ``quat`` (qx, qy, qz, qw),
    ``mean_error`` (m, mean marker error of the solve) and the ``params`` bits.
    """
    id: int
    pos: Vec3
    quat: Quat  # qx, qy, qz, qw
    mean_error: float = 0.0  # m, mean marker error of the solve
    params: int = RB_TRACKING_VALID

    @property
    def tracking_valid(self) -> bool:
        """True when the server tracked the body in this frame (RB_TRACKING_VALID)."""
        return bool(self.params & RB_TRACKING_VALID)


@dataclass(frozen=True)
class LabeledMarker:
    """sMarker: id packs (asset/model id << 16) | member id (1-based within the asset)."""

    id: int
    pos: Vec3
    size: float = 0.014  # m, marker diameter
    params: int = MARKER_MODEL_SOLVED | MARKER_HAS_MODEL
    residual: float = 0.0  # m

    @property
    def model_id(self) -> int:
        """The asset/model id (the id's upper 16 bits)."""
        return self.id >> 16

    @property
    def member_id(self) -> int:
        """The member id within the asset, 1-based (the id's lower 16 bits)."""
        return self.id & 0xFFFF

    @property
    def occluded(self) -> bool:
        """True when the marker was occluded (MARKER_OCCLUDED)."""
        return bool(self.params & MARKER_OCCLUDED)


def marker_id(model_id: int, member_id: int) -> int:
    """The packed labelled-marker id (NatNet_DecodeID's inverse).

    Parameters
    ----------
    model_id : int
        The asset/model id (16 bits).
    member_id : int
        The member id within the asset, 1-based (16 bits).

    Returns
    -------
    int
    """
    return ((int(model_id) & 0xFFFF) << 16) | (int(member_id) & 0xFFFF)


@dataclass(frozen=True)
class FrameOfData:
    """sFrameOfMocapData, the sections this project uses; the others are sent empty."""

    frame_number: int
    marker_sets: tuple[MarkerSet, ...] = ()
    other_markers: tuple[Vec3, ...] = ()  # legacy unlabelled markers
    rigid_bodies: tuple[RigidBody, ...] = ()
    labeled_markers: tuple[LabeledMarker, ...] = ()
    timecode: int = 0
    timecode_sub: int = 0
    timestamp: float = 0.0  # s, server's frame timestamp
    stamp_mid_exposure: int = 0  # ticks of ServerInfo.clock_hz: camera mid-exposure
    stamp_data_received: int = 0  # ticks: camera data received by the server
    stamp_transmit: int = 0  # ticks: frame handed to the network
    precision_s: int = 0  # precision timestamp, seconds (4.1, 0 when not available)
    precision_frac: int = 0  # precision timestamp, fraction of a second
    params: int = 0
    skipped: dict[str, int] = field(default_factory=dict, compare=False)  # sections skipped by size


@dataclass(frozen=True)
class MarkerSetDescription:
    """A marker set's description (NAT_MODELDEF): its name and its markers' names."""
    name: str
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class RigidBodyDescription:
    """A rigid body's description (NAT_MODELDEF): name, id, parent id, ``offset`` (m), its markers'
    positions (m, rigid-body frame, pivot at the origin), active labels (0 for passive markers) and
    names.
    """
    name: str
    id: int
    parent_id: int = -1
    offset: Vec3 = (0.0, 0.0, 0.0)
    marker_positions: tuple[Vec3, ...] = ()  # m, rigid-body frame (pivot at the origin)
    marker_labels: tuple[int, ...] = ()  # active labels (0 for passive markers)
    marker_names: tuple[str, ...] = ()


Description = MarkerSetDescription | RigidBodyDescription


# ----------------------------------------------------------------------------- framing
_HEADER = struct.Struct("<HH")


def pack_message(msg_id: int, payload: bytes = b"") -> bytes:
    """One datagram: the header (message id, payload byte count) and the payload.

    Parameters
    ----------
    msg_id : int
        A NAT_* message id.
    payload : bytes
        At most MAX_PAYLOAD bytes.

    Returns
    -------
    bytes

    Raises
    ------
    NatNetProtocolError
        When the payload is too long for the uint16 byte count.
    """
    if len(payload) > MAX_PAYLOAD:
        raise NatNetProtocolError(f"NatNet payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return _HEADER.pack(msg_id, len(payload)) + payload


def unpack_message(datagram: bytes) -> tuple[int, bytes]:
    """Split a datagram into its message id and payload.

    Bytes past the stated count are ignored: clients such as the SDK's sample append a NUL after a
    zero-length request.

    Parameters
    ----------
    datagram : bytes
        One UDP datagram.

    Returns
    -------
    msg_id : int
    payload : bytes

    Raises
    ------
    NatNetProtocolError
        When the datagram is shorter than its header or its stated count.
    """
    if len(datagram) < 4:
        raise NatNetProtocolError(f"NatNet datagram of {len(datagram)} bytes is shorter than its header")
    msg_id, n = _HEADER.unpack_from(datagram)
    if len(datagram) < 4 + n:
        raise NatNetProtocolError(f"NatNet message {msg_id}: header says {n} bytes, got {len(datagram) - 4}")
    return msg_id, bytes(datagram[4:4 + n])


class _Reader:
    """Cursor over a payload; every read past the end is a NatNetProtocolError."""

    def __init__(self, data: bytes, what: str):
        self.data, self.off, self.what = memoryview(data), 0, what

    def take(self, fmt: str):
        s = struct.calcsize(fmt)
        try:
            v = struct.unpack_from(fmt, self.data, self.off)
        except struct.error as exc:
            raise NatNetProtocolError(f"{self.what}: truncated at byte {self.off} (needs {s} more)") from exc
        self.off += s
        return v

    def one(self, fmt: str):
        return self.take(fmt)[0]

    def cstring(self) -> str:
        end = bytes(self.data[self.off:]).find(b"\0")
        if end < 0:
            raise NatNetProtocolError(f"{self.what}: unterminated string at byte {self.off}")
        s = bytes(self.data[self.off:self.off + end]).decode("utf-8", "replace")
        self.off += end + 1
        return s

    def skip(self, n: int) -> None:
        if n < 0 or self.off + n > len(self.data):
            raise NatNetProtocolError(f"{self.what}: cannot skip {n} bytes at byte {self.off}")
        self.off += n

    def count(self, name: str, limit: int = 100_000) -> int:
        n = self.one("<i")
        if not 0 <= n <= limit:
            raise NatNetProtocolError(f"{self.what}: {name} count {n} out of range")
        return n


def _cstr(s: str) -> bytes:
    return s.encode("utf-8") + b"\0"


def _fixed_name(s: str) -> bytes:
    b = s.encode("utf-8")[:MAX_NAME - 1]
    return b + b"\0" * (MAX_NAME - len(b))


# ----------------------------------------------------------------------------- connect / server info
def pack_connect(req: ConnectRequest = ConnectRequest()) -> bytes:
    """The NAT_CONNECT datagram.

    Parameters
    ----------
    req : ConnectRequest
        The client's name, versions and options.

    Returns
    -------
    bytes
    """
    payload = (_fixed_name(req.app_name) + bytes(req.app_version) + bytes(req.natnet_version)
               + struct.pack("<B", int(req.subscribed_only)) + bytes(req.bitstream_version))
    return pack_message(NAT_CONNECT, payload)


def unpack_connect(payload: bytes) -> ConnectRequest:
    """Decode a NAT_CONNECT payload; a short payload (older clients send only the name) gives
    zero versions and no subscription for the rest.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    ConnectRequest
    """
    name = payload[:MAX_NAME].split(b"\0", 1)[0].decode("utf-8", "replace")
    ver = tuple(payload[256:260]) if len(payload) >= 260 else (0, 0, 0, 0)
    nn = tuple(payload[260:264]) if len(payload) >= 264 else (0, 0, 0, 0)
    sub = bool(payload[264]) if len(payload) >= 265 else False
    bs = tuple(payload[265:269]) if len(payload) >= 269 else (0, 0, 0, 0)
    return ConnectRequest(name, ver, nn, sub, bs)  # type: ignore[arg-type]


_SERVER_TAIL = struct.Struct("<QHB4B")  # HighResClockFrequency, DataPort, IsMulticast, group


def pack_server_info(info: ServerInfo) -> bytes:
    """The NAT_SERVERINFO datagram.

    Parameters
    ----------
    info : ServerInfo

    Returns
    -------
    bytes
    """
    payload = (_fixed_name(info.app_name) + bytes(info.app_version) + bytes(info.natnet_version)
               + _SERVER_TAIL.pack(info.clock_hz, info.data_port, int(info.multicast), *info.multicast_group))
    return pack_message(NAT_SERVERINFO, payload)


def unpack_server_info(payload: bytes) -> ServerInfo:
    """Decode a NAT_SERVERINFO payload; a server older than NatNet 3.0 (no clock or ports) gets
    ``clock_hz`` 0 and the default ports.

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    ServerInfo

    Raises
    ------
    NatNetProtocolError
        When the payload is shorter than the name and versions.
    """
    if len(payload) < MAX_NAME + 8:
        raise NatNetProtocolError(f"NAT_SERVERINFO of {len(payload)} bytes (needs >= {MAX_NAME + 8})")
    name = payload[:MAX_NAME].split(b"\0", 1)[0].decode("utf-8", "replace")
    ver, nn = tuple(payload[256:260]), tuple(payload[260:264])
    if len(payload) >= 264 + _SERVER_TAIL.size:  # NatNet 3.0+ servers add the clock and ports
        hz, port, mc, *grp = _SERVER_TAIL.unpack_from(payload, 264)
        return ServerInfo(name, ver, nn, hz, port, bool(mc), tuple(grp))  # type: ignore[arg-type]
    return ServerInfo(name, ver, nn, 0)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- requests
def pack_request(msg_id: int, text: str = "") -> bytes:
    """A request datagram: NAT_REQUEST (a command string), NAT_REQUEST_MODELDEF, NAT_KEEPALIVE, ...

    Parameters
    ----------
    msg_id : int
        A NAT_* message id.
    text : str
        The command, sent NUL-terminated; empty sends no payload.

    Returns
    -------
    bytes
    """
    return pack_message(msg_id, _cstr(text) if text else b"")


def pack_text(msg_id: int, text: str) -> bytes:
    """NAT_RESPONSE / NAT_MESSAGESTRING carrying a NUL-terminated string.

    Parameters
    ----------
    msg_id : int
        A NAT_* message id.
    text : str

    Returns
    -------
    bytes
    """
    return pack_message(msg_id, _cstr(text))


def unpack_text(payload: bytes) -> str:
    """The string of a text payload, up to its first NUL (undecodable bytes replaced).

    Parameters
    ----------
    payload : bytes

    Returns
    -------
    str
    """
    return payload.split(b"\0", 1)[0].decode("utf-8", "replace")


# ----------------------------------------------------------------------------- frame of data
def _section(count: int, body: bytes) -> bytes:
    # 4.1: every section is int32 count, int32 byte size of what follows, then the items.
    return struct.pack("<ii", count, len(body)) + body


_V3, _Q = struct.Struct("<3f"), struct.Struct("<4f")
_RB = struct.Struct("<i3f4ffh")  # id, pos, quat, mean error, params
_LM = struct.Struct("<i3ffhf")  # id, pos, size, params, residual
_SUFFIX = struct.Struct("<IIdQQQIIh")  # timecode, sub, timestamp, 3 stamps, precision s/frac, params


def pack_frame(f: FrameOfData) -> bytes:
    """The NAT_FRAMEOFDATA datagram (4.1 layout; skeletons, assets, force plates, devices sent empty).

    Parameters
    ----------
    f : FrameOfData

    Returns
    -------
    bytes

    Raises
    ------
    NatNetProtocolError
        When a field is out of its wire range or the frame exceeds MAX_PAYLOAD.
    """
    try:
        return _pack_frame(f)
    except struct.error as exc:  # a field out of its wire range (negative stamp, huge id)
        raise NatNetProtocolError(f"frame {f.frame_number} cannot be packed: {exc}") from exc


def _pack_frame(f: FrameOfData) -> bytes:
    out = [struct.pack("<i", f.frame_number)]
    ms = b"".join(_cstr(m.name) + struct.pack("<i", len(m.markers)) + b"".join(_V3.pack(*p) for p in m.markers)
                  for m in f.marker_sets)
    out.append(_section(len(f.marker_sets), ms))
    out.append(_section(len(f.other_markers), b"".join(_V3.pack(*p) for p in f.other_markers)))
    out.append(_section(len(f.rigid_bodies), b"".join(
        _RB.pack(r.id, *r.pos, *r.quat, r.mean_error, r.params) for r in f.rigid_bodies)))
    out.append(_section(0, b""))  # skeletons
    out.append(_section(0, b""))  # assets (4.1)
    out.append(_section(len(f.labeled_markers), b"".join(
        _LM.pack(m.id, *m.pos, m.size, m.params, m.residual) for m in f.labeled_markers)))
    out.append(_section(0, b""))  # force plates
    out.append(_section(0, b""))  # devices
    out.append(_SUFFIX.pack(f.timecode, f.timecode_sub, f.timestamp, f.stamp_mid_exposure,
                            f.stamp_data_received, f.stamp_transmit, f.precision_s, f.precision_frac,
                            f.params))
    out.append(struct.pack("<i", 0))  # end-of-data tag
    return pack_message(NAT_FRAMEOFDATA, b"".join(out))


def unpack_frame(payload: bytes) -> FrameOfData:
    """Decode a 4.1 frame of data; sections this project does not use are skipped by size.

    Parameters
    ----------
    payload : bytes
        A NAT_FRAMEOFDATA payload.

    Returns
    -------
    FrameOfData
        ``skipped`` counts the items of the sections skipped.

    Raises
    ------
    NatNetProtocolError
        When the payload is truncated or a count is out of range.
    """
    r = _Reader(payload, "NAT_FRAMEOFDATA")
    frame_number = r.one("<i")
    n = r.count("marker set")
    r.one("<i")
    marker_sets = []
    for _ in range(n):
        name = r.cstring()
        k = r.count("marker")
        marker_sets.append(MarkerSet(name, tuple(r.take("<3f") for _ in range(k))))
    n = r.count("other marker")
    r.one("<i")
    other = tuple(r.take("<3f") for _ in range(n))
    n = r.count("rigid body")
    r.one("<i")
    bodies = []
    for _ in range(n):
        rid, x, y, z, qx, qy, qz, qw, err, params = r.take(_RB.format)
        bodies.append(RigidBody(rid, (x, y, z), (qx, qy, qz, qw), err, params))
    skipped = {}
    for section in ("skeletons", "assets"):
        n, size = r.count(section), r.one("<i")
        r.skip(size)
        if n:
            skipped[section] = n
    n = r.count("labeled marker")
    r.one("<i")
    labeled = []
    for _ in range(n):
        mid, x, y, z, size, params, res = r.take(_LM.format)
        labeled.append(LabeledMarker(mid, (x, y, z), size, params, res))
    for section in ("force plates", "devices"):
        n, size = r.count(section), r.one("<i")
        r.skip(size)
        if n:
            skipped[section] = n
    tc, tcs, ts, mid_exp, recv, tx, ps, pf, params = r.take(_SUFFIX.format)
    return FrameOfData(frame_number, tuple(marker_sets), other, tuple(bodies), tuple(labeled), tc, tcs, ts,
                       mid_exp, recv, tx, ps, pf, params, skipped)


# ----------------------------------------------------------------------------- model definitions
def _pack_description(d: Description) -> bytes:
    if isinstance(d, MarkerSetDescription):
        body = _cstr(d.name) + struct.pack("<i", len(d.marker_names)) + b"".join(_cstr(s) for s in d.marker_names)
        kind = DESC_MARKERSET
    else:
        n = len(d.marker_positions)
        labels = d.marker_labels or (0,) * n
        names = d.marker_names or tuple(f"Marker{i + 1}" for i in range(n))
        if len(labels) != n or len(names) != n:
            raise NatNetProtocolError(f"rigid body {d.name!r}: {n} markers, {len(labels)} labels, {len(names)} names")
        body = (_cstr(d.name) + struct.pack("<ii", d.id, d.parent_id) + _V3.pack(*d.offset)
                + struct.pack("<i", n) + b"".join(_V3.pack(*p) for p in d.marker_positions)
                + struct.pack(f"<{n}i", *labels) + b"".join(_cstr(s) for s in names))
        kind = DESC_RIGIDBODY
    return struct.pack("<ii", kind, len(body)) + body  # 4.1: type, byte size, description


def pack_model_def(descriptions: tuple[Description, ...] | list[Description]) -> bytes:
    """The NAT_MODELDEF datagram.

    Parameters
    ----------
    descriptions : sequence of MarkerSetDescription or RigidBodyDescription

    Returns
    -------
    bytes

    Raises
    ------
    NatNetProtocolError
        When a rigid body's labels or names do not match its markers.
    """
    return pack_message(NAT_MODELDEF, struct.pack("<i", len(descriptions))
                        + b"".join(_pack_description(d) for d in descriptions))


def unpack_model_def(payload: bytes) -> list[Description]:
    """Marker set and rigid body descriptions; other kinds are skipped by their byte size.

    Parameters
    ----------
    payload : bytes
        A NAT_MODELDEF payload.

    Returns
    -------
    list of MarkerSetDescription or RigidBodyDescription

    Raises
    ------
    NatNetProtocolError
        When the payload is truncated or a description overruns its size.
    """
    r = _Reader(payload, "NAT_MODELDEF")
    out: list[Description] = []
    for _ in range(r.count("description")):
        kind, size = r.one("<i"), r.one("<i")
        start = r.off
        if kind == DESC_MARKERSET:
            name = r.cstring()
            out.append(MarkerSetDescription(name, tuple(r.cstring() for _ in range(r.count("marker")))))
        elif kind == DESC_RIGIDBODY:
            name = r.cstring()
            rid, parent = r.take("<ii")
            offset = r.take("<3f")
            n = r.count("rigid body marker")
            pos = tuple(r.take("<3f") for _ in range(n))
            labels = r.take(f"<{n}i")
            names = tuple(r.cstring() for _ in range(n))
            out.append(RigidBodyDescription(name, rid, parent, offset, pos, labels, names))
        if r.off - start > size:
            raise NatNetProtocolError(f"NAT_MODELDEF: description of type {kind} overruns its size {size}")
        r.skip(start + size - r.off)
    return out
