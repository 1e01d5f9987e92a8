"""`dt run`: the long-running twin daemon.

Every tick: take the next target from the target source (`service.targets`: the program, or a
simulation stand-in), apply the bounded correction with the twin's maps (twin.bounds around twin.corrector)
under the cell's conditions when the maps read them (joint angles from the controller,
temperature and payload from the program's columns or the simulated cell's sensors, the clock:
`twin.conditions`), move the robot, read the MVS, test the measurement against the prediction
(Eq. 17), feed the escalation state machine, log everything to the durable store (typed rows,
`service.rows`, on the Store's one lock-free queue: the loop never waits on SQLite) and publish
over Zenoh. The cell (`service.cell`: the drivers and the clock; on the simulated cell, `SimCell`,
its truth and fault injection too) is built by `open_cell`, every driver by
`drivers.registry.create` from `drivers.<kind>` (`kind` and the driver's options, checked before
anything opens), the same way whatever their name.

Module layout: this module holds the loop (`Daemon.tick`, `Daemon.run`), start and stop, and
what it reports; `targets` the target sources; `cell` the cell; `paging` the escalation's
records, maintenance requests and operator actions; `counters` the one set of counters that
`.../health`, the summary and the status line read; `housekeeping` the thread that is never the
loop.

Measurements and clocks. Every reading carries the device's time stamp (`t`) and the host's
monotonic receive time (`host_time`, drivers.base). The MVS reading tested against a command is
one received after the command arrived (the move returned) or at most `max_measurement_age_s`
before it; an older one saw the arm elsewhere and is refused, counted (`stale_measurements` in
the summary and on `.../health`), and not tested.

Escalation and paging (`service.paging`). Every transition of the machine is one store
transaction with its snapshot and, on entering `maintenance_requested` or `halted`, that
episode's maintenance requests; only then is it published and the bus woken to deliver the
requests. At start-up a paging state without requests gets them, and the escalation statistics
resume from the store (staged with every batch of rows).

Halts. Every command refused for `halt.after_refused` ticks, `halt.after_driver_faults` driver
faults in a row, no MVS reading tested for `halt.after_camera_refused_s` (refused by the camera
driver, too old, or rejected), or `out_of_control` under `halt.on_untrusted: halt`, put the
machine in `halted` with the reason: stored, paged and published on `.../health`; the first two
resume by themselves when a command goes through again; a camera halt stops the arm (it would
move unmonitored), reads the camera once a tick and resumes at the first accepted reading. In
`out_of_control` and `maintenance_requested` the correction is not trusted: by default the
daemon commands the targets uncorrected.

Operator. `dt ack` (or a signed `.../maintenance/done/<id>` on the bus) stores an operator
action; the housekeeping thread picks it up and the loop applies it (`service.paging`).

Housekeeping (`service.housekeeping`, one thread, never the loop): operator actions,
`.../health` every `bus.health_period_s` (and on every change, from the loop), store retention,
the status line, and the systemd watchdog (`service.sdnotify`: READY on start, WATCHDOG while
the loop ticks, STOPPING).

Start and stop. Any start-up failure closes what was opened (bus, store, drivers) and raises, so
`dt run` exits non-zero within seconds; one daemon per store (a lock). `stop()` (SIGTERM, SIGINT)
aborts a move in flight; `run_daemon` exits within `stop_timeout_s` whatever a device does.

`realtime: true` paces ticks at `rate_hz` on the wall clock (a real cell): a late tick starts at
once and the schedule keeps its rate; more than a period late, a new schedule starts (no burst);
while paced, the GIL's switch interval is 0.2 ms, so a woken loop waits at most that long for
another thread to let go. `realtime: false` runs as fast as it can on the simulated clock (soaks
and tests).
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers import registry
from drivers.base import read_exposed_after
from dt_kernel.errors import ConfigError, DriverError, TwinError
from dt_runtime.fabric.queries import QueryServer
from dt_runtime.programs.program import read_program
from dt_runtime.service import sdnotify
from dt_runtime.service.answers import answers
from dt_runtime.service.cell import Cell, open_cell
from dt_runtime.service.correction_server import CorrectionServer
from dt_runtime.service.counters import Counters
from dt_runtime.service.housekeeping import Housekeeper
from dt_runtime.service.paging import Paging
from dt_runtime.service.path_run import PathStreamer, check_streaming_robot, plan_path
from dt_runtime.service.publisher import Bus
from dt_runtime.service.rows import CommandRow, CorrectionRow, MeasurementRow, TTestRow, shown_time
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
from dt_runtime.service.targets import probe_point, targets_for
from dt_runtime.twin.bounds import Corrected, CorrectionFault, Guard
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.monitor import Monitor
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")
PACED_SWITCH_INTERVAL_S = 2e-4  # the GIL's switch interval while the loop is paced (`run`)


class Daemon:
    def __init__(self, cfg: RuntimeConfig, base: Path, world=None, source: str = "<runtime config>",
                 status_every_s: float | None = None):
        self.cfg, self.base, self.source = cfg, base, source  # source: names the runtime YAML in errors
        self.status_every_s = status_every_s  # the operator's status line on stderr (`status_line`), or None
        self._closers: list[Callable[[], Any]] = []  # what is open, closed in reverse on failure
        try:
            self._start(world)
        except BaseException:
            self._close_opened()
            raise

    def _start(self, world) -> None:
        cfg = self.cfg
        cfg.drivers.check(self.source)  # an unknown driver or a bad option: nothing is opened yet
        self.twin = Twin.load(self._p(cfg.twin))
        trained = self.twin.instruments.get("camera")
        if trained and trained != cfg.drivers.camera.kind:
            raise ConfigError(str(self._p(cfg.twin) / "twin.json"), "instruments.camera", trained,
                              f"the daemon's camera driver '{cfg.drivers.camera.kind}': a twin is valid only "
                              "with the instruments (and frames) it was calibrated with")
        # Read before anything is opened: a bad program stops the start with nothing to close.
        file = self._p(cfg.path.program) if cfg.path.program is not None else None
        self._program = read_program(file) if file is not None and cfg.path.kind == "program" else None
        self._plan = None
        if file is not None and cfg.path.kind == "path":
            check_streaming_robot(cfg.drivers.robot.kind, self.source)
            self._plan = plan_path(self.twin, file, cfg.rate_hz, cfg.limits, self.source)
        self._check_condition_sources()
        self._check_model()
        self.corrector = Guard(self.twin, cfg.limits)
        self.monitor = Monitor(self.twin, cfg.alpha)
        self.counters = Counters()
        self._stop = threading.Event()
        # High-rate rows leave the loop through the Store's lock-free queue; its writer thread
        # commits them every 50 ms, so the loop never waits on a lock or an fsync.
        self.store = Store(self._p(cfg.store), batch_ms=50.0, background=True, exclusive=True)
        self._closers.append(self.store.close)
        self.paging = Paging(cfg.escalation, cfg.bus, self.store, on_change=lambda: self._publish_health(force=True))
        self.escalator = self.paging.escalator
        self.housekeeper = Housekeeper(
            self._stop, take_actions=self.paging.take_actions, send_health=self._send_health, prune=self.prune,
            status_line=self.status_line, last_tick_mono=lambda: self.counters.last_tick_mono,
            health_period_s=cfg.bus.health_period_s, prune_every_s=cfg.retention.every_s,
            status_every_s=self.status_every_s)
        self.bus = (Bus(cfg.bus, self.store, on_ack=self.paging.on_ack,
                        on_done=lambda _id: self.housekeeper.poll_now.set()) if cfg.publish else None)
        if self.bus:
            self._closers.append(self.bus.close)
        self.paging.bus = self.bus
        # The cell's program may ask for corrections on `.../correct` (its own Guard and corrector:
        # the step bound follows the program's requests, and zenoh's thread shares no state with the tick).
        self._cond: Conditions | None = None  # the cell's latest conditions (the correct service reads them)
        # Served on the bus's session now, or once a client's router comes (closed with the bus).
        if self.bus:
            served = Guard(self.twin, cfg.limits, Corrector(self.twin))
            self.bus.serve(lambda s: CorrectionServer(served, cfg.bus, s, conditions=lambda: self._cond))
        self.cell: Cell = open_cell(cfg, self.base, self.source, world, self.twin, self._closers)
        self.world, self.inst = self.cell.world, self.cell.inst
        self.targets = None if self._plan else targets_for(cfg.path, self._program, self.inst.max_speed, cfg.rate_hz)
        self.path: PathStreamer | None = None
        if self._plan is not None:
            self.path = PathStreamer(self._plan, cfg.stream, cfg.rate_hz, self.twin, self._p(cfg.twin), self.inst,
                                     (cfg.drivers.robot.kind, dict(cfg.drivers.robot.options)), self.source,
                                     self.world, self._test_moving, self._camera_refused, self.monitor.u,
                                     self._path_stop, self._beat)
            self.path.restore(self.paging.saved_extra.get("path"))
            self.paging.resume_extra = lambda: {"path": self.path.state.to_dict()} if self.path else {}
        self._camera_halt = False  # halted because the camera gave no usable reading (resumes on one)
        self.tick_times: list[float] | None = None  # set to [] to record tick start times
        self.latencies: list[float] | None = None  # set to [] to record reading receipt -> t-test done (s)
        self.exposure_latencies: list[float] | None = None  # set to []: mid-exposure (host clock) -> t-test done
        self._last_corrected: tuple[float, Corrected] | None = None  # (t, the last command sent), for status_line
        self._status_mark = (time.monotonic(), 0)  # (when, ticks) of the last status line: its rate
        self._health_key: tuple | None = None
        # The plant asks every cell on `dt/<cell>/<robot>/<kind>` (docs/plant.md): served once the daemon is whole.
        if self.bus:
            bus = self.bus
            bus.serve(lambda s: QueryServer(cfg.bus, s, answers(self, self._p(cfg.twin)), sign=bus.signer.sign))
            bus.serve(lambda _s: self.housekeeper.health_due())  # connected: say so at once (returns None)
        self.paging.reconcile(self._now())
        self.housekeeper.start()
        self._closers.append(self.housekeeper.stop)
        self._publish_health(force=True)

    def _close_opened(self) -> None:
        """Close what `_start` opened, newest first; each step bounded by its own time-out."""
        while self._closers:
            close = self._closers.pop()
            try:
                close()
            except Exception as exc:  # noqa: BLE001 - closing is best effort, keep closing the rest
                log.warning("while closing after a failed start: %s", exc)

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

    def _check_model(self) -> None:
        """The twin's maps must predict finite errors: a model file with NaN in it stops the
        start (exit non-zero, nothing opened) instead of refusing every command later. Probed at
        the path's first target (a map that also reads conditions is checked command by command:
        a NaN there is refused, counted and, repeated, halts)."""
        if self.twin.needs:
            return
        probe = self._plan.sp.p[0] if self._plan is not None else probe_point(self.cfg.path, self._program)
        v = 0.5 * self.cfg.limits.max_speed_m_s
        try:
            e = np.concatenate([np.ravel(self.twin.e_lt_hat(probe, v)[0]),
                                np.ravel(self.twin.e_mvs_lt_hat(probe, v)[0])])
        except (TwinError, ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise ConfigError(str(self._p(self.cfg.twin)), "e_lt", "unusable",
                              f"a model that predicts ({exc})") from exc
        if not np.all(np.isfinite(e)):
            raise ConfigError(str(self._p(self.cfg.twin)), "e_lt", f"prediction {e.tolist()} m",
                              "finite predictions: the model file holds NaN or inf (refit it)")

    def _conditions(self, step: int | None) -> Conditions | None:
        """The conditions of the next command, when the twin's maps read any (else None: the
        paper's map needs none and the loop reads nothing more)."""
        if not self.twin.needs:
            return None
        base = self.cell.conditions()
        return self._program.conditions(step, base) if (self._program is not None and step is not None) else base

    def _p(self, rel: str) -> Path:
        p = Path(rel)
        return p if p.is_absolute() else self.base / p

    # --- what the parts keep, under the names the daemon has always shown ----------------------
    @property
    def requests(self) -> list[dict]:
        return self.paging.requests

    @property
    def delivered(self) -> list[int]:
        return self.paging.delivered

    @property
    def _actions(self):
        return self.paging.actions

    @property
    def ticks(self) -> int:
        return self.counters.ticks

    @property
    def failures(self) -> int:
        return self.counters.failures

    @property
    def uncorrected(self) -> int:
        return self.counters.uncorrected

    @property
    def stale_measurements(self) -> int:
        return self.counters.stale_measurements

    @property
    def mvs_refused(self) -> int:
        return self.counters.mvs_refused

    @property
    def driver_faults(self) -> int:
        return self.counters.driver_faults

    @property
    def last_problem(self) -> str | None:
        return self.counters.last_problem

    def acknowledge_maintenance(self, note: str = "maintenance done", by: str = "operator") -> int:
        """Operator confirmation, as `dt ack` does it: stored as an action (who, why), applied by
        the loop at its next tick. Returns the action's id."""
        return self.paging.acknowledge(note, by)

    # --- health ------------------------------------------------------------------------------
    def _status(self) -> tuple[str, str | None]:
        """(running | degraded | halted, why): cheap, no I/O (the loop calls it every tick)."""
        esc = self.escalator
        if esc.state == "halted":
            return "halted", esc.halt_reason
        if self.store.write_errors_in_row:
            return "degraded", "store writes failing"
        if self.counters.in_trouble():
            return "degraded", self.counters.last_problem
        if not self._trusted() and self.cfg.halt.on_untrusted == "uncorrected":
            return "degraded", f"{esc.state}: commands sent uncorrected"
        return "running", None

    def health(self) -> dict[str, Any]:
        """What `.../health` carries: running / degraded / halted and why, the escalation state,
        the last tick, and the counters an operator looks at first."""
        status, reason = self._status()
        esc = self.escalator
        return {"status": status, "reason": reason, "escalation": esc.state, "episode": esc.episode,
                **self.counters.health(self._now()),
                "outbox_pending": self._pending_count(), "drivers": self._driver_counters(),
                # acks and 'done's on the bus without the service's signature: refused, not recorded
                "bus_refused": self.bus.refused if self.bus else 0,
                "bus_last_refused": self.bus.last_refused if self.bus else None,
                "bus": self.bus.state if self.bus else "off",  # connecting (no router yet), connected
                "pid": os.getpid(), "t": time.time(),
                **({"stream": self.path.state.to_dict()} if self.path is not None else {})}

    def status_line(self) -> tuple[str, dict[str, Any]]:
        """The operator's one line (`dt run` logs it every `status_every_s`): ticks and their rate
        since the last line, status and escalation state, the time of the last command and the
        expanded uncertainty (95 %) of the position it reached; and the same as fields."""
        now, ticks = time.monotonic(), self.counters.ticks
        then, before = self._status_mark
        self._status_mark = (now, ticks)
        rate = (ticks - before) / (now - then) if now > then else 0.0
        status, reason = self._status()
        failures = self.counters.failures
        bus = self.bus.state if self.bus else "off"
        f: dict[str, Any] = {"ticks": ticks, "rate_hz": round(rate, 2), "status": status, "reason": reason,
                             "escalation": self.escalator.state, "t_test_failures": failures, "bus": bus}
        text = f"{ticks} ticks ({rate:.1f}/s), {status}" + (f" ({reason})" if reason else "") + \
            f", escalation {self.escalator.state}, Eq. 17 failed {failures}" + \
            (f", bus {bus}" if bus == "connecting" else "")
        if self.path is not None:  # a path: where the stream is, not a last command
            st = self.path.state
            f |= {"stream": st.state, "pass": st.pass_started, "next": st.next, "n": st.n}
            return text + f", path {st.state}, pass {st.pass_started}, at {self.path.plan.where(st.next)}", f
        last = self._last_corrected
        if last is None:
            return text + ", no command yet", f
        t, corr = last
        U = [round(float(u) * 1e3, 4) for u in corr.U_tcp] if np.all(np.isfinite(corr.U_tcp)) else None
        f |= {"last_t": t, "U95_mm": U, "inside": corr.inside}
        return (text + f", last command {shown_time(t)}, U95 "
                + ("x/y/z " + "/".join(f"{u:.3f}" for u in U) + " mm" if U else "none (sent uncorrected)")
                + ("" if corr.inside else " (outside the calibrated volume)")), f

    def _driver_counters(self) -> dict[str, dict]:
        """Each driver's own counters, for those that keep them (`counters()`, no I/O: an RTDE
        link's drops and reconnections, NatNet frames lost and late): a fault the driver
        recovered from by itself still shows on `.../health`."""
        inst = getattr(self, "inst", None)
        out: dict[str, dict] = {}
        for kind in ("robot", "tracker", "camera"):
            counters = getattr(getattr(inst, kind, None), "counters", None)
            if callable(counters):
                try:
                    out[kind] = counters()
                except Exception as exc:  # noqa: BLE001 - a report must not fail on a driver's defect
                    out[kind] = {"error": str(exc)}
        return out

    def _pending_count(self) -> int | None:
        try:
            return len(self.store.outbox_pending())
        except StoreError:
            return None

    def _publish_health(self, force: bool = False) -> None:
        """`.../health` on a change of status, reason or state (checked without I/O: the loop
        calls this every tick; the housekeeping thread publishes it) or when `force`d."""
        key = (*self._status(), self.escalator.state)
        if not force and key == self._health_key:
            return
        self._health_key = key
        self.housekeeper.health_due()

    def _send_health(self) -> None:
        if self.bus:
            self.bus.publish_health(self.health())

    def prune(self) -> int:
        """Apply the retention policy to the store's high-rate rows; returns rows deleted."""
        r = self.cfg.retention
        before = None if r.max_age_s is None else self._now() - r.max_age_s
        return self.store.prune(before_t=before, keep_rows=r.max_rows)

    # --- the loop -----------------------------------------------------------------------------
    def _now(self) -> float:
        return self.cell.now()

    def _idle(self) -> None:
        """A tick that moved nothing: on the simulated clock, let a period pass (or a run of
        refused commands would never end in simulated time)."""
        self.cell.idle(1.0 / self.cfg.rate_hz)

    def _trusted(self) -> bool:
        return self.escalator.state not in ("out_of_control", "maintenance_requested")

    def tick(self) -> None:
        n = self.counters
        t_now = self._now()
        self.paging.apply_actions(t_now)
        assert self.targets is not None  # a path program runs passes (`_run_path`), not ticks
        target, v, step = self.targets.next()
        self.cell.inject_due_faults()
        esc = self.escalator
        policy = self.cfg.halt.on_untrusted
        if not self._trusted() and policy == "halt":
            esc.halt(f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)", t_now, sticky=True)
        if esc.state == "halted" and esc.halt_sticky:  # waits for the operator's 'done'
            self._idle()
            self._publish_health()
            return
        if self._camera_halt and esc.state != "halted":  # left by the operator's 'done': time afresh
            self._camera_halt, n.camera_refused_since = False, None
        if self._camera_halt:
            self._probe_camera(t_now)
            return
        cond = self._cond = self._conditions(step)
        try:
            if self._trusted() or policy == "correct":
                corr = self.corrector(target, v, cond)
            else:
                corr = self.corrector.uncorrected(target, v)
                n.uncorrected += 1
        except CorrectionFault as exc:
            n.refused += 1
            n.refused_in_row += 1
            n.last_problem = f"command refused: {exc}"
            log.error("command refused, robot not moved: %s", exc)
            if n.refused_in_row >= self.cfg.halt.after_refused:
                esc.halt(f"every command refused for {n.refused_in_row} ticks; last: {exc}", t_now)
            self._idle()
            self._publish_health()
            return
        self.inst.robot.move_linear(corr.command, v)
        arrived = time.monotonic()  # the command has arrived: the arm stands where it was sent
        n.refused_in_row = n.driver_faults_in_row = 0
        if esc.state == "halted":
            esc.resume(t_now)
        self.cell.score(corr.target)  # simulation: the true error in GL, as `dt demo` scores it
        t = self._now()
        x, y, z = corr.target
        self.store.put(CommandRow(t, x, y, z, speed=v))
        self.store.put(CorrectionRow(t, *corr.correction, *corr.u_tcp))
        self._last_corrected = (t, corr)
        camera = self.inst.camera
        assert camera is not None  # open_cell always builds one (drivers.camera names a driver)
        reading = read_exposed_after(camera, arrived)  # a streamed frame exposed mid-move saw the arm elsewhere
        n.ticked()
        if not reading.ok or reading.point is None:
            self._camera_refused(reading)  # the arm is not moved again
            return
        n.mvs_refused_in_row = 0
        age = arrived - reading.host_time
        if age > self.cfg.max_measurement_age_s:
            n.stale_measurements += 1
            n.last_problem = (f"stale measurement: received {age * 1e3:.0f} ms before the command arrived "
                              f"(max_measurement_age_s {self.cfg.max_measurement_age_s})")
            log.warning("MVS reading refused, not tested: %s", n.last_problem)
            self._camera_untested(n.last_problem)
            self._publish_health()
            return
        chk = self._test(corr.command, v, reading.point, cond, t, None, True,
                         self._telemetry(corr) if self.bus else {})
        if chk is None:
            return
        done = time.monotonic()
        if self.latencies is not None:
            self.latencies.append(done - reading.host_time)
        mid = reading.quality.get("mid_exposure_host_s")
        if self.exposure_latencies is not None and mid is not None:
            self.exposure_latencies.append(done - mid)
        self._publish_health()

    def _telemetry(self, corr: Corrected) -> dict[str, Any]:
        """A command's telemetry beside its Eq. 17 (docs/bus.md): for the dashboard's view also the
        controller's joint angles after the move (the conditions' are from before it), U (95 %) of
        the position reached and the calibrated-volume flag."""
        q = self.inst.robot.read_joint_state().q
        return {"target": corr.target.tolist(), "command": corr.command.tolist(), "q": np.asarray(q).tolist(),
                "U": corr.U_tcp.tolist(), "inside": corr.inside}

    def _test(self, command: np.ndarray, v: float, point: np.ndarray, cond: Conditions | None, t: float,
              u_extra: np.ndarray | None, observe: bool, telemetry: dict[str, Any]):
        """Eq. 17 of one MVS reading of the arm at `command`: stored, and when `observe`d counted,
        fed to the escalation and published; the Check, or None if the value was rejected."""
        n, esc = self.counters, self.escalator
        try:
            chk = self.monitor(command, v, point, cond, u_extra)
        except CorrectionFault as exc:
            log.error("MVS value rejected: %s", exc)
            self._camera_untested(f"MVS value rejected: {exc}")
            return None
        n.camera_refused_since = None
        self.store.put(MeasurementRow(t, *point, *chk.diff))
        if not observe:
            return chk
        worst = int(np.argmax(np.abs(chk.t)))
        self.store.put(TTestRow(t, float(chk.t[worst]), None, float(np.min(chk.p_value)), chk.passed,
                                data={"t": chk.t.tolist()}))
        n.failures += int(not chk.passed)
        esc.observe(chk.passed, float(chk.t[worst]), t)
        # The statistics travel with the next batch of rows: a restart resumes them.
        self.store.stage_state(*self.paging.resume_row())
        if self.bus:
            # `measured` (the MVS's TCP in the robot frame) for the dashboard's view (docs/bus.md)
            measured = self.twin.T_rdk.inverse().apply(self.twin.T_mvs.apply(point)).tolist()
            self.bus.publish_telemetry({"t": t, **telemetry, "t_stat": chk.t.tolist(), "passed": chk.passed,
                                        "state": esc.state, "measured": measured})
        return chk

    def _camera_refused(self, reading) -> None:
        """A reading the camera driver refused: nothing to test; counted and reported (degraded
        while it lasts, a halt after `halt.after_camera_refused_s`)."""
        n = self.counters
        n.mvs_refused += 1
        n.mvs_refused_in_row += 1
        n.last_problem = f"MVS refused: {reading.refused}"
        log.info("MVS refused: %s", reading.refused)
        self._camera_untested(n.last_problem)
        self._publish_health()

    def _camera_untested(self, why: str) -> None:
        """A reading that could not be tested: after `halt.after_camera_refused_s` of nothing
        but these, halt (paged; the loop then stops the arm and probes the camera)."""
        n = self.counters
        t = self._now()
        if n.camera_refused_since is None:
            n.camera_refused_since = t
        limit = self.cfg.halt.after_camera_refused_s
        blind = t - n.camera_refused_since
        if blind >= limit and self.escalator.state != "halted":
            self._camera_halt = self.escalator.halt(
                f"no MVS reading tested for {blind:.1f} s (halt.after_camera_refused_s {limit:g} s); last: {why}", t)

    def _probe_camera(self, t_now: float) -> None:
        """Halted for the camera: the arm stands; one reading a tick, the first accepted resumes."""
        camera = self.inst.camera
        assert camera is not None
        reading = camera.read()
        n = self.counters
        if reading.ok:
            self._camera_halt, n.camera_refused_since, n.mvs_refused_in_row = False, None, 0
            self.escalator.resume(t_now)
            log.warning("the camera gives readings again: resumed")
        else:
            n.last_problem = f"MVS refused: {reading.refused}"
            self._idle()
        self._publish_health()

    def _driver_fault(self, exc: DriverError) -> None:
        n = self.counters
        n.driver_faults += 1
        n.driver_faults_in_row += 1
        n.last_problem = f"driver fault: {exc}"
        log.error("driver fault: %s", exc)
        if n.driver_faults_in_row >= self.cfg.halt.after_driver_faults and not self._stop.is_set():
            try:
                self.escalator.halt(f"driver fault {n.driver_faults_in_row} times in a row: {exc}", self._now())
            except StoreError as store_exc:
                log.error("halt not recorded, retried on the next fault: %s", store_exc)
        self._publish_health()

    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> dict:
        if self.path is not None:  # passes of a path: the streaming loop keeps the controller's rate
            return self._run_path(duration_s)
        if not self.cfg.realtime:
            return self._run(duration_s, max_ticks)
        # A thread that wakes for its tick waits for the GIL until its holder (the store's writer,
        # housekeeping, a bus callback) is made to drop it: up to the switch interval, 5 ms by
        # default, more than a period at 500 Hz. Paced, the loop bounds that wait.
        before = sys.getswitchinterval()
        sys.setswitchinterval(min(before, PACED_SWITCH_INTERVAL_S))
        try:
            return self._run(duration_s, max_ticks)
        finally:
            sys.setswitchinterval(before)

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
                self._publish_health()
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

    # --- a path program (service.path_run) ---------------------------------------------------
    def _test_moving(self, command: np.ndarray, v: float, point: np.ndarray, cond: Conditions | None, s: float,
                     u_extra: np.ndarray, observe: bool):
        """A reading of the moving arm at path time `s`, against where the path has the arm then."""
        self.counters.mvs_refused_in_row = 0
        q = {"q": np.asarray(cond.joints).tolist()} if cond is not None and cond.joints is not None else {}
        return self._test(command, v, point, cond, self._now(), u_extra, observe,
                          {"target": command.tolist(), "command": command.tolist(), "path_t": s, **q})

    def _path_stop(self) -> str:
        """Why a pass must end now ('' to go on): the daemon stopping, or a halt (the camera's:
        the arm must not move unmonitored; a sticky one)."""
        if self._stop.is_set():
            return "the daemon is stopping"
        esc = self.escalator
        if esc.state == "halted":
            return f"halted: {esc.halt_reason}"
        if not self._trusted() and self.cfg.halt.on_untrusted == "halt":
            return f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)"
        return ""

    def _beat(self) -> None:
        """A step of a pass: the watchdog's tick, the simulated cell's faults when due, health on
        a change (no I/O here)."""
        self.counters.last_tick_mono = time.monotonic()
        self.cell.inject_due_faults()
        self._publish_health()

    def _run_path(self, duration_s: float | None) -> dict:
        """Passes of the path until the duration, `stream.passes` or a stop; a pass that stopped
        early halts (sticky) until the operator's 'done' resumes it where the arm stands."""
        ps = self.path
        assert ps is not None
        st, esc, n = ps.state, self.escalator, self.counters
        t0 = self._now()
        sdnotify.notify("READY=1")
        n.last_tick_mono = time.monotonic()
        k0 = st.next  # 0, or where the last run of this path stopped (restored at the start)
        while not self._stop.is_set():
            if duration_s is not None and self._now() - t0 >= duration_s:
                break
            if self.cfg.stream.passes is not None and st.passes >= self.cfg.stream.passes:
                break
            t_now = self._now()
            self.paging.apply_actions(t_now)
            if not self._trusted() and self.cfg.halt.on_untrusted == "halt":
                esc.halt(f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)", t_now, sticky=True)
            if self._camera_halt and esc.state != "halted":
                self._camera_halt, n.camera_refused_since = False, None
            if self._camera_halt:
                self._probe_camera(t_now)
                self._stop.wait(0.0 if self.world is not None and not self.cfg.realtime else 0.05)
                continue
            if esc.state == "halted":  # sticky: waits for the operator's 'done'
                self._idle()
                self._beat()
                self._stop.wait(0.0 if self.world is not None and not self.cfg.realtime else 0.05)
                continue
            if st.rerun_from is not None:
                log.warning("resuming the path at %s", ps.plan.where(k0) + st.rerun_from)
                st.rerun_from = None
            corrected = self._trusted() or self.cfg.halt.on_untrusted == "correct"
            try:
                rep = ps.run_pass(k0, corrected)
            except (DriverError, TwinError) as exc:  # the child could not start (a driver, the twin)
                if isinstance(exc, StoreError):
                    raise
                self._driver_fault(DriverError(f"path pass from {ps.plan.where(k0)}: {exc}"))
                self._stop.wait(0.5)
                continue
            n.ticked(rep.n_sent)
            if not corrected:
                n.uncorrected += rep.n_sent
            n.driver_faults_in_row = 0
            self._stage_path()
            if not rep.stopped:
                k0 = 0
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
            if self._stop.is_set() or esc.state == "halted":
                continue  # stopping, or already halted (the camera's halt resumes by itself)
            why = (f"path stopped at {ps.plan.where(k_stop)}: {rep.stopped}; clear the cause, then confirm "
                   f"(dt ack): the path resumes at {ps.plan.where(k0)}")
            n.last_problem = why
            log.error("%s", why)
            esc.halt(why, self._now(), sticky=True)
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

    def stop(self, *_: Any) -> None:
        """Stop the loop (a signal handler: only sets flags): the move in flight is aborted."""
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

    def summary(self) -> dict:
        esc = self.escalator
        return {**self.counters.summary(), "state": esc.state, "halt_reason": esc.halt_reason,
                "maintenance_requests": len(self.paging.requests), "requests_delivered": len(self.paging.delivered),
                "store": str(self.store.path), **self.cell.truth(),
                **({"path": self.path.state.to_dict()} if self.path is not None else {})}

    def close(self) -> None:
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
        self._close_opened()



def run_daemon(config: str | Path, duration_s: float | None = None, status_every_s: float | None = None) -> dict:
    """`dt run`: start (a failure raises with everything closed), run until the duration ends or
    SIGTERM/SIGINT, stop within `stop_timeout_s` whatever a device does; the status line every
    `status_every_s` (None: never)."""
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


def _exit_hard(after_s: float) -> None:
    log.error("not stopped within stop_timeout_s = %.1f s: exiting now", after_s)
    logging.shutdown()
    os._exit(75)  # EX_TEMPFAIL: the service manager may restart it
