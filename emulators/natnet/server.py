"""A NatNet 4.1 server streaming the simulated camera rig (what Motive does for a real rig).

`NatNetEmulator` answers the command channel, streams frames of the cluster's labelled markers
and rigid body at `rate_hz` (unicast or multicast), holds both its ports as Motive does, and
injects seeded faults (dropped, delayed or untracked frames, occluded markers, renumbering).
What it answers and the faults: docs/drivers.md ("OptiTrack NatNet", "Start the emulator")."""
from __future__ import annotations

import argparse
import heapq
import select
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from drivers.mvs.cluster import kabsch
from drivers.natnet import protocol as nn
from dt_kernel.config import Frozen, validate
from dt_kernel.errors import DriverError
from emulators.natnet.rig_source import SimRigMarkers


class Faults(Frozen):
    """The emulator's injected faults (seeded by ``seed``): ``drop_probability``, ``delay_probability``
    with ``delay_s`` (s), ``untracked_probability``, ``occluded_markers`` (0-based indices).
    """
    drop_probability: float = Field(0.0, ge=0, le=1)
    delay_probability: float = Field(0.0, ge=0, le=1)
    delay_s: float = Field(0.0, ge=0, le=10)
    untracked_probability: float = Field(0.0, ge=0, le=1)
    occluded_markers: tuple[int, ...] = ()
    seed: int = 0


class EmulatorConfig(Frozen):
    """The emulator's config: address and ports (0 picks a free one), multicast and its group, frame
    rate (Hz), the server clock (``clock_hz`` ticks per second, ``clock_offset_s`` s from the host's),
    the announced app and NatNet versions, the rigid body's id and name, how long a unicast client
    stays subscribed (s), and the faults.
    """
    host: str = "127.0.0.1"
    command_port: int = Field(1510, ge=0, le=65535)
    data_port: int = Field(1511, ge=0, le=65535)
    multicast: bool = False
    data_group: str = "239.255.42.99"  # where multicast frames go (a host address works too)
    rate_hz: float = Field(120.0, gt=0, le=1000)
    clock_hz: int = Field(10_000_000, gt=0)
    clock_offset_s: float = 1000.0  # the server clock is not the host's: it starts elsewhere
    app_name: str = "Motive (dt emulator)"
    app_version: tuple[int, int, int, int] = (3, 1, 0, 0)
    natnet_version: tuple[int, int, int, int] = nn.VERSION  # another value tests clients' checks
    rigid_body_id: int = Field(1, ge=1, le=0xFFFF)
    rigid_body_name: str = "tool"
    client_timeout_s: float = Field(10.0, gt=0)
    faults: Faults = Faults()


@dataclass
class Stats:
    """The emulator's counters: frames captured, sent, dropped, delayed, untracked, and the last 10000
    dropped frame numbers."""
    frames_captured: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0
    frames_delayed: int = 0
    frames_untracked: int = 0
    dropped: list[int] = field(default_factory=list)  # frame numbers never sent (last 10000)


class NatNetEmulator:
    """The server; `start()` binds and streams in a thread, `close()` stops it (context manager).

    `source` gives the markers (emulators.natnet.rig_source.SimRigMarkers); `config` a mapping
    validated into EmulatorConfig (errors name `source_name`, the key and what is allowed)."""

    def __init__(self, source: SimRigMarkers, config: Mapping[str, Any] | None = None,
                 source_name: str = "<natnet emulator config>"):
        self.cfg = validate(EmulatorConfig, dict(config or {}), source_name)
        self.source = source
        self.stats = Stats()
        self._faults = self.cfg.faults
        self._rng = np.random.default_rng([self._faults.seed, 7])
        self._clients: dict[tuple[str, int], float] = {}
        self._pending: list[tuple[float, int, nn.FrameOfData]] = []
        self._renumber: int | None = None  # set_frame_number: the next frame's number - 1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.last_truth: dict[int, np.ndarray] = {}  # frame number -> true TCP (MVS), for scoring
        self._t0 = 0.0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> NatNetEmulator:
        """Bind both ports and start streaming on a thread.

        Returns
        -------
        NatNetEmulator
            self.

        Raises
        ------
        OSError
            When a port cannot be bound.
        """
        c = self.cfg
        try:
            self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._cmd.bind((c.host, c.command_port))
            self.command_port = self._cmd.getsockname()[1]
            self.data_port = c.data_port
            self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._data_sends = not (c.multicast and self._group() == socket.gethostbyname(c.host))
            if self._data_sends:
                self._data.bind((c.host, c.data_port))
                self.data_port = self._data.getsockname()[1]
            iface = socket.inet_aton(socket.gethostbyname(c.host))  # multicast leaves by the host's interface
            for sock in (self._cmd, self._data):
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
        except OSError as exc:
            for opened in (getattr(self, "_cmd", None), getattr(self, "_data", None)):
                if opened is not None:
                    opened.close()
            raise DriverError(f"NatNet emulator cannot bind {c.host}:{c.command_port} (commands) and"
                              f" {c.host}:{c.data_port} (data): {exc}") from exc
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="natnet-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close both sockets."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for s in (getattr(self, "_cmd", None), getattr(self, "_data", None)):
            if s is not None:
                s.close()

    def __enter__(self) -> NatNetEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def set_faults(self, **changes: Any) -> None:
        """Change the injected faults while streaming (validated like the config).

        Parameters
        ----------
        **changes
            Faults fields and their new values.

        Raises
        ------
        ConfigError
            When a value does not validate.
        """
        data = {**self._faults.model_dump(), **changes}
        with self._lock:
            self._faults = validate(Faults, data, "<NatNetEmulator.set_faults>")

    @property
    def clients(self) -> list[tuple[str, int]]:
        """The unicast clients subscribed (address, port)."""
        with self._lock:
            return list(self._clients)

    # ------------------------------------------------------------------ clock
    def ticks(self, t_host: float) -> int:
        """The server's high-resolution clock at a host time.

        Parameters
        ----------
        t_host : float
            s, host monotonic clock.

        Returns
        -------
        int
            Ticks of ``clock_hz``.
        """
        return int((t_host - self._t0 + self.cfg.clock_offset_s) * self.cfg.clock_hz)

    # ------------------------------------------------------------------ messages
    def server_info(self) -> nn.ServerInfo:
        """What NAT_SERVERINFO announces (versions, clock frequency, data port, multicast group).

        Returns
        -------
        ServerInfo
        """
        grp = tuple(int(x) for x in socket.inet_aton(self._group()))
        return nn.ServerInfo(self.cfg.app_name, self.cfg.app_version, self.cfg.natnet_version, self.cfg.clock_hz,
                             self.data_port, self.cfg.multicast, grp)  # type: ignore[arg-type]

    def _group(self) -> str:
        try:
            return socket.gethostbyname(self.cfg.data_group)
        except OSError:
            return "0.0.0.0"

    def descriptions(self) -> list[nn.Description]:
        """The model definitions: the tool's marker set and rigid body (marker offsets, pivot at the TCP).

        Returns
        -------
        list of MarkerSetDescription or RigidBodyDescription
        """
        m = self.source.markers
        names = tuple(f"{self.cfg.rigid_body_name}_{i + 1}" for i in range(len(m)))
        return [nn.MarkerSetDescription(self.cfg.rigid_body_name, names),
                nn.RigidBodyDescription(self.cfg.rigid_body_name, self.cfg.rigid_body_id, -1, (0.0, 0.0, 0.0),
                                        tuple(tuple(map(float, p)) for p in m),  # type: ignore[misc]
                                        (0,) * len(m), names)]

    def _answer(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            msg, payload = nn.unpack_message(data)
        except nn.NatNetProtocolError:
            return  # a server ignores what it cannot parse
        reply: bytes | None = None
        if msg == nn.NAT_CONNECT:
            self._subscribe(addr)
            reply = nn.pack_server_info(self.server_info())
        elif msg == nn.NAT_KEEPALIVE:
            self._subscribe(addr)
        elif msg == nn.NAT_DISCONNECT:
            with self._lock:
                self._clients.pop(addr, None)
        elif msg == nn.NAT_REQUEST_MODELDEF:
            reply = nn.pack_model_def(self.descriptions())
        elif msg == nn.NAT_REQUEST and nn.unpack_text(payload).startswith("Bitstream"):
            reply = nn.pack_text(nn.NAT_RESPONSE, "Bitstream," + ".".join(map(str, self.cfg.natnet_version)))
        else:
            reply = nn.pack_message(nn.NAT_UNRECOGNIZED_REQUEST)
        if reply is not None:
            self._cmd.sendto(reply, addr)

    def _subscribe(self, addr: tuple[str, int]) -> None:
        with self._lock:
            self._clients[addr] = time.monotonic()

    # ------------------------------------------------------------------ frames
    def make_frame(self, number: int, t_capture: float, faults: Faults) -> nn.FrameOfData:
        """One frame of data: the cluster captured now, solved as Motive solves a rigid body.

        Parameters
        ----------
        number : int
            The frame number.
        t_capture : float
            s, host monotonic time of the capture (the mid-exposure stamp).
        faults : Faults
            The faults in force.

        Returns
        -------
        FrameOfData
        """
        obs = self.source.capture(hidden=faults.occluded_markers)
        self.last_truth[number] = obs.tcp_truth
        self.last_truth.pop(number - 1000, None)
        rb_id, model = self.cfg.rigid_body_id, self.source.markers
        untracked = self._rng.random() < faults.untracked_probability
        solved = obs.seen.sum() >= 3
        err = np.zeros(len(model))
        if solved:
            R, t = kabsch(model[obs.seen], obs.X[obs.seen])
            fit = model @ R.T + t
            err = np.linalg.norm(obs.X - fit, axis=1)
            mean_err = float(err[obs.seen].mean())
        labeled, bodies = [], []
        for i in range(len(model)):
            mid = nn.marker_id(rb_id, i + 1)
            if obs.seen[i]:
                labeled.append(nn.LabeledMarker(mid, tuple(obs.X[i]), self.source.cfg.markers.diameter_m,
                                                nn.MARKER_PC_SOLVED | nn.MARKER_MODEL_SOLVED | nn.MARKER_HAS_MODEL,
                                                float(err[i])))
            elif solved:  # Motive streams an occluded member at its model-solved position
                labeled.append(nn.LabeledMarker(mid, tuple(fit[i]), self.source.cfg.markers.diameter_m,
                                                nn.MARKER_OCCLUDED | nn.MARKER_MODEL_SOLVED | nn.MARKER_HAS_MODEL, 0.0))
        if solved and not untracked:
            qx, qy, qz, qw = Rotation.from_matrix(R).as_quat()
            bodies.append(nn.RigidBody(rb_id, tuple(t), (qx, qy, qz, qw), mean_err, nn.RB_TRACKING_VALID))
        else:
            self.stats.frames_untracked += 1
            bodies.append(nn.RigidBody(rb_id, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, 0))
        ms = nn.MarkerSet(self.cfg.rigid_body_name, tuple(m.pos for m in labeled))
        stamp = self.ticks(t_capture)
        return nn.FrameOfData(number, (ms,), (), tuple(bodies), tuple(labeled),
                              timestamp=number / self.cfg.rate_hz, stamp_mid_exposure=stamp,
                              stamp_data_received=self.ticks(time.monotonic()))

    def _send(self, frame: nn.FrameOfData) -> None:
        now = time.monotonic()
        data = nn.pack_frame(replace(frame, stamp_transmit=self.ticks(now)))
        if self.cfg.multicast:
            targets = [(self.cfg.data_group, self.data_port)]
        else:
            with self._lock:
                for a in [a for a, seen in self._clients.items() if now - seen > self.cfg.client_timeout_s]:
                    del self._clients[a]
                targets = list(self._clients)
        sock = self._data if (self.cfg.multicast and self._data_sends) else self._cmd
        for addr in targets:
            try:
                sock.sendto(data, addr)
            except OSError:
                pass  # UDP: a vanished client is not the server's problem
        self.stats.frames_sent += 1

    def set_frame_number(self, number: int) -> None:
        """The next frame carries ``number``, and the count goes on from it.

        What a restarted server (back to 1) or a switched take (anywhere) does to a client.

        Parameters
        ----------
        number : int
        """
        with self._lock:
            self._renumber = int(number) - 1

    def _run(self) -> None:
        period, number = 1.0 / self.cfg.rate_hz, 0
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            while self._pending and self._pending[0][0] <= now:
                self._send(heapq.heappop(self._pending)[2])
            wake = min(next_t, self._pending[0][0]) if self._pending else next_t
            r, _, _ = select.select([self._cmd], [], [], max(0.0, wake - now))
            if r:
                try:
                    data, addr = self._cmd.recvfrom(65536)
                except OSError:
                    continue
                self._answer(data, addr)
                continue
            if time.monotonic() < next_t:
                continue
            number += 1
            with self._lock:
                faults = self._faults
                if self._renumber is not None:
                    number, self._renumber = self._renumber + 1, None
            frame = self.make_frame(number, next_t, faults)
            self.stats.frames_captured += 1
            next_t += period
            if next_t < time.monotonic() - 10 * period:  # fell far behind (a paused machine): resync
                next_t = time.monotonic() + period
            if self._rng.random() < faults.drop_probability:
                self.stats.frames_dropped += 1
                self.stats.dropped = self.stats.dropped[-9999:] + [number]
            elif faults.delay_s > 0 and self._rng.random() < faults.delay_probability:
                self.stats.frames_delayed += 1
                heapq.heappush(self._pending, (time.monotonic() + faults.delay_s, number, frame))
            else:
                self._send(frame)


def main(argv: list[str] | None = None) -> int:
    """The ``python -m emulators.natnet`` command: stream a static TCP until Ctrl-C.

    Parameters
    ----------
    argv : list of str or None
        The arguments (sys.argv[1:] when None).

    Returns
    -------
    int
        Exit status.
    """
    ap = argparse.ArgumentParser(prog="python -m emulators.natnet",
                                 description="NatNet 4.1 server streaming the simulated camera rig.")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--command-port", type=int, default=1510)
    ap.add_argument("--data-port", type=int, default=1511)
    ap.add_argument("--multicast", action="store_true", help="send frames to --data-group:--data-port")
    ap.add_argument("--data-group", default="239.255.42.99")
    ap.add_argument("--rate", type=float, default=120.0, help="frames per second")
    ap.add_argument("--cameras", default=None, help="rig config (default configs/cameras.yaml)")
    ap.add_argument("--tcp", type=float, nargs=3, default=(0.9, 0.0, 0.55), help="static TCP, world m")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drop", type=float, default=0.0, help="probability of a dropped frame")
    ap.add_argument("--delay", type=float, nargs=2, default=(0.0, 0.0), metavar=("P", "S"),
                    help="probability of a late frame and its delay (s)")
    ap.add_argument("--untracked", type=float, default=0.0, help="probability the rigid body is not tracked")
    ap.add_argument("--occlude", type=int, nargs="*", default=(), help="marker indices hidden from all cameras")
    a = ap.parse_args(argv)
    from sim.kinematics import TOOL_DOWN

    tcp = np.array(a.tcp, float)
    src = SimRigMarkers(lambda: (TOOL_DOWN, tcp), **({"config": a.cameras} if a.cameras else {}), seed=a.seed)
    faults = {"drop_probability": a.drop, "delay_probability": a.delay[0], "delay_s": a.delay[1],
              "untracked_probability": a.untracked, "occluded_markers": tuple(a.occlude), "seed": a.seed}
    cfg = {"host": a.host, "command_port": a.command_port, "data_port": a.data_port, "multicast": a.multicast,
           "data_group": a.data_group, "rate_hz": a.rate, "faults": faults}
    with NatNetEmulator(src, cfg, "<command line>") as emu:
        print(f"NatNet 4.1 emulator: commands on {a.host}:{emu.command_port}, "
              f"{'multicast to ' + a.data_group + ':' + str(a.data_port) if a.multicast else 'unicast'}; Ctrl-C stops",
              flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
