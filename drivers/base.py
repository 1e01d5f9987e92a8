"""Driver interfaces (typing.Protocol) and the shared lifecycle.

Lifecycle: unconfigured --configure--> inactive --activate--> active --deactivate--> inactive
--close--> closed. Calling read/write outside `active` raises StateError. Units: SI, robot
frame for the controller, the instrument's own frame for the tracker and the camera rig.

Construction is uniform: every driver class takes the keywords `world` (the simulated cell, for
drivers with `needs_world = True`; others ignore it) and `source` (names the config in errors),
and `Lifecycle.from_config(config, world=..., source=...)` builds one and configures it. The
registry (drivers.registry.create) uses only that, so no caller branches on a driver's name.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel

from dt_kernel.errors import ConfigError, DriverError, StateError

UNCONFIGURED, INACTIVE, ACTIVE, CLOSED = "unconfigured", "inactive", "active", "closed"


def reject_keys(config: Mapping[str, Any], source: str, allowed: tuple[str, ...] = (),
                what: str = "this driver") -> None:
    """ConfigError naming the first key of `config` that is not in `allowed`."""
    unknown = sorted(set(config) - set(allowed))
    if unknown:
        known = ", ".join(allowed) if allowed else "none"
        raise ConfigError(source, unknown[0], config[unknown[0]], f"{what} knows the keys: {known}")


class Lifecycle:
    """Mixin enforcing the lifecycle; subclasses override the `_on_*` hooks."""

    _state: str = UNCONFIGURED
    #: True for drivers that run on the simulated world: the caller must pass `world`.
    needs_world: ClassVar[bool] = False
    #: The driver's options (a pydantic model, e.g. a dt_kernel.config.Frozen): declared, they are
    #: checked with the runtime YAML before any driver is opened (drivers.registry.check);
    #: None: the driver checks them in `configure`.
    config_model: ClassVar[type[BaseModel] | None] = None

    def __init__(self, *, world: Any = None, source: str = "<driver config>") -> None:
        """The constructor every driver offers (its own may take more, all optional)."""
        self._source = source

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None = None, *, world: Any = None,
                    source: str = "<driver config>"):
        """The one way to build any driver: `cls(world=world, source=source)`, configured with
        `config` when one is given (state `inactive`), else left `unconfigured`."""
        drv = cls(world=world, source=source)
        if config is not None:
            drv.configure(config)
        return drv

    @property
    def state(self) -> str:
        return self._state

    def _require(self, *states: str) -> None:
        if self._state not in states:
            raise StateError(
                f"{type(self).__name__}: call not allowed in state '{self._state}'"
                f" (needs {' or '.join(states)})"
            )

    def configure(self, config: Mapping[str, Any] | None = None) -> None:
        self._require(UNCONFIGURED, INACTIVE)
        self._on_configure(dict(config or {}))
        self._state = INACTIVE

    def activate(self) -> None:
        self._require(INACTIVE)
        self._on_activate()
        self._state = ACTIVE

    def deactivate(self) -> None:
        self._require(ACTIVE)
        self._on_deactivate()
        self._state = INACTIVE

    def close(self) -> None:
        if self._state == CLOSED:
            return
        if self._state == ACTIVE:
            self.deactivate()
        self._on_close()
        self._state = CLOSED

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # hooks
    def _on_configure(self, config: dict[str, Any]) -> None: ...
    def _on_activate(self) -> None: ...
    def _on_deactivate(self) -> None: ...
    def _on_close(self) -> None: ...


class Abortable:
    """The host's stop button for a robot driver (mixin): `abort(reason)` makes a move or request
    in flight end promptly with DriverError and refuses later ones until `clear_abort()`. It only
    sets an Event: safe from any thread or a signal handler, it never blocks or takes a lock.
    A driver calls `_check_abort()` before a move and wherever it waits (the serial link checks
    the event while it polls for a reply)."""

    _abort_reason: str = ""

    @property
    def abort_event(self) -> threading.Event:
        ev = self.__dict__.get("_abort_ev")
        if ev is None:
            ev = self.__dict__.setdefault("_abort_ev", threading.Event())
        return ev

    def abort(self, reason: str = "stopping") -> None:
        self._abort_reason = str(reason)
        self.abort_event.set()

    def clear_abort(self) -> None:
        self.abort_event.clear()

    def _check_abort(self) -> None:
        if self.abort_event.is_set():
            raise DriverError(f"{type(self).__name__}: aborted ({self._abort_reason})")


# Clocks. Every reading carries two times: `t`, the device's own clock (s; `device_time`: the
# controller's or instrument's time stamp, the simulated clock for simulated drivers), and
# `host_time`, this host's time.monotonic() when the reading arrived (s). The device's clock
# orders a device's readings; only the host's can be compared with the host's other events (a
# command's arrival), so the daemon's staleness check and latency use `host_time`. A driver sets
# it at receipt (before parsing); left out, it is the moment the reading is built.
class _Stamped:
    t: float

    @property
    def device_time(self) -> float:
        """The device's time stamp (s, its own clock): `t`."""
        return self.t


@dataclass(frozen=True)
class JointState(_Stamped):
    q: np.ndarray  # rad, encoder reading
    t: float  # s, device clock
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt


@dataclass(frozen=True)
class TrackerReading(_Stamped):
    point: np.ndarray  # (3,) m, tracker frame (cartesian from d, azimuth, elevation)
    spherical: tuple[float, float, float]  # (d m, azimuth rad, elevation rad)
    t: float  # s, device clock
    status: str = "ok"  # "ok" or a reason such as "beam_broken"
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class RigReading(_Stamped):
    point: np.ndarray | None  # (3,) m, MVS frame; None when refused
    t: float  # s, device clock (the frame's exposure)
    cov: np.ndarray | None = None  # (3,3) m^2 propagated from pixel noise, if known
    quality: Mapping[str, Any] = field(default_factory=dict)  # markers_used, cameras_used, reproj_rms_px
    refused: str | None = None  # reason, when no measurement is reported
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt of the frames

    @property
    def ok(self) -> bool:
        return self.refused is None and self.point is not None


@runtime_checkable
class RobotController(Protocol):
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None: ...
    def activate(self) -> None: ...
    def deactivate(self) -> None: ...
    def close(self) -> None: ...

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Linear move of the TCP to `target` (m, robot frame) at `speed` (m/s); returns when settled."""

    def read_joint_state(self) -> JointState: ...

    def read_commanded_tcp(self) -> np.ndarray:
        """The controller's own TCP (m, robot frame) from its encoders and nominal kinematics."""

    def abort(self, reason: str = "stopping") -> None:
        """End a move in flight promptly (DriverError) and refuse moves until `clear_abort`;
        callable from any thread or a signal handler (`Abortable`)."""

    def clear_abort(self) -> None: ...


# Streaming set-points is a capability a robot driver declares by implementing SetpointStreamer
# (`streams(driver)`), not a method every driver must fake with a blocking move: a controller
# that follows a stream (a UR's servoj over RTDE registers) keeps moving between set-points,
# with the lag and overshoot of its servo, and stops by itself when the stream stops.
LOOKAHEAD_RANGE_S = (0.03, 0.2)  # servoj's lookahead_time (URScript manual): smoothing vs. lag
GAIN_RANGE = (100.0, 2000.0)  # servoj's proportional gain (URScript manual)


@dataclass(frozen=True)
class StreamStatus:
    """What a streaming driver knows of its stream. `state`: "idle" (never started or stopped
    by the host), "streaming", or "stopped" (the controller ended it: `reason` says why, e.g.
    the watchdog or a protective stop). `sent`: set-points written since `start_stream`;
    `consumed`: the newest set-point number the controller has taken (0: none yet, -1: unknown);
    `cycles_quiet`: control cycles since the controller last saw a new one (-1: unknown)."""

    state: str
    sent: int = 0
    consumed: int = -1
    reason: str = ""
    rate_hz: float = 0.0
    lookahead_s: float = 0.0
    gain: float = 0.0
    cycles_quiet: int = -1


@runtime_checkable
class SetpointStreamer(Protocol):
    """A robot driver that follows a stream of TCP set-points at the controller's rate.

    `start_stream` makes the controller follow set-points (servo with `lookahead_s` and `gain`,
    one expected every 1/`rate_hz` s); `stream(target, t)` hands over one set-point (m, robot
    frame) meant for time `t` (s, the caller's clock, increasing) and returns at once, never
    waiting for the arm; a set-point the controller refuses (protective stop, the watchdog has
    stopped the stream) is a DriverError naming the reason. `stop_stream` ends it (the arm stops
    where the stream left it). If the host stops calling `stream` for the controller's watchdog
    time, the controller stops the arm by itself."""

    def start_stream(self, rate_hz: float, lookahead_s: float = 0.1, gain: float = 300.0) -> None: ...
    def stream(self, target: np.ndarray, t: float) -> None: ...
    def stop_stream(self) -> None: ...
    def stream_status(self) -> StreamStatus: ...


def streams(driver: Any) -> bool:
    """True when the driver declares the streaming capability (implements SetpointStreamer)."""
    return isinstance(driver, SetpointStreamer)


def check_stream_params(rate_hz: Any, lookahead_s: Any, gain: Any, max_rate_hz: float) -> tuple[float, float, float]:
    """A stream's rate (Hz), look-ahead (s) and gain as floats, or DriverError saying what is allowed."""
    rate, la, g = float(rate_hz), float(lookahead_s), float(gain)
    if not (math.isfinite(rate) and 0.0 < rate <= max_rate_hz):
        raise DriverError(f"invalid stream rate {rate_hz!r} Hz: need 0 < rate <= {max_rate_hz} Hz "
                          "(the controller's loop)")
    lo, hi = LOOKAHEAD_RANGE_S
    if not (math.isfinite(la) and lo <= la <= hi):
        raise DriverError(f"invalid look-ahead time {lookahead_s!r} s: need {lo} <= lookahead_s <= {hi} s")
    lo, hi = GAIN_RANGE
    if not (math.isfinite(g) and lo <= g <= hi):
        raise DriverError(f"invalid servo gain {gain!r}: need {lo:g} <= gain <= {hi:g}")
    return rate, la, g


@runtime_checkable
class LaserTracker(Protocol):
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None: ...
    def activate(self) -> None: ...
    def deactivate(self) -> None: ...
    def close(self) -> None: ...

    def measure(self) -> TrackerReading: ...


@runtime_checkable
class CameraRig(Protocol):
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None: ...
    def activate(self) -> None: ...
    def deactivate(self) -> None: ...
    def close(self) -> None: ...

    def read(self) -> RigReading:
        """Measure the TCP/SMR point from the marker cluster (m, MVS frame)."""


def check_move(target: Any, speed: Any, tcp_abs_m: float, max_speed_m_s: float) -> tuple[np.ndarray, float]:
    """A controller's move arguments as (3,) m and m/s, or DriverError saying what is allowed
    (a real controller's drivers check them before anything is sent)."""
    target = np.asarray(target, dtype=float)
    if target.shape != (3,) or not np.all(np.isfinite(target)) or np.any(np.abs(target) > tcp_abs_m):
        raise DriverError(f"invalid move target {target!r}: need 3 finite coordinates within ±{tcp_abs_m} m")
    speed = float(speed)
    if not (math.isfinite(speed) and 0.0 < speed <= max_speed_m_s):
        raise DriverError(f"invalid speed {speed!r}: need 0 < speed <= {max_speed_m_s} m/s")
    return target, speed


def read_exposed_after(camera: CameraRig, t_host: float, tries: int = 3) -> RigReading:
    """The camera's reading exposed after host time `t_host` (e.g. the move's arrival).

    A streaming camera hands out its newest frame, which may have been exposed while the arm was
    still settling: when the reading states its mid-exposure on the host clock
    (`quality["mid_exposure_host_s"]`, NatNet) and that precedes `t_host`, the next frame is
    read, at most `tries` times in all. A reading without that stamp (a polled camera, exposed
    when asked) is returned as it is, and so is the last one tried."""
    reading = camera.read()
    for _ in range(tries - 1):
        mid = reading.quality.get("mid_exposure_host_s") if reading.ok else None
        if mid is None or mid >= t_host:
            break
        reading = camera.read()
    return reading
