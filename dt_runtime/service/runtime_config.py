"""The runtime YAML of `dt run` (configs/runtime.yaml), validated once into frozen objects.

Every bound is checked here, before anything is opened: a value that would silently switch a
safeguard off (an infinite or metre-sized correction bound, a path box outside the workspace, a
speed above the maximum, a count so large that paging never happens) is a ConfigError naming the
key, the value and what is allowed. Plausible ranges are physical: this is a cobot cell of a few
metres, and its error map corrects millimetres.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from drivers import registry
from drivers.base import GAIN_RANGE, LOOKAHEAD_RANGE_S
from dt_kernel.config import Frozen, load_yaml
from dt_runtime.fabric import BusConfig
from dt_runtime.service.escalation import EscalationConfig
from dt_runtime.twin.bounds import Limits

Vec3 = tuple[float, float, float]
KINDS = registry.KINDS


def _finite(name: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be finite, got {values if len(values) > 1 else values[0]}")


class Fault(Frozen):
    """A fault injected into the simulated plant `at_s` simulated seconds after the run's first
    tick (0: from the first tick on; the world's clock already reads its registration and warm-up
    when the run starts, so `at_s` is not that clock)."""

    at_s: float = Field(ge=0)
    joint_offset_rad: tuple[float, float, float, float, float, float] | None = None
    camera_shift_m: Vec3 | None = None


class PathConfig(Frozen):
    """Targets the daemon commands: the cell's 'program' (a program file as `dt correct` reads it:
    x, y, z in mm, speed in mm/s, optional point_id; repeated from the start when done), or, as
    simulation stand-ins, 'random' points in a box (seeded) or a 'circle' streamed at the loop
    rate (set-points v / rate_hz apart). Speeds are fractions of the maximum speed, in (0, 1]."""

    kind: Literal["random", "circle", "program", "path"] = "random"
    # the program file for kind 'program' (a point program) or 'path' (a path program, streamed at
    # rate_hz: `stream`), relative to the runtime config
    program: str | None = None
    circle_center_m: Vec3 = (0.9, 0.0, 0.55)
    circle_radius_m: float = Field(0.15, gt=0, le=2.0)
    box_min_m: Vec3 = (0.65, -0.3, 0.25)
    box_max_m: Vec3 = (1.15, 0.3, 0.85)
    speeds: tuple[float, ...] = Field((0.4, 0.8), min_length=1, max_length=100)
    seed: int = 0

    @field_validator("speeds")
    @classmethod
    def _speeds(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        bad = [s for s in v if not (math.isfinite(s) and 0 < s <= 1)]
        if bad:
            raise ValueError(f"speeds are fractions of the maximum speed in (0, 1], got {bad[0]}")
        return v

    @model_validator(mode="after")
    def _check(self) -> PathConfig:
        if (self.kind in ("program", "path")) != (self.program is not None):
            raise ValueError("path.program names the program file exactly when path.kind is 'program' or 'path'")
        _finite("box_min_m/box_max_m/circle_center_m", *self.box_min_m, *self.box_max_m, *self.circle_center_m)
        if not all(lo < hi for lo, hi in zip(self.box_min_m, self.box_max_m)):
            raise ValueError(f"box_min_m {list(self.box_min_m)} must be below box_max_m {list(self.box_max_m)} "
                             "on every axis")
        return self


class StreamSection(Frozen):
    """How `dt run` streams a path program (path.kind 'path'; docs/streaming.md): the servo's
    look-ahead (s) and gain (servoj's ranges), the streaming process's SCHED_FIFO priority (0:
    none), how many passes (null: until stopped), the servo lag (`learn` from the first pass's
    readings, or `none`), the camera readings tested per second, the standard uncertainty of a
    reading's time on the path's clock (s) and how far its timing term may exceed the reading's
    own uncertainty before the reading is refused."""

    lookahead_s: float = Field(0.1, ge=LOOKAHEAD_RANGE_S[0], le=LOOKAHEAD_RANGE_S[1])
    gain: float = Field(300.0, ge=GAIN_RANGE[0], le=GAIN_RANGE[1])
    rt_priority: int = Field(10, ge=0, le=98)
    passes: int | None = Field(None, ge=1, le=10_000_000)
    lag: Literal["learn", "none"] = "learn"
    monitor_hz: float = Field(50.0, gt=0, le=1000)
    u_time_s: float = Field(0.5e-3, ge=0, le=0.1)
    max_timing_ratio: float = Field(1.0, gt=0, le=100)
    # A streaming process stops the stream (the arm stops) when the daemon gave no sign for this
    # long: a stalled daemon no longer monitors the moving arm. Many monitor periods, above a
    # loaded host's scheduling hiccups.
    host_timeout_s: float = Field(1.0, ge=0.05, le=60)


class SimSection(Frozen):
    """The simulated cell (used when a driver needs the simulated world): `scenario`, the
    simulation scenario YAML, and `cell`, the simulated cell's file (both relative to the runtime
    config); `faults` injected at their simulated times."""

    scenario: str = "scenarios/paper_default.yaml"
    cell: str = "cell.yaml"
    faults: list[Fault] = []


class DriverChoice(Frozen):
    """One driver: `kind`, its name among the installed drivers (drivers.registry: entry points),
    and its own options, checked against the driver's `config_model` (`Drivers.check`)."""

    kind: str = Field(min_length=1)
    options: dict[str, Any] = {}

    @model_validator(mode="before")
    @classmethod
    def _short(cls, value: Any) -> Any:
        """`robot: sim` is `{kind: sim}`; in `robot: {kind: serial, url: ...}` every key but
        `kind` is the driver's option."""
        if isinstance(value, str):
            return {"kind": value}
        if isinstance(value, dict) and "options" not in value:
            options = {k: v for k, v in value.items() if k != "kind"}
            return {"options": options, **({"kind": value["kind"]} if "kind" in value else {})}
        return value


class Drivers(Frozen):
    """Which driver of each kind, each with its options, e.g.::

        drivers:
          robot: {kind: serial, url: /dev/ttyUSB0, timeout_s: 2.0}
          tracker: {kind: serial, url: socket://tracker:4000}
          camera: {kind: sim_images, render: {spurious_blobs: 2}}

    (`robot: sim` is short for `robot: {kind: sim}`). The form `robot: serial` with
    `robot_config: {url: ...}` is read too, and means the same."""

    robot: DriverChoice = DriverChoice(kind="sim")
    tracker: DriverChoice = DriverChoice(kind="sim")
    camera: DriverChoice = DriverChoice(kind="sim_images")

    @model_validator(mode="before")
    @classmethod
    def _forms(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = dict(data)
        for kind in KINDS:
            legacy = data.pop(f"{kind}_config", None)
            if legacy is None:
                continue
            choice = data.get(kind, cls.model_fields[kind].default.kind)
            if not isinstance(legacy, dict) or not isinstance(choice, str):
                raise ValueError(f"{kind}_config (the earlier form) goes with `{kind}: NAME` only; "
                                 f"write `{kind}: {{kind: NAME, key: value, ...}}`")
            data[kind] = {"kind": choice, "options": legacy}
        return data

    def chosen(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(kind, name, options) of the three drivers."""
        return [(k, c.kind, c.options) for k, c in ((k, getattr(self, k)) for k in KINDS)]

    def create(self, world: Any, source: str) -> list:
        """The three drivers [robot, tracker, camera], built and configured (not yet active);
        those already built are closed if a later one fails, so nothing is left open.

        Parameters
        ----------
        world : SimWorld or None
            The simulated world the simulated drivers run on.
        source : str
            Names the runtime config in errors.

        Returns
        -------
        list
            The robot, tracker and camera drivers.

        Raises
        ------
        TwinError
            A driver could not be built (ConfigError for its options, DriverError for its device).
        """
        built: list = []
        try:
            for kind, name, options in self.chosen():
                built.append(registry.create(kind, name, options, world=world, source=source, key=f"drivers.{kind}"))
        except BaseException:
            for drv in built:
                drv.close()
            raise
        return built

    def check(self, source: str) -> None:
        """Check, before anything opens, that every driver is installed, loads, and takes its
        options (drivers.registry.check).

        Parameters
        ----------
        source : str
            Names the runtime config in errors.

        Raises
        ------
        ConfigError
            Naming `source` and the key (e.g. `drivers.tracker.url`).
        """
        for kind, name, options in self.chosen():
            registry.check(kind, name, options, source=source, key=f"drivers.{kind}")


class HaltConfig(Frozen):
    """When the daemon halts (a state of the escalation machine, stored and published on
    `.../health`), and what it does with corrections it does not trust."""

    after_refused: int = Field(10, ge=1, le=100_000)  # consecutive commands refused -> halted
    after_driver_faults: int = Field(3, ge=1, le=1_000)  # consecutive driver faults -> halted
    # No MVS reading tested (refused by the camera driver: stale, untracked, too few markers; or
    # too old for the move; or rejected) for this long, on the daemon's clock (simulated or wall)
    # -> halted: the arm stops moving unmonitored and it pages; the first accepted reading
    # resumes. Long enough that a person walking through the cameras' view does not page.
    after_camera_refused_s: float = Field(30.0, gt=0, le=86_400)
    # In out_of_control, rereference_offered and maintenance_requested the twin's correction is not trusted:
    # 'uncorrected' commands the target as is (the arm's native accuracy, still tested),
    # 'halt' stops moving until maintenance is confirmed done, 'correct' goes on correcting.
    on_untrusted: Literal["uncorrected", "halt", "correct"] = "uncorrected"


class RetentionConfig(Frozen):
    """Rolling retention of the store's high-rate rows (commands, corrections, measurements,
    t-tests); transitions, requests and operator actions are always kept. A tick writes about
    350 B: the defaults keep a day at 10 Hz (about 0.3 GB) and cap each table at 5 million rows
    (about 2 GB in all, under 3 h at 500 Hz). `null` switches a bound off."""

    max_age_s: float | None = Field(86_400.0, gt=0)  # rows older than this (daemon time) go
    max_rows: int | None = Field(5_000_000, ge=1_000)  # newest rows kept per table
    every_s: float = Field(60.0, gt=0, le=86_400)  # how often the daemon prunes (wall clock)


class RuntimeConfig(Frozen):
    """The runtime YAML of `dt run`: `twin` (a twin directory), `store` (the SQLite file),
    `rate_hz` (the loop's or the controller's rate, Hz), `realtime` (paced on the wall clock, or
    as fast as it can on the simulated clock), `alpha` (Eq. 17's significance level),
    `stop_timeout_s`, `max_measurement_age_s`, `publish` (use the bus), and the sections
    `drivers`, `sim`, `path`, `stream`, `limits`, `escalation`, `halt`, `retention` and `bus`.
    Relative paths are relative to the YAML. docs/service.md ("Configuration")."""

    twin: str  # a twin directory written by `dt demo` (DIR/model) or `dt calibrate`
    store: str = "out/run/dt.sqlite"
    rate_hz: float = Field(10.0, gt=0, le=2000)
    realtime: bool = True
    alpha: float = Field(0.05, gt=0, lt=1)
    # SIGTERM -> exit within this time even with a silent device (the move is aborted, the
    # store flushed, the bus closed; past it the process exits hard: committed rows are safe).
    stop_timeout_s: float = Field(8.0, gt=0, le=60)
    # A measurement received (host clock) longer than this before the command arrived (the move
    # returned) saw the arm elsewhere: refused, not tested (a streaming driver's last frame from
    # before the move, a stalled stream). A polled driver's reading comes after the arrival.
    max_measurement_age_s: float = Field(0.25, gt=0, le=10)
    drivers: Drivers = Drivers()
    sim: SimSection = SimSection()
    path: PathConfig = PathConfig()
    stream: StreamSection = StreamSection()
    limits: Limits = Limits()
    escalation: EscalationConfig = EscalationConfig()
    halt: HaltConfig = HaltConfig()
    retention: RetentionConfig = RetentionConfig()
    bus: BusConfig = BusConfig()
    publish: bool = True

    @model_validator(mode="after")
    def _path_in_workspace(self) -> RuntimeConfig:
        """A path that leaves the workspace would have every command refused: refuse the config."""
        lo, hi = self.limits.workspace_min_m, self.limits.workspace_max_m
        p = self.path
        corners: tuple[Vec3, ...]
        if p.kind == "random":
            corners = (p.box_min_m, p.box_max_m)
        elif p.kind == "circle":
            c, r = p.circle_center_m, p.circle_radius_m
            corners = ((c[0] - r, c[1] - r, c[2]), (c[0] + r, c[1] + r, c[2]))
        else:
            corners = ()
        for corner in corners:
            if any(not (a <= v <= b) for v, a, b in zip(corner, lo, hi)):
                raise ValueError(f"path ({p.kind}) reaches {list(corner)} m, outside the workspace "
                                 f"{list(lo)} .. {list(hi)} m (limits.workspace_*): every command there "
                                 "would be refused")
        return self


def load_runtime_config(path: str | Path) -> RuntimeConfig:
    """The runtime YAML, every driver's options checked too (`Drivers.check`).

    Parameters
    ----------
    path : str or Path
        The runtime YAML (configs/runtime.yaml).

    Returns
    -------
    RuntimeConfig

    Raises
    ------
    ConfigError
        Naming the file, the key and the value: unreadable, malformed or out-of-bounds YAML, or a
        driver that is not installed or refuses its options.
    """
    cfg = load_yaml(path, RuntimeConfig)
    cfg.drivers.check(str(path))
    return cfg


__all__ = ["DriverChoice", "Drivers", "Fault", "HaltConfig", "PathConfig", "RetentionConfig", "RuntimeConfig",
           "SimSection", "StreamSection", "load_runtime_config"]
