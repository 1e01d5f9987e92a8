"""`dt run`: the long-running twin daemon.

Every tick: take the next target, apply the bounded correction with the twin's maps
(service.correction) under the cell's conditions when the maps read them (joint angles from the
controller, temperature and payload from the program's columns or the simulated cell's sensors,
the clock: `twin.conditions`),
move the robot, read the MVS, test the measurement against the prediction (Eq. 17), feed the
escalation state machine, log everything to the durable store (typed rows, `service.rows`, on
the Store's one lock-free queue: the loop never waits on SQLite) and publish over Zenoh.
Drivers are built by `drivers.registry.create` from `drivers.<kind>` and `drivers.<kind>_config`,
the same way whatever their name. Entering
`maintenance_requested` writes a request to the store's outbox, which the bus republishes until
a consumer acknowledges delivery; the machine returns to nominal only when maintenance is
confirmed done (`Daemon.acknowledge_maintenance`). The machine's
state is saved on every transition and restored from the store after a restart.

`realtime: true` paces ticks at `rate_hz` on the wall clock (a real cell); `realtime: false`
runs as fast as it can on the simulated clock (soaks and tests).
"""
from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from drivers import registry
from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import ConfigError, DriverError, TwinError
from dt_runtime.service.bus import Bus, BusConfig, CorrectionServer
from dt_runtime.service.correction import CorrectionFault, Corrector, Limits, Monitor
from dt_runtime.service.escalation import EscalationConfig, Escalator
from dt_runtime.service.rows import CommandRow, CorrectionRow, MeasurementRow, TTestRow
from dt_runtime.service.store import Store, StoreError
from dt_runtime.twin.campaign import Instruments
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.program import read_program
from dt_runtime.twin.simulate import load_scenario_file
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")


class Fault(Frozen):
    """A fault injected into the simulated plant at a given (simulated) time."""

    at_s: float = Field(ge=0)
    joint_offset_rad: tuple[float, float, float, float, float, float] | None = None
    camera_shift_m: tuple[float, float, float] | None = None


class PathConfig(Frozen):
    """Targets the daemon commands: the cell's 'program' (a program file as `dt correct` reads it:
    x, y, z in mm, speed in mm/s, optional point_id; repeated from the start when done), or, as
    simulation stand-ins, 'random' points in a box (seeded) or a 'circle' streamed at the loop
    rate (set-points v / rate_hz apart)."""

    kind: Literal["random", "circle", "program"] = "random"
    program: str | None = None  # the program file for kind 'program' (relative to the runtime config)
    circle_center_m: tuple[float, float, float] = (0.9, 0.0, 0.55)
    circle_radius_m: float = Field(0.15, gt=0)
    box_min_m: tuple[float, float, float] = (0.65, -0.3, 0.25)
    box_max_m: tuple[float, float, float] = (1.15, 0.3, 0.85)
    speeds: tuple[float, ...] = (0.4, 0.8)  # fractions of the maximum speed
    seed: int = 0

    @model_validator(mode="after")
    def _program_named(self) -> PathConfig:
        if (self.kind == "program") != (self.program is not None):
            raise ValueError("path.program names the program file exactly when path.kind is 'program'")
        return self


class SimSection(Frozen):
    scenario: str = "scenarios/paper_default.yaml"
    cell: str = "cell.yaml"
    faults: list[Fault] = []


class Drivers(Frozen):
    """Which driver of each kind (drivers.registry names) and the config each one is given."""

    robot: str = "sim"
    tracker: str = "sim"
    camera: str = "sim_images"
    robot_config: dict[str, Any] = {}  # e.g. {url: /dev/ttyUSB0} for robot: serial
    tracker_config: dict[str, Any] = {}
    camera_config: dict[str, Any] = {}  # e.g. {render: {...}} for camera: sim_images

    def chosen(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(kind, name, config) of the three drivers."""
        return [(k, getattr(self, k), getattr(self, f"{k}_config")) for k in ("robot", "tracker", "camera")]


class RuntimeConfig(Frozen):
    twin: str  # a twin directory written by `dt demo` (DIR/model) or `dt calibrate`
    store: str = "out/run/dt.sqlite"
    rate_hz: float = Field(10.0, gt=0, le=2000)
    realtime: bool = True
    alpha: float = Field(0.05, gt=0, lt=1)
    drivers: Drivers = Drivers()
    sim: SimSection = SimSection()
    path: PathConfig = PathConfig()
    limits: Limits = Limits()
    escalation: EscalationConfig = EscalationConfig()
    bus: BusConfig = BusConfig()
    publish: bool = True


def load_runtime_config(path: str | Path) -> RuntimeConfig:
    return load_yaml(path, RuntimeConfig)


class Daemon:
    def __init__(self, cfg: RuntimeConfig, base: Path, world=None):
        self.cfg, self.base = cfg, base
        self.twin = Twin.load(self._p(cfg.twin))
        trained = self.twin.instruments.get("camera")
        if trained and trained != cfg.drivers.camera:
            raise ConfigError(str(self._p(cfg.twin) / "twin.json"), "instruments.camera", trained,
                              f"the daemon's camera driver '{cfg.drivers.camera}': a twin is valid only "
                              "with the instruments (and frames) it was calibrated with")
        # Read before anything is opened: a bad program stops the start with nothing to close.
        self._program = read_program(self._p(cfg.path.program)) if cfg.path.program else None
        self._check_condition_sources()
        self._step = 0  # the next program target
        self.corrector = Corrector(self.twin, cfg.limits)
        self.monitor = Monitor(self.twin, cfg.alpha)
        # High-rate rows leave the loop through the Store's lock-free queue; its writer thread
        # commits them every 50 ms, so the loop never waits on a lock or an fsync.
        self.store = Store(self._p(cfg.store), batch_ms=50.0, background=True)
        self.bus = Bus(cfg.bus, self.store, on_ack=self._on_ack) if cfg.publish else None
        # The cell's program may ask for corrections on `.../correct` (its own Corrector: the
        # step bound follows the program's sequence of requests, not the daemon's path).
        self._cond: Conditions | None = None  # the cell's latest conditions (the correct service reads them)
        self.correct_server = (CorrectionServer(Corrector(self.twin, cfg.limits), cfg.bus, self.bus.session,
                                                conditions=lambda: self._cond) if self.bus else None)
        self.world = world if world is not None else self._make_world()
        self.inst = self._make_instruments()
        self.escalator = Escalator(cfg.escalation, on_transition=self._on_transition)
        saved = self.store.load_state()
        if saved and saved.get("name") == "escalation":
            self.escalator.restore(saved["data"])
            log.info("resumed escalation state %s from %s", self.escalator.state, self.store.path)
        self._rng = np.random.default_rng(cfg.path.seed)
        self._phase = 0.0
        self._faults = sorted(cfg.sim.faults, key=lambda f: f.at_s)
        self._stop = threading.Event()
        self.delivered: list[int] = []
        self._ack_requested = threading.Event()
        self._ack_note = ""
        self.ticks = self.failures = self.faults_refused = 0
        self._true_sq: list[float] = []  # squared 3D true error of each command (simulation only)
        self.requests: list[dict] = []
        self.tick_times: list[float] | None = None  # set to [] to record tick start times

    def _check_condition_sources(self) -> None:
        """Every condition the twin's maps read must have a source, or the start fails (not every
        command later): joint angles from the controller, the clock always; temperature and
        payload from the program's columns or the simulated cell (a real cell's sensor driver:
        not yet available)."""
        sim = any(registry.needs_world(k, n) for k, n, _ in self.cfg.drivers.chosen())
        for need in self.twin.needs:
            if need in ("temperature", "payload") and not sim and getattr(self._program, need, None) is None:
                raise ConfigError(str(self._p(self.cfg.twin) / "twin.json"), "e_lt effects", need,
                                  f"a source of {need}: a program (path.kind program) with a {need} column, or "
                                  "the simulated cell's drivers")

    def _conditions(self, step: int | None) -> Conditions | None:
        """The conditions of the next command, when the twin's maps read any (else None: the
        paper's map needs none and the loop reads nothing more)."""
        if not self.twin.needs:
            return None
        base = dataclasses.replace(self.inst.conditions(), t=self._now())
        return self._program.conditions(step, base) if (self._program is not None and step is not None) else base

    def _p(self, rel: str) -> Path:
        p = Path(rel)
        return p if p.is_absolute() else self.base / p

    def _make_world(self):
        if not any(registry.needs_world(kind, name) for kind, name, _ in self.cfg.drivers.chosen()):
            return None
        from drivers.simulated.devices import SimWorld

        scenario, _ = load_scenario_file(self._p(self.cfg.sim.scenario))  # without dt simulate's `data:` block
        return SimWorld(scenario, self._p(self.cfg.sim.cell), source=str(self._p(self.cfg.sim.scenario)))

    def _make_instruments(self) -> Instruments:
        robot, tracker, camera = (
            registry.create(kind, name, config, world=self.world, source=f"<runtime config drivers.{kind}_config>")
            for kind, name, config in self.cfg.drivers.chosen())
        inst = Instruments(robot, tracker, camera, world=self.world,
                           max_speed=self.world.max_speed() if self.world else self.cfg.limits.max_speed_m_s)
        inst.activate()
        return inst

    # --- callbacks (never block: bus callbacks come from its worker thread) ---------------
    def _on_transition(self, src: str, dst: str, evidence: dict, t: float) -> None:
        log.warning("escalation %s -> %s at t=%.1f s: %s", src, dst, t, evidence)
        self.store.log_transition(src, dst, evidence, t)
        self.store.save_state("escalation", self.escalator.snapshot())
        if self.bus:
            self.bus.publish_state({"src": src, "dst": dst, "t": t, "evidence": evidence})
        if dst == "maintenance_requested":
            req = {"t": t, "state": dst, "evidence": evidence, "reason": "repeated Eq. 17 t-test failures"}
            self.requests.append(req)
            if self.bus:
                self.bus.request_maintenance(req)

    def _on_ack(self, oid: int, payload: dict) -> None:
        # Delivery acknowledgement: the request reached maintenance and leaves the outbox. The
        # machine stays in maintenance_requested until maintenance is confirmed done
        # (`acknowledge_maintenance`), or the same fault would page again at once.
        self.delivered.append(oid)

    def acknowledge_maintenance(self, note: str = "maintenance done") -> None:
        """Operator confirmation: maintenance_requested -> nominal (statistics reset)."""
        self._ack_requested.set()
        self._ack_note = note

    # --- the loop -----------------------------------------------------------------------------
    def _inject_faults(self, t: float) -> None:
        while self._faults and self._faults[0].at_s <= t:
            f = self._faults.pop(0)
            log.warning("injecting fault at t=%.1f s: %s", t, f.model_dump(exclude_none=True))
            if f.joint_offset_rad is not None:
                self.world.inject_joint_offset(f.joint_offset_rad)
            if f.camera_shift_m is not None:
                self.world.bump_camera(f.camera_shift_m)

    def _now(self) -> float:
        return self.world.t if (self.world is not None and not self.cfg.realtime) else time.time()

    def _next_target(self) -> tuple[np.ndarray, float, int | None]:
        """The next target, its speed and its program row (None off a program)."""
        pc = self.cfg.path
        if self._program is not None:
            i = self._step % self._program.n
            self._step += 1
            return self._program.target[i], float(self._program.speed[i]), i
        if pc.kind == "circle":
            v = pc.speeds[0] * self.inst.max_speed
            self._phase += v / self.cfg.rate_hz / pc.circle_radius_m
            c = np.array(pc.circle_center_m)
            return c + pc.circle_radius_m * np.array([np.cos(self._phase), np.sin(self._phase), 0.0]), v, None
        target = self._rng.uniform(np.array(pc.box_min_m), np.array(pc.box_max_m))
        return target, float(self._rng.choice(pc.speeds)) * self.inst.max_speed, None

    def tick(self) -> None:
        target, v, step = self._next_target()
        if self.world is not None:
            self._inject_faults(self.world.t)
        if self._ack_requested.is_set():
            self._ack_requested.clear()
            if self.escalator.state == "maintenance_requested":
                self.escalator.acknowledge(self._now(), note=self._ack_note)
        cond = self._cond = self._conditions(step)
        try:
            corr = self.corrector(target, v, cond)
        except CorrectionFault as exc:
            self.faults_refused += 1
            log.error("command refused, robot not moved: %s", exc)
            return
        self.inst.robot.move_linear(corr.command, v)
        if self.world is not None:  # simulation: the true error in GL, as `dt demo` scores it (target - truth)
            tw = self.twin
            e = tw.T_rdk.apply(corr.target) - tw.T_lt.apply(self.world.truth_in_tracker_frame())
            self._true_sq.append(float(np.sum(e ** 2)))
        t = self._now()
        x, y, z = corr.target
        self.store.put(CommandRow(t, x, y, z, speed=v))
        self.store.put(CorrectionRow(t, *corr.correction, *corr.u_tcp))
        camera = self.inst.camera
        assert camera is not None  # _make_instruments always builds one (drivers.camera names a driver)
        reading = camera.read()
        self.ticks += 1
        if not reading.ok or reading.point is None:
            log.info("MVS refused: %s", reading.refused)
            return
        try:
            chk = self.monitor(corr.command, v, reading.point, cond)
        except CorrectionFault as exc:
            log.error("MVS value rejected: %s", exc)
            return
        self.store.put(MeasurementRow(t, *reading.point, *chk.diff))
        worst = int(np.argmax(np.abs(chk.t)))
        self.store.put(TTestRow(t, float(chk.t[worst]), None, float(np.min(chk.p_value)), chk.passed,
                                data={"t": chk.t.tolist()}))
        self.failures += int(not chk.passed)
        self.escalator.observe(chk.passed, float(chk.t[worst]), t)
        if self.bus:
            self.bus.publish_telemetry({"t": t, "target": corr.target.tolist(), "command": corr.command.tolist(),
                                        "t_stat": chk.t.tolist(), "passed": chk.passed,
                                        "state": self.escalator.state})

    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> dict:
        period = 1.0 / self.cfg.rate_hz
        t0 = self._now()
        next_t = time.monotonic()
        while not self._stop.is_set():
            if max_ticks is not None and self.ticks >= max_ticks:
                break
            if duration_s is not None and self._now() - t0 >= duration_s:
                break
            if self.tick_times is not None:
                self.tick_times.append(time.perf_counter())
            try:
                self.tick()
            except StoreError as exc:  # disk full: keep controlling, rows are retried
                log.error("store write failed, continuing: %s", exc)
            except DriverError as exc:
                log.error("driver fault: %s", exc)
                time.sleep(min(period, 0.1))
            if self.cfg.realtime:
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    # Sleep to just before the tick, then spin: OS wake-up latency is ~0.1-1 ms.
                    if delay > 1e-3:
                        self._stop.wait(delay - 1e-3)
                    while time.monotonic() < next_t:
                        pass
                else:
                    next_t = time.monotonic()
        return self.summary()

    def stop(self, *_: Any) -> None:
        self._stop.set()

    def summary(self) -> dict:
        out = {"ticks": self.ticks, "t_test_failures": self.failures, "refused_commands": self.faults_refused,
               "state": self.escalator.state, "maintenance_requests": len(self.requests),
               "requests_delivered": len(self.delivered),
               "store": str(self.store.path)}
        if self._true_sq:  # the simulated cell's truth: 3D RMS of target - where the arm went
            out["true_rms_mm"] = round(float(np.sqrt(np.mean(self._true_sq))) * 1e3, 5)
            out["true_n"] = len(self._true_sq)
        return out

    def close(self) -> None:
        try:
            self.store.save_state("escalation", self.escalator.snapshot())
            self.store.flush()
        except TwinError as exc:
            log.error("could not save state on close: %s", exc)
        if self.correct_server:
            self.correct_server.close()
        if self.bus:
            self.bus.close()
        self.inst.close()
        self.store.close()


def run_daemon(config: str | Path, duration_s: float | None = None) -> dict:
    config = Path(config)
    cfg = load_runtime_config(config)
    d = Daemon(cfg, config.parent)
    signal.signal(signal.SIGINT, d.stop)
    signal.signal(signal.SIGTERM, d.stop)
    try:
        return d.run(duration_s)
    finally:
        d.close()
