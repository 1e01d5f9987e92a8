"""NatNetRig: the OptiTrack camera system behind the CameraRig protocol, over NatNet 4.1.

It connects to Motive (or the emulator), finds the tool's rigid body, receives frames on a
thread (accepting datagrams only from the server's address and ports) and turns the newest
frame's labelled markers into the TCP with drivers.mvs.cluster's fit. Config keys, who is
listened to, frame-number resets, frame age and the refusals: docs/drivers.md ("OptiTrack NatNet")."""
from __future__ import annotations

import select
import socket
import threading
import time
from typing import Any

import numpy as np
from pydantic import Field

from drivers.base import Lifecycle, RigReading
from drivers.mvs.cluster import fit_points, point_fit_cov
from drivers.natnet import protocol as nn
from dt_kernel.config import Frozen, validate
from dt_kernel.errors import DriverError

SUPPORTED = {(4, 1)}


class NatNetConfig(Frozen):
    """The ``natnet`` camera driver's options (m, s, ports); the table is in docs/drivers.md."""
    server: str = "127.0.0.1"
    command_port: int = Field(1510, ge=1, le=65535)
    data_port: int = Field(1511, ge=1, le=65535)
    multicast: bool = False  # False: Motive's unicast mode (frames on the command socket)
    multicast_group: str = "239.255.42.99"
    local_address: str = ""  # interface to bind ("": the one the route to `server` leaves by)
    rigid_body: int | str = 1  # id or name of the tool's rigid body in Motive
    markers: tuple[tuple[float, float, float], ...] | None = None  # m, rigid-body frame; None: from Motive
    max_age_s: float = Field(0.05, gt=0)
    min_markers: int = Field(3, ge=3)
    max_residual_m: float = Field(0.5e-3, gt=0)
    marker_sigma_m: float = Field(0.1e-3, gt=0)  # one marker's standard uncertainty, per axis
    gate_sigma: float = Field(5.0, gt=0)
    timeout_s: float = Field(2.0, gt=0)  # connect / model definition reply
    read_timeout_s: float = Field(1.0, gt=0)  # wait for a new frame in read()
    keepalive_s: float = Field(1.0, gt=0)
    # A frame number further than this from the newest frame's (ahead or back) starts a new
    # reference (module docstring): 1000 frames is 8 s at Motive's 120 Hz, far beyond any
    # reordering of a healthy stream.
    max_frame_jump: int = Field(1000, ge=1, le=2**31)


class NatNetRig(Lifecycle):
    """CameraRig over an OptiTrack (Motive) NatNet 4.1 server or its emulator."""

    def __init__(self, *, world: Any = None, source: str = "<natnet camera config>"):
        self._source = source
        self.cfg = NatNetConfig()
        self.server_info: nn.ServerInfo | None = None
        self.body: nn.RigidBodyDescription | None = None
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []
        self._reset_counters()

    def _reset_counters(self) -> None:
        self.stats = {"frames_received": 0, "frames_lost": 0, "frames_late": 0, "frames_malformed": 0,
                      "frames_foreign": 0, "frame_resets": 0}
        self._latest: tuple[nn.FrameOfData, float, float] | None = None  # frame, t_recv, transit
        self._seq = 0  # counts frames that became the newest (frame numbers may restart)
        self._last_read_seq = 0
        self.last_foreign = ""  # the last sender whose datagram was ignored ("address:port")
        self.last_reset = ""  # why the frame reference was last reset
        self._missing: set[int] = set()
        self._min_transit = np.inf
        self._last_read = -1
        self.first_frame: int | None = None  # first frame number received since activation
        self._lost_at_last_read = 0
        self.last_error = ""

    # ------------------------------------------------------------------ lifecycle hooks
    def _on_configure(self, config: dict[str, Any]) -> None:
        self.cfg = validate(NatNetConfig, config, self._source)

    def _on_activate(self) -> None:
        c = self.cfg
        self._reset_counters()
        self._stop.clear()
        try:
            self._server_ip = socket.gethostbyname(c.server)
            iface = c.local_address or self._route_interface()
            self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._cmd.bind((iface, 0))
            self._sockets = [self._cmd]
            if c.multicast:
                group = socket.gethostbyname(c.multicast_group)
                self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self._data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # other clients on this host
                self._sockets.append(self._data)
                # Bound to the group's address, the socket takes only datagrams sent to the group
                # (not every datagram to the port); joined on the one interface.
                self._data.bind((group, c.data_port))
                if 224 <= int(socket.inet_aton(group)[0]) <= 239:
                    mreq = socket.inet_aton(group) + socket.inet_aton(iface)
                    self._data.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            self.server_info = self._connect()
            if c.multicast and self.server_info.data_port != c.data_port:
                raise DriverError(f"NatNet server {c.server} streams to data port {self.server_info.data_port},"
                                  f" the config's data_port is {c.data_port}")
            self.body = self._find_body(self._request_model_def())
        except OSError as exc:
            self._close_sockets()
            raise DriverError(f"NatNet server {c.server}:{c.command_port}: {exc}") from exc
        except DriverError:
            self._close_sockets()
            raise
        markers = np.array(c.markers if c.markers is not None else self.body.marker_positions, float)
        if markers.ndim != 2 or len(markers) < c.min_markers:
            self._close_sockets()
            raise DriverError(f"rigid body {self.body.name!r} (id {self.body.id}) has {len(markers)} markers;"
                              f" the cluster fit needs at least min_markers = {c.min_markers}")
        self.model = markers.reshape(-1, 3)
        self._thread = threading.Thread(target=self._receive, name="natnet-receive", daemon=True)
        self._thread.start()

    def _on_deactivate(self) -> None:
        self._stop.set()
        try:
            self._cmd.sendto(nn.pack_request(nn.NAT_DISCONNECT), self._server)
        except OSError:
            pass  # the server may be gone already
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_sockets()

    def _close_sockets(self) -> None:
        for s in self._sockets:
            s.close()
        self._sockets = []

    # ------------------------------------------------------------------ command channel
    @property
    def _server(self) -> tuple[str, int]:
        return (self._server_ip, self.cfg.command_port)

    def _route_interface(self) -> str:
        """The local address the route to the server leaves by (a UDP connect sends nothing)."""
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect((self._server_ip, self.cfg.command_port))
            return str(s.getsockname()[0])

    def _frame_ports(self) -> set[int]:
        """The server's ports frames may come from: its command port, and the data port it
        announced (Motive streams multicast from it: 1511 -> group:1511 in captures)."""
        ports = {self.cfg.command_port, self.cfg.data_port}
        if self.server_info is not None and self.server_info.data_port:
            ports = {self.cfg.command_port, self.server_info.data_port}
        return ports

    def _foreign(self, addr: tuple[str, int]) -> None:
        """A datagram from someone who is not the server: ignored and counted (caller holds no lock)."""
        with self._cond:
            self.stats["frames_foreign"] += 1
            self.last_foreign = f"{addr[0]}:{addr[1]}"

    def _exchange(self, request: bytes, want: int, what: str) -> bytes:
        """Send `request` and wait for a reply with message id `want` (frames are skipped)."""
        deadline = time.monotonic() + self.cfg.timeout_s
        tries = 0
        while time.monotonic() < deadline:
            if tries < 3:  # UDP: resend a few times within the timeout
                self._cmd.sendto(request, self._server)
                tries += 1
            r, _, _ = select.select([self._cmd], [], [], min(0.3, max(0.0, deadline - time.monotonic())))
            if not r:
                continue
            data, addr = self._cmd.recvfrom(65536)
            if (addr[0], addr[1]) != self._server:  # a reply comes from the port it was sent to
                self._foreign(addr)
                continue
            try:
                msg, payload = nn.unpack_message(data)
            except nn.NatNetProtocolError:
                continue
            if msg == want:
                return payload
            if msg == nn.NAT_UNRECOGNIZED_REQUEST:
                raise DriverError(f"NatNet server {self._server[0]}:{self._server[1]} does not know {what}")
        raise DriverError(f"NatNet server {self._server[0]}:{self._server[1]} did not answer {what}"
                          f" within {self.cfg.timeout_s} s")

    def _connect(self) -> nn.ServerInfo:
        info = nn.unpack_server_info(self._exchange(nn.pack_connect(), nn.NAT_SERVERINFO, "NAT_CONNECT"))
        if tuple(info.natnet_version[:2]) not in SUPPORTED:
            v = ".".join(map(str, info.natnet_version))
            raise DriverError(f"NatNet server {info.app_name!r} speaks NatNet {v}; this driver implements"
                              f" NatNet 4.1 only (set Motive's streaming bitstream to 4.1)")
        if info.clock_hz <= 0:
            raise DriverError(f"NatNet server {info.app_name!r} reports no high-resolution clock frequency")
        return info

    def _request_model_def(self) -> list[nn.Description]:
        payload = self._exchange(nn.pack_request(nn.NAT_REQUEST_MODELDEF), nn.NAT_MODELDEF, "NAT_REQUEST_MODELDEF")
        return nn.unpack_model_def(payload)

    def _find_body(self, descs: list[nn.Description]) -> nn.RigidBodyDescription:
        bodies = [d for d in descs if isinstance(d, nn.RigidBodyDescription)]
        want = self.cfg.rigid_body
        for b in bodies:
            if (isinstance(want, int) and b.id == want) or (isinstance(want, str) and b.name == want):
                return b
        known = ", ".join(f"{b.name!r} (id {b.id})" for b in bodies) or "none"
        raise DriverError(f"NatNet server has no rigid body {want!r}; it streams: {known}")

    # ------------------------------------------------------------------ receive thread
    def _receive(self) -> None:
        next_keepalive = 0.0
        ports = self._frame_ports()
        while not self._stop.is_set():
            if not self.cfg.multicast and time.monotonic() >= next_keepalive:
                try:
                    self._cmd.sendto(nn.pack_request(nn.NAT_KEEPALIVE), self._server)
                except OSError:
                    pass  # reported as stale frames, not as a crash of this thread
                next_keepalive = time.monotonic() + self.cfg.keepalive_s
            try:
                ready, _, _ = select.select(self._sockets, [], [], 0.1)
                for s in ready:
                    data, addr = s.recvfrom(65536)
                    if addr[0] != self._server_ip or addr[1] not in ports:
                        self._foreign(addr)
                        continue
                    self._on_datagram(data, time.monotonic())
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                time.sleep(0.05)

    def _on_datagram(self, data: bytes, t_recv: float) -> None:
        try:
            msg, payload = nn.unpack_message(data)
            if msg != nn.NAT_FRAMEOFDATA:
                return
            frame = nn.unpack_frame(payload)
        except nn.NatNetProtocolError as exc:
            with self._cond:
                self.stats["frames_malformed"] += 1
                self.last_error = str(exc)
            return
        assert self.server_info is not None
        transit = t_recv - frame.stamp_transmit / self.server_info.clock_hz
        with self._cond:
            self.stats["frames_received"] += 1
            last = self._latest[0].frame_number if self._latest else None
            n = frame.frame_number
            if last is not None:
                prev, prev_recv, _ = self._latest  # type: ignore[misc]
                # how far the server's clock moved against the host's since the newest frame: ~0
                # for a frame of the same stream (in order or not), seconds for a new server
                clock_step = ((frame.stamp_transmit - prev.stamp_transmit) / self.server_info.clock_hz
                              - (t_recv - prev_recv))
                why = self._reset_reason(n, last, t_recv - prev_recv, clock_step)
                if why:
                    self._reset_reference(why)
                    last = None
            if last is not None and n <= last:
                self.stats["frames_late"] += 1  # overtaken by a newer frame: never used
                if n in self._missing:
                    self._missing.discard(n)
                    self.stats["frames_lost"] -= 1  # it came after all: late, not lost
                return
            self._min_transit = min(self._min_transit, transit)
            if last is not None and n > last + 1:
                gap = range(last + 1, n)
                self.stats["frames_lost"] += len(gap)
                self._missing.update(gap[-1000:])
                if len(self._missing) > 5000:
                    self._missing = set(sorted(self._missing)[-1000:])
            if self.first_frame is None:
                self.first_frame = n
            self._latest = (frame, t_recv, transit)
            self._seq += 1
            self._cond.notify_all()

    def _reset_reason(self, n: int, last: int, newest_for: float, clock_step: float) -> str:
        """Why frame `n` starts a new reference after the newest `last`, received `newest_for`
        seconds ago, the server's clock having moved `clock_step` s against the host's between
        them ("" if it does not): see the module docstring."""
        jump = n - last
        if abs(jump) > self.cfg.max_frame_jump:
            way = "jumped ahead" if jump > 0 else "went back"
            return (f"frame {n} after {last}: the frame counter {way} by {abs(jump)}"
                    f" (> max_frame_jump {self.cfg.max_frame_jump})")
        if jump <= 0 and newest_for > self.cfg.max_age_s:
            return (f"frame {n} after {last}, and no newer frame for {1e3 * newest_for:.0f} ms"
                    f" (> max_age_s): the frame counter restarted")
        if jump <= 0 and abs(clock_step) > self.cfg.max_age_s:
            # a late frame of the same stream keeps its clock; a server restarted within max_age_s
            # counts again from 1 on a clock that starts elsewhere
            return (f"frame {n} after {last}, the server's clock stepped by {clock_step:+.3f} s"
                    f" (> max_age_s): the server restarted")
        return ""

    def _reset_reference(self, why: str) -> None:
        """Forget the frame numbers seen so far (the caller holds the lock)."""
        self.stats["frame_resets"] += 1
        self.last_reset = why
        self._missing.clear()
        self._min_transit = np.inf  # the clock offset is learnt again from the new stream

    # ------------------------------------------------------------------ read
    def counters(self) -> dict[str, int]:
        """frames_received, frames_lost, frames_late, frames_malformed, frames_foreign,
        frame_resets: no I/O, for a health report."""
        return dict(self.stats)

    def read(self) -> RigReading:
        """The TCP from the first frame newer than the last one read (m, the rig's frame).

        Waits up to ``read_timeout_s`` for that frame; ``t`` is the frame's mid-exposure on the server's
        clock (s), ``host_time`` when it arrived, and ``quality`` holds the frame's stamps, age and the
        counters (docs/drivers.md).

        Returns
        -------
        RigReading
            Refused, naming the frame, when no new frame came, it is stale (age > ``max_age_s``), the
            rigid body is absent or not tracked, too few markers are seen, the cluster does not fit or
            its residual exceeds ``max_residual_m``.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        with self._cond:
            self._cond.wait_for(lambda: self._seq > self._last_read_seq, timeout=self.cfg.read_timeout_s)
            latest, stats, min_transit, seq = self._latest, dict(self.stats), self._min_transit, self._seq
            foreign = self.last_foreign
        now = time.monotonic()
        if latest is None or seq <= self._last_read_seq:
            what = "no NatNet frame received" if latest is None else f"no NatNet frame after {self._last_read}"
            if stats["frames_foreign"]:
                ports = "/".join(map(str, sorted(self._frame_ports())))
                what += (f" ({stats['frames_foreign']} datagrams from other senders ignored, the last from"
                         f" {foreign}; frames are taken from {self._server_ip}:{ports} only)")
            return RigReading(None, now, quality={**stats, "host_time_s": now},  # no device time: the host's
                              refused=f"{what} within {self.cfg.read_timeout_s} s", host_time=now)
        frame, t_recv, transit = latest
        self._last_read, self._last_read_seq = frame.frame_number, seq
        assert self.server_info is not None
        hz = self.server_info.clock_hz
        server_latency = (frame.stamp_transmit - frame.stamp_mid_exposure) / hz
        age_at_recv = server_latency + (transit - min_transit)
        age = age_at_recv + (now - t_recv)
        q: dict[str, Any] = {**stats, "frames_lost_since_last_read": stats["frames_lost"] - self._lost_at_last_read,
                             "frame_number": frame.frame_number, "timestamp_s": frame.timestamp,
                             "mid_exposure_s": frame.stamp_mid_exposure / hz, "server_latency_s": server_latency,
                             "age_s": age, "host_receive_s": t_recv,
                             # the mid-exposure on the host clock (latency from exposure to use)
                             "mid_exposure_host_s": t_recv - age_at_recv}
        self._lost_at_last_read = stats["frames_lost"]

        def refuse(reason: str) -> RigReading:
            return RigReading(None, frame.stamp_mid_exposure / hz, quality=q,
                              refused=f"frame {frame.frame_number}: {reason}", host_time=t_recv)

        if age > self.cfg.max_age_s:
            return refuse(f"stale: age {1e3 * age:.1f} ms > max_age_s {1e3 * self.cfg.max_age_s:.1f} ms")
        return self._measure(frame, q, refuse, t_recv)

    def _measure(self, frame: nn.FrameOfData, q: dict[str, Any], refuse, t_recv: float) -> RigReading:
        assert self.body is not None and self.server_info is not None
        c, body = self.cfg, self.body
        name = f"rigid body {body.name!r} (id {body.id})"
        q.update({"rigid_body": body.name, "rigid_body_id": body.id})
        rb = next((r for r in frame.rigid_bodies if r.id == body.id), None)
        if rb is None:
            return refuse(f"{name} not in the frame")
        q.update({"tracking_valid": rb.tracking_valid, "mean_marker_error_m": rb.mean_error})
        if not rb.tracking_valid:
            return refuse(f"{name} not tracked (tracking-valid flag off)")
        M = len(self.model)
        X = np.full((M, 3), np.nan)
        for m in frame.labeled_markers:
            if m.model_id == body.id and 1 <= m.member_id <= M and not m.occluded:
                X[m.member_id - 1] = m.pos
        seen = np.flatnonzero(np.isfinite(X[:, 0]))
        q.update({"markers_seen": int(len(seen)), "markers_used": 0, "residual_rms_m": float("nan")})
        if len(seen) < c.min_markers:
            return refuse(f"only {len(seen)} markers of {name} seen (needs {c.min_markers})")
        cov = np.broadcast_to(np.eye(3) * c.marker_sigma_m ** 2, (M, 3, 3)).copy()
        R, t, idx, refused = fit_points(self.model, X, cov, seen, c.gate_sigma, c.min_markers)
        e = X[idx] - (self.model[idx] @ R.T + t)
        q.update({"markers_used": len(idx), "residual_rms_m": float(np.sqrt((e ** 2).sum(1).mean())),
                  "server_tcp_diff_m": float(np.linalg.norm(np.asarray(rb.pos) - t))})
        if refused:
            return refuse(refused)
        if q["residual_rms_m"] > c.max_residual_m:
            return refuse(f"cluster fit residual {1e3 * q['residual_rms_m']:.3f} mm rms"
                          f" > max_residual_m {1e3 * c.max_residual_m:.3f} mm")
        pcov = point_fit_cov(self.model[idx], R, cov[idx])
        return RigReading(t.copy(), frame.stamp_mid_exposure / self.server_info.clock_hz, cov=pcov[3:, 3:].copy(),
                          quality=q, host_time=t_recv)
