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
    """Refuse a driver config that holds a key the driver does not know.

    Parameters
    ----------
    config : Mapping
        The driver's options as given.
    source : str
        Names the config in the error (e.g. the YAML file).
    allowed : tuple of str
        The keys the driver knows (none by default).
    what : str
        Names the driver in the error's hint.

    Raises
    ------
    ConfigError
        Naming the first unknown key (in sorted order) and listing the allowed ones.
    """
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
        """The one way to build any driver: ``cls(world=world, source=source)``, then configured.

        Parameters
        ----------
        config : Mapping or None
            The driver's options; given, the driver is configured (state ``inactive``); None leaves
            it ``unconfigured``.
        world : object, optional
            The simulated cell, for drivers with ``needs_world = True``; others ignore it.
        source : str
            Names the config in errors.

        Returns
        -------
        Lifecycle
            The driver, of class ``cls``.

        Raises
        ------
        ConfigError
            When ``configure`` refuses the options.
        """
        drv = cls(world=world, source=source)
        if config is not None:
            drv.configure(config)
        return drv

    @property
    def state(self) -> str:
        """The lifecycle state: ``unconfigured``, ``inactive``, ``active`` or ``closed``."""
        return self._state

    def _require(self, *states: str) -> None:
        if self._state not in states:
            raise StateError(
                f"{type(self).__name__}: call not allowed in state '{self._state}'"
                f" (needs {' or '.join(states)})"
            )

    def configure(self, config: Mapping[str, Any] | None = None) -> None:
        """Check and apply the driver's options (from ``unconfigured`` or ``inactive``; ends ``inactive``).

        Parameters
        ----------
        config : Mapping or None
            The driver's options; None is an empty mapping.

        Raises
        ------
        StateError
            When the driver is ``active`` or ``closed``.
        ConfigError
            When the driver refuses an option.
        """
        self._require(UNCONFIGURED, INACTIVE)
        self._on_configure(dict(config or {}))
        self._state = INACTIVE

    def activate(self) -> None:
        """Open the device (from ``inactive``; ends ``active``).

        Raises
        ------
        StateError
            When the driver is not ``inactive``.
        """
        self._require(INACTIVE)
        self._on_activate()
        self._state = ACTIVE

    def deactivate(self) -> None:
        """Release the device (from ``active``; ends ``inactive``).

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require(ACTIVE)
        self._on_deactivate()
        self._state = INACTIVE

    def close(self) -> None:
        """Close the driver for good (deactivating it first when ``active``); closing twice does nothing."""
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
        """The Event ``abort`` sets (created on first use); a driver's waits poll it."""
        ev = self.__dict__.get("_abort_ev")
        if ev is None:
            ev = self.__dict__.setdefault("_abort_ev", threading.Event())
        return ev

    def abort(self, reason: str = "stopping") -> None:
        """Make a move or request in flight end with DriverError and refuse later ones until ``clear_abort``.

        Only sets an Event: safe from any thread or a signal handler.

        Parameters
        ----------
        reason : str
            Stated in the DriverError.
        """
        self._abort_reason = str(reason)
        self.abort_event.set()

    def clear_abort(self) -> None:
        """Accept moves and requests again after ``abort``."""
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
    """Joint positions read from the controller: ``q`` (rad, encoders), ``t`` (s, device clock),
    ``host_time`` (s, host monotonic clock at receipt).
    """
    q: np.ndarray  # rad, encoder reading
    t: float  # s, device clock
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt


@dataclass(frozen=True)
class TrackerReading(_Stamped):
    """One laser-tracker measurement: ``point`` (3,) m in the tracker frame, ``spherical``
    (distance m, azimuth rad, elevation rad), ``t`` (s, device clock), ``status`` ("ok" or a reason
    such as "beam_broken") and ``host_time`` (s, host monotonic clock at receipt).
    """
    point: np.ndarray  # (3,) m, tracker frame (cartesian from d, azimuth, elevation)
    spherical: tuple[float, float, float]  # (d m, azimuth rad, elevation rad)
    t: float  # s, device clock
    status: str = "ok"  # "ok" or a reason such as "beam_broken"
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt

    @property
    def ok(self) -> bool:
        """True when the tracker measured (``status == "ok"``)."""
        return self.status == "ok"


@dataclass(frozen=True)
class RigReading(_Stamped):
    """One camera-rig measurement of the TCP point: ``point`` (3,) m in the MVS frame (None
    when refused), ``t`` (s, device clock, the exposure), ``cov`` (3, 3) m^2 when known, ``quality``
    (markers_used, cameras_used, reproj_rms_px, ...), ``refused`` (the reason, when no point is
    reported) and ``host_time`` (s, host monotonic clock at receipt of the frames).
    """
    point: np.ndarray | None  # (3,) m, MVS frame; None when refused
    t: float  # s, device clock (the frame's exposure)
    cov: np.ndarray | None = None  # (3,3) m^2 propagated from pixel noise, if known
    quality: Mapping[str, Any] = field(default_factory=dict)  # markers_used, cameras_used, reproj_rms_px
    refused: str | None = None  # reason, when no measurement is reported
    host_time: float = field(default_factory=time.monotonic)  # s, host monotonic clock at receipt of the frames

    @property
    def ok(self) -> bool:
        """True when a point was measured (not refused)."""
        return self.refused is None and self.point is not None


@runtime_checkable
class RobotController(Protocol):
    """What every robot-controller driver offers: the lifecycle, linear moves, joint and TCP reads, abort."""
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None:
        """Check and apply the driver's options (see ``Lifecycle.configure``).

        Parameters
        ----------
        config : Mapping or None
            The driver's options.
        """
        ...
    def activate(self) -> None:
        """Connect to the controller (see ``Lifecycle.activate``)."""
        ...
    def deactivate(self) -> None:
        """Disconnect from the controller (see ``Lifecycle.deactivate``)."""
        ...
    def close(self) -> None:
        """Close the driver for good (see ``Lifecycle.close``)."""
        ...

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Linear move of the TCP; returns when settled.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s.

        Raises
        ------
        DriverError
            When the arguments are out of range, the move fails or is aborted.
        """

    def read_joint_state(self) -> JointState:
        """The joint positions from the encoders.

        Returns
        -------
        JointState
        """
        ...

    def read_commanded_tcp(self) -> np.ndarray:
        """The controller's own TCP (m, robot frame) from its encoders and nominal kinematics."""

    def abort(self, reason: str = "stopping") -> None:
        """End a move in flight promptly (DriverError) and refuse moves until ``clear_abort``.

        Callable from any thread or a signal handler (``Abortable``).

        Parameters
        ----------
        reason : str
            Stated in the DriverError.
        """

    def clear_abort(self) -> None:
        """Accept moves again after ``abort``."""
        ...


class WatchdogStop(DriverError):
    """A set-point refused because the controller's stream watchdog stopped the arm: no set-point
    came from the host for the watchdog's time (the host stalled or is gone; the cell is fine)."""


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

    def start_stream(self, rate_hz: float, lookahead_s: float = 0.1, gain: float = 300.0) -> None:
        """Make the controller follow set-points.

        Parameters
        ----------
        rate_hz : float
            One set-point expected every 1/``rate_hz`` s.
        lookahead_s : float
            The servo's look-ahead time (s), within ``LOOKAHEAD_RANGE_S``.
        gain : float
            The servo's proportional gain, within ``GAIN_RANGE``.

        Raises
        ------
        DriverError
            When a parameter is out of range or the controller refuses.
        """
        ...
    def stream(self, target: np.ndarray, t: float) -> None:
        """Hand over one set-point and return at once (never waits for the arm).

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        t : float
            s, the caller's clock (increasing): the time the set-point is meant for.

        Raises
        ------
        DriverError
            When the controller refuses it (protective stop, stopped by the watchdog), naming the reason.
        """
        ...
    def stop_stream(self) -> None:
        """End the stream; the arm stops where the stream left it."""
        ...
    def stream_status(self) -> StreamStatus:
        """What the driver knows of its stream.

        Returns
        -------
        StreamStatus
        """
        ...


def streams(driver: Any) -> bool:
    """True when the driver declares the streaming capability (implements SetpointStreamer).

    Parameters
    ----------
    driver : object
        A robot driver.

    Returns
    -------
    bool
    """
    return isinstance(driver, SetpointStreamer)


def check_stream_params(rate_hz: Any, lookahead_s: Any, gain: Any, max_rate_hz: float) -> tuple[float, float, float]:
    """A stream's rate, look-ahead and gain as floats, checked.

    Parameters
    ----------
    rate_hz : object
        Hz; 0 < rate <= ``max_rate_hz``.
    lookahead_s : object
        s; within ``LOOKAHEAD_RANGE_S``.
    gain : object
        Within ``GAIN_RANGE``.
    max_rate_hz : float
        The controller's loop rate (Hz).

    Returns
    -------
    rate_hz, lookahead_s, gain : float

    Raises
    ------
    DriverError
        Saying what is allowed, when one is out of range or not finite.
    """
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
    """What every laser-tracker driver offers: the lifecycle and ``measure``."""
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None:
        """Check and apply the driver's options (see ``Lifecycle.configure``).

        Parameters
        ----------
        config : Mapping or None
            The driver's options.
        """
        ...
    def activate(self) -> None:
        """Connect to the tracker (see ``Lifecycle.activate``)."""
        ...
    def deactivate(self) -> None:
        """Disconnect from the tracker (see ``Lifecycle.deactivate``)."""
        ...
    def close(self) -> None:
        """Close the driver for good (see ``Lifecycle.close``)."""
        ...

    def measure(self) -> TrackerReading:
        """Measure the SMR (m, tracker frame).

        Returns
        -------
        TrackerReading
            ``status`` says why when the tracker could not measure.
        """
        ...


@runtime_checkable
class CameraRig(Protocol):
    """What every camera-rig driver offers: the lifecycle and ``read``."""
    state: str

    def configure(self, config: Mapping[str, Any] | None = None) -> None:
        """Check and apply the driver's options (see ``Lifecycle.configure``).

        Parameters
        ----------
        config : Mapping or None
            The driver's options.
        """
        ...
    def activate(self) -> None:
        """Open the rig (see ``Lifecycle.activate``)."""
        ...
    def deactivate(self) -> None:
        """Release the rig (see ``Lifecycle.deactivate``)."""
        ...
    def close(self) -> None:
        """Close the driver for good (see ``Lifecycle.close``)."""
        ...

    def read(self) -> RigReading:
        """Measure the TCP/SMR point from the marker cluster (m, MVS frame)."""


def check_move(target: Any, speed: Any, tcp_abs_m: float, max_speed_m_s: float) -> tuple[np.ndarray, float]:
    """A controller's move arguments, checked (as a real controller's driver does before sending).

    Parameters
    ----------
    target : object
        (3,) m; every coordinate finite and within ±``tcp_abs_m``.
    speed : object
        m/s; 0 < speed <= ``max_speed_m_s``.
    tcp_abs_m : float
        The largest coordinate allowed (m).
    max_speed_m_s : float
        The fastest speed allowed (m/s).

    Returns
    -------
    target : ndarray
        (3,) m.
    speed : float
        m/s.

    Raises
    ------
    DriverError
        Saying what is allowed.
    """
    target = np.asarray(target, dtype=float)
    if target.shape != (3,) or not np.all(np.isfinite(target)) or np.any(np.abs(target) > tcp_abs_m):
        raise DriverError(f"invalid move target {target!r}: need 3 finite coordinates within ±{tcp_abs_m} m")
    speed = float(speed)
    if not (math.isfinite(speed) and 0.0 < speed <= max_speed_m_s):
        raise DriverError(f"invalid speed {speed!r}: need 0 < speed <= {max_speed_m_s} m/s")
    return target, speed


def read_exposed_after(camera: CameraRig, t_host: float, tries: int = 3) -> RigReading:
    """The camera's reading exposed after host time ``t_host`` (e.g. the move's arrival).

    A streaming camera hands out its newest frame, which may have been exposed while the arm was
    still settling: when the reading states its mid-exposure on the host clock
    (``quality["mid_exposure_host_s"]``, NatNet) and that precedes ``t_host``, the next frame is
    read, at most ``tries`` times in all. A reading without that stamp (a polled camera, exposed
    when asked) is returned as it is, and so is the last one tried.

    Parameters
    ----------
    camera : CameraRig
        An active camera rig.
    t_host : float
        s, host monotonic clock.
    tries : int
        Reads at most.

    Returns
    -------
    RigReading
    """
    reading = camera.read()
    for _ in range(tries - 1):
        mid = reading.quality.get("mid_exposure_host_s") if reading.ok else None
        if mid is None or mid >= t_host:
            break
        reading = camera.read()
    return reading
