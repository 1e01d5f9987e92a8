"""`dt run`: the long-running twin daemon of one cell, and its composition root.

Every tick of a point program: target -> bounded correction -> move -> MVS reading -> Eq. 17
test -> escalation -> store and bus (`Daemon.tick`); a path program runs passes instead
(`service.path_run`). `Daemon._start` builds every part in one place and registers what it opens
on one `Parts` stack, closed newest first by `close()` or when the start fails half way; the
parts live in the sibling modules (supervisor, paging, health, housekeeping, ...).

What it guarantees, halts, health, the operator, pacing, start and stop, and the module map:
docs/service.md; the bus keys: docs/bus.md.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import RigReading, read_exposed_after
from dt_kernel.errors import DriverError, TwinError
from dt_runtime.common.paths import beside
from dt_runtime.fabric.queries import QueryServer
from dt_runtime.programs.program import read_program
from dt_runtime.service import sdnotify
from dt_runtime.service.answers import answers, twin_identity
from dt_runtime.service.cell import Cell, open_cell
from dt_runtime.service.correction_server import CorrectionServer
from dt_runtime.service.counters import Counters
from dt_runtime.service.events import ActionQueued, Events, HealthDue, RequestsQueued, Transition
from dt_runtime.service.health import CellStatus, HealthReporter, StatusLine
from dt_runtime.service.housekeeping import Housekeeper
from dt_runtime.service.paging import Paging
from dt_runtime.service.path_run import (
    PassHooks,
    PathPlan,
    PathStreamer,
    StreamCell,
    StreamState,
    check_streaming_robot,
    plan_path,
)
from dt_runtime.service.preflight import check_camera, check_condition_sources, check_model
from dt_runtime.service.publisher import Bus
from dt_runtime.service.rereference import MvsFrame
from dt_runtime.service.rows import CommandRow, CorrectionRow, MeasurementRow, TTestRow
from dt_runtime.service.runtime_config import (  # noqa: F401 - re-exported: the daemon's config
    Drivers,
    Fault,
    HaltConfig,
    PathConfig,
    RetentionConfig,
    RuntimeConfig,
    SimSection,
    load_runtime_config,
)
from dt_runtime.service.store import Store, StoreError
from dt_runtime.service.supervisor import Step, Supervisor
from dt_runtime.service.targets import probe_point, targets_for
from dt_runtime.twin.adaptive import AdaptiveCoverage
from dt_runtime.twin.bounds import Corrected, CorrectionFault, Guard
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.monitor import Check, Monitor
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")
PACED_SWITCH_INTERVAL_S = 2e-4  # the GIL's switch interval while the loop is paced (`run`)
MAX_HOST_STALLS = 3  # passes in a row stopped by a host stall (the controller's watchdog) resumed without a halt
HOST_STALL_WAIT_S = 0.5  # the pause before such a resume (a burst of load may pass)


class Parts(ExitStack):
    """What the daemon opened, closed newest first by `close()`; a close that fails is logged and
    the others are still closed (each bounded by its own time-out)."""

    def callback(self, close: Callable[..., Any], /, *args: Any, **kwds: Any) -> Callable[..., Any]:
        """Register `close(*args, **kwds)`, called when the stack closes (best effort: an
        exception it raises is logged and the other closes still run).

        Parameters
        ----------
        close : callable
            What closes the part.
        *args, **kwds
            Passed to `close`.

        Returns
        -------
        callable
            The registered callback (`ExitStack.callback`'s return value).
        """
        return super().callback(_close_quietly, close, *args, **kwds)


def _close_quietly(close: Callable[..., Any], *args: Any, **kwds: Any) -> None:
    try:
        close(*args, **kwds)
    except Exception as exc:  # noqa: BLE001 - closing is best effort, keep closing the rest
        log.warning("while closing after a failed start: %s", exc)


class Daemon:
    """The twin daemon of one cell: built whole or not at all, then `run`, `stop`, `close`.

    Parameters
    ----------
    cfg : RuntimeConfig
        The validated runtime config.
    base : Path
        The directory relative paths of the config are resolved against (the YAML's).
    world : SimWorld, optional
        A simulated world to run on (left open); None builds one from `sim` when a driver needs it.
    source : str
        Names the runtime YAML in errors.
    status_every_s : float, optional
        Period of the operator's status line on stderr (s); None: no status line.

    Raises
    ------
    TwinError
        Any failure of the start (ConfigError for a bad config, twin or program, StoreError for a
        store in use, DriverError, BusError): everything opened so far is closed first.

    Threads: `run` runs the loop on the caller's thread; the store's writer, the housekeeping
    thread, the bus worker and zenoh's callbacks run beside it. `stop` may be called from a signal
    handler.
    """

    def __init__(self, cfg: RuntimeConfig, base: Path, world=None, source: str = "<runtime config>",
                 status_every_s: float | None = None):
        self.cfg, self.base, self.source = cfg, base, source  # source: names the runtime YAML in errors
        self.status_every_s = status_every_s  # the operator's status line on stderr (`status_line`), or None
        self._parts = Parts()  # what is open, closed in reverse by `close()` or a failed start
        try:
            self._start(world)
        except BaseException:
            self._parts.close()
            raise

    def _start(self, world) -> None:
        """Every part built here, in order; each one that opens something is registered on
        `self._parts` as soon as it is open."""
        cfg, parts = self.cfg, self._parts
        cfg.drivers.check(self.source)  # an unknown driver or a bad option: nothing is opened yet
        twin_dir = self._p(cfg.twin)
        self.twin = Twin.load(twin_dir)
        check_camera(self.twin, twin_dir, cfg.drivers.camera.kind)
        # Read before anything is opened: a bad program stops the start with nothing to close.
        file = self._p(cfg.path.program) if cfg.path.program is not None else None
        self._program = read_program(file) if file is not None and cfg.path.kind == "program" else None
        self._plan: PathPlan | None = None
        if file is not None and cfg.path.kind == "path":
            check_streaming_robot(cfg.drivers.robot.kind, self.source)
            self._plan = plan_path(self.twin, file, cfg.rate_hz, cfg.limits, self.source)
        check_condition_sources(self.twin, twin_dir, cfg.drivers, self._program)
        check_model(self.twin, twin_dir, self._plan.sp.p[0] if self._plan is not None
                    else probe_point(cfg.path, self._program), 0.5 * cfg.limits.max_speed_m_s)
        self.corrector = Guard(self.twin, cfg.limits)
        self.monitor = Monitor(self.twin, cfg.alpha)
        self.counters = Counters()
        self.events = Events()
        self._stop = threading.Event()
        # High-rate rows leave the loop through the Store's lock-free queue; its writer thread
        # commits them every 50 ms, so the loop never waits on a lock or an fsync.
        self.store = Store(self._p(cfg.store), batch_ms=50.0, background=True, exclusive=True)
        parts.callback(self.store.close)
        stream = StreamState(self._plan.n, str(self._plan.file)) if self._plan is not None else None
        # A rigid shift of the camera set-up is offered for re-referencing; applied, it moves T_mvs.
        self.mvs_frame = MvsFrame(self.twin)
        # The U the twin states follows the monitored readings (adaptive conformal, twin/adaptive.py);
        # Eq. 17 keeps the calibrated U, so the scale never hides a fault from the escalation.
        self.coverage = AdaptiveCoverage()
        self.paging = Paging(cfg.escalation, cfg.bus, self.store, self.events,
                             resume_extra=lambda: ({"path": stream.to_dict()} if stream is not None else {})
                             | self.mvs_frame.to_dict() | {"stated_u": self.coverage.to_dict()},
                             on_rereference=self.mvs_frame.apply, jacobian=self.mvs_frame.jacobian())
        self.mvs_frame.restore(self.paging.saved_extra.get("mvs_rereferenced"))
        if "stated_u" in self.paging.saved_extra:  # the scale resumes where it was: a restart does not shrink U
            self.coverage = AdaptiveCoverage.from_dict(self.paging.saved_extra["stated_u"])
        self.escalator = self.paging.escalator
        self.bus = self._open_bus()
        # The cell's program may ask for corrections on `.../correct` (its own Guard and corrector:
        # the step bound follows the program's requests, and zenoh's thread shares no state with the tick).
        self._cond: Conditions | None = None  # the cell's latest conditions (the correct service reads them)
        # Served on the bus's session now, or once a client's router comes (closed with the bus).
        if self.bus:
            served = Guard(self.twin, cfg.limits, Corrector(self.twin))
            self.bus.serve(lambda s: CorrectionServer(served, cfg.bus, s, conditions=lambda: self._cond))
        self.cell: Cell = open_cell(cfg, self.base, self.source, world, self.twin, parts)
        self.world, self.inst = self.cell.world, self.cell.inst
        self.supervisor = Supervisor(cfg.halt, cfg.max_measurement_age_s, self.escalator, self.counters, self._now,
                                     self._stop, streaming=stream is not None,
                                     store_failing=lambda: bool(self.store.write_errors_in_row))
        self.targets = None if self._plan else targets_for(cfg.path, self._program, self.inst.max_speed, cfg.rate_hz)
        self.path = self._streamer(self._plan, stream) if self._plan is not None and stream is not None else None
        self.reporter = HealthReporter(self.supervisor.status, self.escalator, self.counters, self.store, self._now,
                                       self.inst, self.bus, self.events,
                                       stream=stream.to_dict if stream is not None else lambda: None,
                                       stated_u=self.coverage.health)
        self.status_line = StatusLine(self.supervisor.status, self.counters, self.escalator, self.path, self.bus)
        self.housekeeper = Housekeeper(
            self._stop, self.events, take_actions=self.paging.take_actions, send_health=self.reporter.send,
            prune=self.prune, status_line=self.status_line, last_tick_mono=lambda: self.counters.last_tick_mono,
            health_period_s=cfg.bus.health_period_s, prune_every_s=cfg.retention.every_s,
            status_every_s=self.status_every_s)
        self.tick_times: list[float] | None = None  # set to [] to record tick start times
        self.latencies: list[float] | None = None  # set to [] to record reading receipt -> t-test done (s)
        self.exposure_latencies: list[float] | None = None  # set to []: mid-exposure (host clock) -> t-test done
        self.realtime_thread = False  # the paced loop's thread got SCHED_FIFO (`rt_priority`)
        # The plant asks every cell on `dt/<cell>/<robot>/<kind>` (docs/plant.md): served once the daemon is whole.
        if self.bus:
            bus, view = self.bus, CellStatus(self.reporter, self.store, self.counters, self.escalator)
            twin = twin_identity(self.twin, self._p(cfg.twin))
            bus.serve(lambda s: QueryServer(cfg.bus, s, answers(view, twin), sign=bus.signer.sign))
            bus.serve(lambda _s: self.events.emit(HealthDue()))  # connected: say so at once (returns None)
        self.paging.reconcile(self._now())
        self.housekeeper.start()
        parts.callback(self.housekeeper.stop)
        self.reporter.changed(force=True)

    def _open_bus(self) -> Bus | None:
        """The bus (None unless `publish`): it publishes every recorded transition and delivers
        the requests; an operator's 'done' wakes the housekeeping thread."""
        if not self.cfg.publish:
            return None
        bus = Bus(self.cfg.bus, self.store, on_ack=self.paging.on_ack,
                  on_done=lambda aid: self.events.emit(ActionQueued(aid)))
        self._parts.callback(bus.close)
        self.events.subscribe(Transition, bus.on_transition)
        self.events.subscribe(RequestsQueued, bus.on_requests)
        return bus

    def _streamer(self, plan: PathPlan, stream: StreamState) -> PathStreamer:
        """The path program's streamer, resumed where the store says the last run stopped."""
        cfg = self.cfg
        cell = StreamCell(self.twin, self._p(cfg.twin), self.inst, self.world,
                          (cfg.drivers.robot.kind, dict(cfg.drivers.robot.options)), self.source)
        hooks = PassHooks(test=self._test_moving, refused=self._camera_refused, stop=self.supervisor.pass_stop,
                          beat=self._beat, u_reading=self.monitor.u)
        ps = PathStreamer(plan, stream, cfg.stream, cfg.rate_hz, cell, hooks)
        ps.restore(self.paging.saved_extra.get("path"))
        return ps

    def _conditions(self, step: int | None) -> Conditions | None:
        """The conditions of the next command, when the twin's maps read any (else None: the
        paper's map needs none and the loop reads nothing more)."""
        if not self.twin.needs:
            return None
        base = self.cell.conditions()
        return self._program.conditions(step, base) if (self._program is not None and step is not None) else base

    def _p(self, rel: str) -> Path:
        return beside(self.base, rel)

    def acknowledge_maintenance(self, note: str = "maintenance done", by: str = "operator") -> int:
        """Operator confirmation, as `dt ack` does it: stored as an action (who, why), applied by
        the loop at its next tick.

        Parameters
        ----------
        note : str
            Why (what was done).
        by : str
            Who.

        Returns
        -------
        int
            The action's id.

        Raises
        ------
        StoreError
            The action could not be stored.
        """
        return self.paging.acknowledge(note, by)

    def rereference(self, note: str = "camera re-referenced", by: str = "operator") -> int:
        """Operator: apply the offered re-referencing of the camera frame, as `dt ack --rereference`
        does it: stored as an action (who, why), applied by the loop at its next tick (ignored
        unless the escalation is in `rereference_offered`).

        Parameters
        ----------
        note : str
            Why.
        by : str
            Who.

        Returns
        -------
        int
            The action's id.

        Raises
        ------
        StoreError
            The action could not be stored.
        """
        return self.paging.rereference(note, by)

    # --- what it reports ------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        """What `.../health` carries (`service.health.HealthReporter`)."""
        return self.reporter.health()

    def prune(self) -> int:
        """Apply the retention policy to the store's high-rate rows; returns rows deleted."""
        r = self.cfg.retention
        before = None if r.max_age_s is None else self._now() - r.max_age_s
        return self.store.prune(before_t=before, keep_rows=r.max_rows)

    def summary(self) -> dict:
        """What `dt run` prints at the end (`--json`): the counters, the escalation state and halt
        reason, the maintenance requests opened and delivered, the store's path, the simulated
        cell's truth figures and a path program's state."""
        esc = self.escalator
        return {**self.counters.summary(), "state": esc.state, "halt_reason": esc.halt_reason,
                "maintenance_requests": len(self.paging.requests), "requests_delivered": len(self.paging.delivered),
                "store": str(self.store.path), **self.cell.truth(),
                **({"path": self.path.state.to_dict()} if self.path is not None else {})}

    # --- the point loop: target -> correct -> move -> read -> test -> record ------------------------
    def _now(self) -> float:
        return self.cell.now()

    def _idle(self) -> None:
        """A tick that moved nothing: on the simulated clock, let a period pass (or a run of
        refused commands would never end in simulated time)."""
        self.cell.idle(1.0 / self.cfg.rate_hz)

    def tick(self) -> None:
        """One command of a point program, as the supervisor allows; `.../health` marked due on
        a change, whatever the tick did."""
        try:
            self._tick()
        finally:
            self.reporter.changed()

    def _tick(self) -> None:
        t_now = self._now()
        self.paging.apply_actions(t_now)
        target, v, step = self._target()
        todo = self.supervisor.next_step(t_now)
        if todo is Step.WAIT:  # a sticky halt: waits for the operator's 'done'
            self._idle()
            return
        if todo is Step.PROBE:
            self._probe_camera(t_now)
            return
        cond = self._cond = self._conditions(step)
        corr = self._command(target, v, cond, t_now)
        if corr is None:  # refused: the robot is not moved
            self._idle()
            return
        arrived, t = self._move(corr, v, t_now)
        reading = self._read(arrived)
        if reading is None or reading.point is None:  # refused or stale: the arm is not moved again
            return
        chk = self._test(corr.command, v, reading.point, cond, None)
        if chk is None:
            return
        # the joint angles also serve the escalation's shift check (a changed arm is ruled out with them)
        wanted = self.bus is not None or self.escalator.jacobian is not None
        self._record(t, reading.point, chk, True, self._telemetry(corr) if wanted else {})
        self._latency(reading)

    def _target(self) -> tuple[np.ndarray, float, int | None]:
        """The next target, its speed and program row; the simulated cell's faults when due."""
        assert self.targets is not None  # a path program runs passes (`_run_path`), not ticks
        target, v, step = self.targets.next()
        self.cell.inject_due_faults()
        return target, v, step

    def _command(self, target: np.ndarray, v: float, cond: Conditions | None, t: float) -> Corrected | None:
        """The command for `target`: corrected while the supervisor trusts the correction, else
        the target as it is (counted); None if the correction refused it (counted, may halt)."""
        try:
            if self.supervisor.corrects():
                return self._correct(target, v, cond)
            corr = self.corrector.uncorrected(target, v)
            self.counters.uncorrected += 1
            return corr
        except CorrectionFault as exc:
            self.supervisor.refused(exc, t)
            return None

    def _correct(self, target: np.ndarray, speed: float, cond: Conditions | None) -> Corrected:
        """The bounded correction of one target."""
        return self.corrector(target, speed, cond)

    def _move(self, corr: Corrected, v: float, t_now: float) -> tuple[float, float]:
        """Send the command; once it arrived the arm stands where it was sent. The command and its
        correction are stored at once (a camera that fails next leaves them on record). Returns
        (arrival on the host's monotonic clock, daemon time after the move)."""
        self.inst.robot.move_linear(corr.command, v)
        arrived = time.monotonic()  # the command has arrived: the arm stands where it was sent
        self.supervisor.moved(t_now)
        self.cell.score(corr.target)  # simulation: the true error in GL, as `dt demo` scores it
        t = self._now()
        x, y, z = corr.target
        self.store.put(CommandRow(t, x, y, z, speed=v))
        self.store.put(CorrectionRow(t, *corr.correction, *corr.u_tcp))
        self.status_line.last = (t, corr)
        return arrived, t

    def _read(self, arrived: float) -> RigReading | None:
        """The MVS reading of the arm after the move; None if the camera refused it or it is
        older than `max_measurement_age_s` (counted by the supervisor)."""
        camera = self.inst.camera
        assert camera is not None  # open_cell always builds one (drivers.camera names a driver)
        reading = read_exposed_after(camera, arrived)  # a streamed frame exposed mid-move saw the arm elsewhere
        self.counters.ticked()
        return reading if self.supervisor.usable(reading, arrived) else None

    def _test(self, command: np.ndarray, v: float, point: np.ndarray, cond: Conditions | None,
              u_extra: np.ndarray | None) -> Check | None:
        """Eq. 17 of one MVS reading of the arm at `command`: the Check, or None if the monitor
        rejected the value (not tested: counted by the supervisor)."""
        try:
            chk = self.monitor(command, v, point, cond, u_extra)
        except CorrectionFault as exc:
            self.supervisor.rejected(exc)
            return None
        self.supervisor.tested()
        return chk

    def _record(self, t: float, point: np.ndarray, chk: Check, observe: bool, telemetry: dict[str, Any]) -> None:
        """A tested reading stored; when `observe`d also its t-test, counted, fed to the
        escalation, staged with the rows and published."""
        self.store.put(MeasurementRow(t, *point, *chk.diff))
        if not observe:
            return
        worst = int(np.argmax(np.abs(chk.t)))
        self.store.put(TTestRow(t, float(chk.t[worst]), None, float(np.min(chk.p_value)), chk.passed,
                                data={"t": chk.t.tolist()}))
        self.counters.failures += int(not chk.passed)
        # Did the U stated with the current scale cover this reading's difference? |t| <= scale t_crit.
        self.coverage.update(np.abs(chk.t) <= self.coverage.scale * self.monitor.t_crit)
        esc = self.escalator
        # the reading where the camera saw it (GL) with its difference from the prediction: a rigid
        # shift of these is offered for re-referencing (Escalator.shift)
        q = telemetry.get("q")
        reading = (self.twin.T_mvs.apply(point), chk.diff - chk.predicted, self.monitor.u,
                   None if q is None else np.asarray(q, dtype=float))
        esc.observe(chk.passed, float(chk.t[worst]), t, reading)
        # The statistics travel with the next batch of rows: a restart resumes them.
        self.store.stage_state(*self.paging.resume_row())
        if self.bus:
            # `measured` (the MVS's TCP in the robot frame) for the dashboard's view (docs/bus.md)
            measured = self.twin.T_rdk.inverse().apply(self.twin.T_mvs.apply(point)).tolist()
            self.bus.publish_telemetry({"t": t, **telemetry, "t_stat": chk.t.tolist(), "passed": chk.passed,
                                        "state": esc.state, "measured": measured})

    def _telemetry(self, corr: Corrected) -> dict[str, Any]:
        """A command's telemetry beside its Eq. 17 (docs/bus.md): for the dashboard's view also the
        controller's joint angles after the move (the conditions' are from before it), the stated U
        (95 %) of the position reached (the calibrated U times the adaptive scale, `U_scale`) and
        the calibrated-volume flag."""
        q = self.inst.robot.read_joint_state().q
        return {"target": corr.target.tolist(), "command": corr.command.tolist(), "q": np.asarray(q).tolist(),
                "U": self.coverage.stated(corr.U_tcp).tolist(), "U_scale": self.coverage.scale.tolist(),
                "inside": corr.inside}

    def _latency(self, reading: RigReading) -> None:
        """Reading receipt (and mid-exposure) -> t-test done, when recorded (benchmarks)."""
        done = time.monotonic()
        if self.latencies is not None:
            self.latencies.append(done - reading.host_time)
        mid = reading.quality.get("mid_exposure_host_s")
        if self.exposure_latencies is not None and mid is not None:
            self.exposure_latencies.append(done - mid)

    def _camera_refused(self, reading: RigReading) -> None:
        """A reading the camera driver refused (counted by the supervisor; health on a change)."""
        self.supervisor.camera_refused(reading)
        self.reporter.changed()

    def _probe_camera(self, t_now: float) -> None:
        """Halted for the camera: the arm stands; one reading a step, the first accepted resumes."""
        camera = self.inst.camera
        assert camera is not None
        if not self.supervisor.probed(camera.read(), t_now):
            self._idle()
        self.reporter.changed()

    def _driver_fault(self, exc: DriverError) -> None:
        self.supervisor.driver_fault(exc)
        self.reporter.changed()

    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> dict:
        """Run the loop on this thread until `duration_s`, `max_ticks` or `stop()`; a path
        program runs its passes instead (`max_ticks` is then ignored). Paced (`realtime: true`),
        the GIL's switch interval is lowered to `PACED_SWITCH_INTERVAL_S` meanwhile.

        Parameters
        ----------
        duration_s : float, optional
            How long to run, s of the daemon's clock (simulated or wall); None: until stopped.
        max_ticks : int, optional
            Loop iterations of a point program, moved or not; None: no limit.

        Returns
        -------
        dict
            The `summary()`.

        Raises
        ------
        TwinError
            A failure the loop does not absorb (store and driver failures are counted and the
            loop goes on; a StoreError out of a path pass is raised).
        """
        if self.path is not None:  # passes of a path: the streaming loop keeps the controller's rate
            return self._run_path(duration_s)
        if not self.cfg.realtime:
            return self._run(duration_s, max_ticks)
        # A thread that wakes for its tick waits for the GIL until its holder (the store's writer,
        # housekeeping, a bus callback) is made to drop it: up to the switch interval, 5 ms by
        # default, more than a period at 500 Hz. Paced, the loop bounds that wait.
        before = sys.getswitchinterval()
        sys.setswitchinterval(min(before, PACED_SWITCH_INTERVAL_S))
        policy = _fifo_thread(self.cfg.rt_priority)
        self.realtime_thread = policy is not None
        try:
            return self._run(duration_s, max_ticks)
        finally:
            sys.setswitchinterval(before)
            if policy is not None:
                os.sched_setscheduler(0, *policy)

    def _run(self, duration_s: float | None, max_ticks: int | None) -> dict:
        period = 1.0 / self.cfg.rate_hz
        t0 = self._now()
        next_t = time.monotonic()
        sdnotify.notify("READY=1")
        self.counters.last_tick_mono = time.monotonic()
        iterations = 0
        while not self._stop.is_set():
            # max_ticks counts loop iterations, moved or not: a run of refused commands ends too
            if max_ticks is not None and iterations >= max_ticks:
                break
            iterations += 1
            if duration_s is not None and self._now() - t0 >= duration_s:
                break
            if self.tick_times is not None:
                self.tick_times.append(time.perf_counter())
            try:
                self.tick()
            except StoreError as exc:  # disk full: keep controlling, rows are retried
                log.error("store write failed, continuing: %s", exc)
                self.reporter.changed()
            except DriverError as exc:
                self._driver_fault(exc)
                self._stop.wait(min(period, 0.1))
                self._idle()
            if self.cfg.realtime:
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    # Sleep to just before the tick, then spin: OS wake-up latency is ~0.1-1 ms.
                    if delay > 1e-3:
                        self._stop.wait(delay - 1e-3)
                    while time.monotonic() < next_t and not self._stop.is_set():
                        pass
                elif delay < -period:
                    # More than a period late (a stalled device, the host): start a new schedule
                    # rather than fire the missed ticks in a burst. Less late, the next tick
                    # starts at once and the schedule keeps its rate.
                    next_t = time.monotonic()
        return self.summary()

    # --- the path loop (service.path_run) -------------------------------------------------------
    def _test_moving(self, command: np.ndarray, v: float, point: np.ndarray, cond: Conditions | None, s: float,
                     u_extra: np.ndarray, observe: bool) -> Check | None:
        """A reading of the moving arm at path time `s`, against where the path has the arm then."""
        self.supervisor.accepted()
        t = self._now()
        chk = self._test(command, v, point, cond, u_extra)
        if chk is not None:
            q = {"q": np.asarray(cond.joints).tolist()} if cond is not None and cond.joints is not None else {}
            self._record(t, point, chk, observe, {"target": command.tolist(), "command": command.tolist(),
                                                  "path_t": s, **q})
        return chk

    def _beat(self) -> None:
        """A step of a pass: the watchdog's tick, the simulated cell's faults when due, health on
        a change (no I/O here)."""
        self.counters.last_tick_mono = time.monotonic()
        self.cell.inject_due_faults()
        self.reporter.changed()

    def _run_path(self, duration_s: float | None) -> dict:
        """Passes of the path until the duration, `stream.passes` or a stop; a pass that stopped
        early halts (sticky) until the operator's 'done' resumes it where the arm stands."""
        ps = self.path
        assert ps is not None
        st, n = ps.state, self.counters
        t0 = self._now()
        sdnotify.notify("READY=1")
        n.last_tick_mono = time.monotonic()
        k0 = st.next  # 0, or where the last run of this path stopped (restored at the start)
        stalls = 0  # passes stopped by a host stall in a row
        while not self._stop.is_set():
            if duration_s is not None and self._now() - t0 >= duration_s:
                break
            if self.cfg.stream.passes is not None and st.passes >= self.cfg.stream.passes:
                break
            t_now = self._now()
            self.paging.apply_actions(t_now)
            todo = self.supervisor.next_step(t_now)
            if todo is not Step.MOVE:  # halted: probe the camera, or wait for the operator's 'done'
                if todo is Step.PROBE:
                    self._probe_camera(t_now)
                else:
                    self._idle()
                    self._beat()
                self._stop.wait(0.0 if self.world is not None and not self.cfg.realtime else 0.05)
                continue
            if st.rerun_from is not None:
                log.warning("resuming the path at %s", ps.plan.where(k0) + st.rerun_from)
                st.rerun_from = None
            corrected = self.supervisor.corrects()
            try:
                rep = ps.run_pass(k0, corrected)
            except (DriverError, TwinError) as exc:  # the child could not start (a driver, the twin)
                if isinstance(exc, StoreError):
                    raise
                self._driver_fault(DriverError(f"path pass from {ps.plan.where(k0)}: {exc}"))
                self._stop.wait(0.5)
                continue
            self.supervisor.pass_done(rep.n_sent, corrected)
            self._stage_path()
            if not rep.stopped:
                k0, stalls = 0, 0
                log.info("pass %d of the path done: %d set-points at %.1f Hz%s", st.passes, rep.n_sent, rep.rate_hz,
                         f", p99 jitter {rep.jitter_p99_ms:.3f} ms" if np.isfinite(rep.jitter_p99_ms)
                         else " (the simulated clock: not paced)")
                continue
            k_stop = st.next  # the first set-point not sent
            k0 = ps.resume_point(self._arm_position(), k0, k_stop)
            st.next = k0
            if k0 < k_stop:
                st.rerun += k_stop - k0
                st.rerun_from = (f" (set-points {k0 + 1}..{k_stop} were sent before the stop but the arm had not "
                                 f"reached them: they are streamed again)")
            else:
                st.rerun_from = ""
            self._stage_path()
            if self._stop.is_set() or self.escalator.state == "halted":
                continue  # stopping, or already halted (the camera's halt resumes by itself)
            stalls = stalls + 1 if rep.host_stalled else 0
            if 0 < stalls <= MAX_HOST_STALLS:  # the host, not the cell: the arm stands, the path goes on from there
                st.host_pauses += 1
                log.warning("path paused at %s: %s; resuming at %s (host stall %d of %d in a row before a halt)",
                            ps.plan.where(k_stop), rep.stopped, ps.plan.where(k0), stalls, MAX_HOST_STALLS)
                self._stop.wait(HOST_STALL_WAIT_S)
                continue
            hint = (f" (the host stalled {stalls} passes in a row: give the streaming process real-time priority, "
                    "docs/streaming.md, or lower the load)") if stalls else ""
            self.supervisor.pass_stopped(f"path stopped at {ps.plan.where(k_stop)}: {rep.stopped}{hint}; clear the "
                                         f"cause, then confirm (dt ack): the path resumes at {ps.plan.where(k0)}")
        return self.summary()

    def _arm_position(self) -> np.ndarray | None:
        """Where the arm stands (the controller's TCP), None if the controller cannot tell now."""
        try:
            return np.asarray(self.inst.robot.read_commanded_tcp(), dtype=float)
        except (DriverError, TwinError) as exc:
            log.warning("the arm's position is unknown after the stop (%s): the path resumes at the first "
                        "set-point not sent", exc)
            return None

    def _stage_path(self) -> None:
        """The path's state (its resume point) travels with the next batch of rows."""
        self.store.stage_state(*self.paging.resume_row())

    # --- stop and close ---------------------------------------------------------------------------
    def stop(self, *_: Any) -> None:
        """Stop the loop: safe in a signal handler (it sets flags, aborts the move in flight and
        cancels a streamed pass; nothing waits).

        Parameters
        ----------
        *_ : Any
            Ignored: a signal handler's (signum, frame).
        """
        self._stop.set()
        housekeeper = getattr(self, "housekeeper", None)
        if housekeeper is not None:
            housekeeper.poll_now.set()
        robot = getattr(getattr(self, "inst", None), "robot", None)
        abort = getattr(robot, "abort", None)
        if abort is not None:
            abort("the daemon is stopping")
        path = getattr(self, "path", None)
        if path is not None:
            path.cancel()

    def close(self) -> None:
        """Save the resume row, stop housekeeping, send the last health, close every part
        (newest first)."""
        self.housekeeper.stopping()
        try:
            self.store.save_state(*self.paging.resume_row())
        except TwinError as exc:
            log.error("could not save state on close: %s", exc)
        self.housekeeper.stop()
        try:
            if self.bus:
                self.bus.publish_health(self.health() | {"status": "stopped", "reason": "the daemon stopped"})
        except TwinError as exc:
            log.warning("last health not sent: %s", exc)
        self._parts.close()


def run_daemon(config: str | Path, duration_s: float | None = None, status_every_s: float | None = None) -> dict:
    """`dt run`: start, run until the duration ends or SIGTERM/SIGINT, close.

    The signal handlers are this daemon's while it runs and the caller's again after; once a
    signal came, the process exits with status 75 if it is not stopped within `stop_timeout_s`
    whatever a device does.

    Parameters
    ----------
    config : str or Path
        The runtime YAML.
    duration_s : float, optional
        How long to run, s of the daemon's clock; None: until a signal.
    status_every_s : float, optional
        Period of the operator's status line (s); None: never.

    Returns
    -------
    dict
        The daemon's `summary()`.

    Raises
    ------
    TwinError
        The start failed (ConfigError for the config, twin or program; everything opened is
        closed first), or the loop failed.
    """
    config = Path(config)
    cfg = load_runtime_config(config)
    d = Daemon(cfg, config.parent, source=str(config), status_every_s=status_every_s)
    deadline: list[threading.Timer] = []

    def on_signal(signum: int, _frame: Any) -> None:
        d.stop()
        if not deadline:  # the last resort: committed rows are safe (synchronous=FULL)
            timer = threading.Timer(cfg.stop_timeout_s, _exit_hard, args=(cfg.stop_timeout_s,))
            timer.daemon = True
            timer.start()
            deadline.append(timer)

    # The handlers hold this daemon: put the caller's back when it is closed (a later signal to a
    # process that ran `dt run` in-process, a test, must not stop a daemon that is gone).
    before = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return d.run(duration_s)
    finally:
        d.close()
        for timer in deadline:
            timer.cancel()
        for s, handler in before.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


def _fifo_thread(priority: int) -> tuple[int, Any] | None:
    """SCHED_FIFO at `priority` for the calling thread (Linux applies the policy per thread: the
    store's writer, housekeeping and the bus's threads, started before, keep theirs), when the
    user may have it; returns the policy to restore, or None (not allowed, or priority 0)."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return None
    try:
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError):
        return None
    return old


def _exit_hard(after_s: float) -> None:
    log.error("not stopped within stop_timeout_s = %.1f s: exiting now", after_s)
    logging.shutdown()
    os._exit(75)  # EX_TEMPFAIL: the service manager may restart it
