"""`dt run`: the long-running twin daemon.

Every tick: take the next target, apply the bounded correction with the twin's maps
(service.correction) under the cell's conditions when the maps read them (joint angles from the
controller, temperature and payload from the program's columns or the simulated cell's sensors,
the clock: `twin.conditions`), move the robot, read the MVS, test the measurement against the
prediction (Eq. 17), feed the escalation state machine, log everything to the durable store
(typed rows, `service.rows`, on the Store's one lock-free queue: the loop never waits on SQLite)
and publish over Zenoh. Drivers are built by `drivers.registry.create` from `drivers.<kind>`
(`kind` and the driver's options, checked before anything opens), the same way whatever their name.

Measurements and clocks. Every reading carries the device's time stamp (`t`) and the host's
monotonic receive time (`host_time`, drivers.base). The MVS reading tested against a command is
one received after the command arrived (the move returned) or at most `max_measurement_age_s`
before it; an older one saw the arm elsewhere and is refused, counted (`stale_measurements` in
the summary and on `.../health`), and not tested.

Escalation and paging. Every transition of the machine (`service.escalation`) is one store
transaction with the machine's new snapshot and, on entering `maintenance_requested` or
`halted`, that episode's maintenance requests (one per consumer group) in the outbox; only then
is it published (`.../state`, `.../health`) and the bus woken to deliver the requests, which it
republishes until each group acknowledges. If the store cannot commit, the machine stays where
it was and the next test fires the transition again. At start-up the daemon re-creates the
requests of a paging state that has none (`_reconcile`), and the escalation statistics resume
from the store (staged with every batch of rows).

Halts. Every command refused for `halt.after_refused` ticks, `halt.after_driver_faults` driver
faults in a row, no MVS reading tested for `halt.after_camera_refused_s` (refused by the camera
driver, too old, or rejected), or `out_of_control` under `halt.on_untrusted: halt`, put the
machine in `halted` with the reason: stored, paged and published on `.../health`; the first two
resume by themselves when a command goes through again; a camera halt stops the arm (it would
move unmonitored), reads the camera once a tick and resumes at the first accepted reading. In
`out_of_control` and `maintenance_requested` the correction is not trusted: by default the
daemon commands the targets uncorrected.

Operator. `dt ack` (or a maintenance system's `.../maintenance/done/<id>` on the bus, signed with
the service's key: bus.auth) stores an operator action (who, why); the daemon's housekeeping
thread picks it up and the loop applies it:
`maintenance_requested` or `halted` -> `nominal`, statistics reset, in the transition's
transaction. A 'done' that names a request of an earlier episode is stored as ignored.

Housekeeping (one thread, never the loop): operator actions, `.../health` every
`bus.health_period_s` (and on every change, from the loop), store retention, and the systemd
watchdog (`service.sdnotify`: READY on start, WATCHDOG while the loop ticks, STOPPING).

Start and stop. Any start-up failure closes what was opened (bus, store, drivers) and raises, so
`dt run` exits non-zero within seconds; one daemon per store (a lock). `stop()` (SIGTERM, SIGINT)
aborts a move in flight; `run_daemon` exits within `stop_timeout_s` whatever a device does.

`realtime: true` paces ticks at `rate_hz` on the wall clock (a real cell); `realtime: false`
runs as fast as it can on the simulated clock (soaks and tests).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers import registry
from drivers.base import read_exposed_after
from dt_kernel.errors import ConfigError, DriverError, TwinError
from dt_runtime.service import sdnotify
from dt_runtime.service.bus import Bus, CorrectionServer
from dt_runtime.service.bus.publisher import new_requests
from dt_runtime.service.correction import Corrected, CorrectionFault, Corrector, Monitor
from dt_runtime.service.escalation import PAGING, Escalator
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
from dt_runtime.service.store import OperatorAction, Store, StoreError
from dt_runtime.twin.campaign import Instruments
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.program import read_program
from dt_runtime.twin.simulate import load_scenario_file
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")
status_log = logging.getLogger("dt.run.status")  # the operator's periodic one-line status


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
        self._program = read_program(self._p(cfg.path.program)) if cfg.path.program else None
        self._check_condition_sources()
        self._check_model()
        self._step = 0  # the next program target
        self.corrector = Corrector(self.twin, cfg.limits)
        self.monitor = Monitor(self.twin, cfg.alpha)
        # High-rate rows leave the loop through the Store's lock-free queue; its writer thread
        # commits them every 50 ms, so the loop never waits on a lock or an fsync.
        self.store = Store(self._p(cfg.store), batch_ms=50.0, background=True, exclusive=True)
        self._closers.append(self.store.close)
        self.bus = (Bus(cfg.bus, self.store, on_ack=self._on_ack, on_done=lambda _id: self._poll_now.set())
                    if cfg.publish else None)
        if self.bus:
            self._closers.append(self.bus.close)
        # The cell's program may ask for corrections on `.../correct` (its own Corrector: the
        # step bound follows the program's sequence of requests, not the daemon's path).
        self._cond: Conditions | None = None  # the cell's latest conditions (the correct service reads them)
        self.correct_server = (CorrectionServer(Corrector(self.twin, cfg.limits), cfg.bus, self.bus.session,
                                                conditions=lambda: self._cond) if self.bus else None)
        if self.correct_server:
            self._closers.append(self.correct_server.close)
        self.world = world if world is not None else self._make_world()
        if world is None and self.world is not None:
            self._closers.append(self.world.close)
        self.inst = self._make_instruments()
        self.escalator = Escalator(cfg.escalation, on_transition=self._on_transition)
        saved = self.store.load_state()
        if saved and saved.get("name") == "escalation":
            self.escalator.restore(saved["data"])
            log.info("resumed escalation state %s (episode %d) from %s", self.escalator.state,
                     self.escalator.episode, self.store.path)
        self._rng = np.random.default_rng(cfg.path.seed)
        self._phase = 0.0
        self._faults = sorted(cfg.sim.faults, key=lambda f: f.at_s)
        self._stop = threading.Event()
        self._poll_now = threading.Event()  # an operator action arrived: poll at once
        self._actions: collections.deque[OperatorAction] = collections.deque()
        self._actions_seen: set[int] = set()
        self._actions_lock = threading.Lock()
        self.delivered: list[int] = []
        self.ticks = self.failures = self.faults_refused = self.driver_faults = self.stale_measurements = 0
        self.mvs_refused = 0  # MVS readings refused by the camera driver (lost, late, untracked, ...)
        self.refused_in_row = self.driver_faults_in_row = self.mvs_refused_in_row = 0
        self._camera_refused_since: float | None = None  # daemon time of the first untested reading in a row
        self._camera_halt = False  # halted because the camera gave no usable reading (resumes on one)
        self.last_problem: str | None = None
        self.uncorrected = 0  # commands sent without the correction (it was not trusted)
        self._true_sq: list[float] = []  # squared 3D true error of each command (simulation only)
        self.requests: list[dict] = []
        self.tick_times: list[float] | None = None  # set to [] to record tick start times
        self.latencies: list[float] | None = None  # set to [] to record reading receipt -> t-test done (s)
        self.exposure_latencies: list[float] | None = None  # set to []: mid-exposure (host clock) -> t-test done
        self._last_tick_wall: float | None = None
        self._last_tick_mono = float("-inf")  # the watchdog is fed from READY on
        self._last_corrected: tuple[float, Corrected] | None = None  # (t, the last command sent), for status_line
        self._status_mark = (time.monotonic(), 0)  # (when, ticks) of the last status line: its rate
        self._notify_lock = threading.Lock()  # STOPPING=1 is the last message systemd gets
        self._stopping = False
        self._health_key: tuple | None = None
        self._health_due = threading.Event()  # the loop saw a change: the housekeeper publishes
        self._applying: OperatorAction | None = None  # the 'done' whose transition is being recorded
        self._reconcile()
        self._housekeeper = threading.Thread(target=self._housekeep, name="dt-daemon-housekeeping", daemon=True)
        self._housekeeper.start()
        self._closers.append(self._stop_housekeeping)
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
        pc = self.cfg.path
        probe = (self._program.target[0] if self._program is not None else
                 np.array(pc.circle_center_m) if pc.kind == "circle" else
                 (np.array(pc.box_min_m) + np.array(pc.box_max_m)) / 2)
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
        robot, tracker, camera = self.cfg.drivers.create(self.world, self.source)
        inst = Instruments(robot, tracker, camera, world=self.world,
                           max_speed=self.world.max_speed() if self.world else self.cfg.limits.max_speed_m_s)
        self._closers.append(inst.close)
        inst.activate()
        return inst

    # --- escalation, paging and the store (callbacks never block on the bus) -----------------
    def _request_body(self, dst: str, evidence: dict, t: float, reconciled: bool = False) -> dict:
        esc = self.escalator
        halt = dst == "halted"
        return {"t": t, "state": dst, "episode": esc.episode, "kind": "halt" if halt else "t_test",
                "reason": (f"halted: {esc.halt_reason}" if halt else "repeated Eq. 17 t-test failures"),
                "evidence": evidence, **({"reconciled": True} if reconciled else {})}

    def _on_transition(self, src: str, dst: str, evidence: dict, t: float) -> None:
        """Record first (one transaction; raises StoreError and the machine stays), then act."""
        opens = dst in PAGING and src not in PAGING
        reqs = new_requests(self.cfg.bus, self._request_body(dst, evidence, t)) if opens else []
        applying = self._applying
        applied = (applying.id, f"applied: {src} -> {dst}") if applying is not None and dst == "nominal" else None
        _, ids = self.store.record_transition(src, dst, evidence, t, state=("escalation", self.escalator.snapshot()),
                                              requests=reqs, applied=applied)
        log.warning("escalation %s -> %s at t=%.1f s: %s", src, dst, t, evidence)
        if reqs:
            self.requests.append(reqs[0][1] | {"ids": ids})
        if self.bus:
            self.bus.publish_state({"src": src, "dst": dst, "t": t, "evidence": evidence})
            if reqs:
                self.bus.wake()
        self._publish_health(force=True)

    def _reconcile(self) -> None:
        """A paging state without its requests (a store written by an older version, or edited)
        gets them now; a 'done' left unapplied is queued."""
        esc = self.escalator
        if esc.state in PAGING and not self.store.outbox_of_episode(esc.episode):
            last = next((tr for tr in reversed(self.store.transitions(50)) if tr["dst"] == esc.state), None)
            evidence = last["evidence"] if last else esc.evidence()
            body = self._request_body(esc.state, evidence, last["t"] if last else self._now(), reconciled=True)
            ids = self.store.outbox_add_many(new_requests(self.cfg.bus, body))
            self.requests.append(body | {"ids": ids})
            log.warning("state %s (episode %d) had no maintenance request in %s: re-created %s",
                        esc.state, esc.episode, self.store.path, ids)
            if self.bus:
                self.bus.wake()

    def _on_ack(self, oid: int, payload: dict) -> None:
        # Delivery acknowledgement: the request reached maintenance and leaves the outbox. The
        # machine stays in maintenance_requested until maintenance is confirmed done, or the
        # same fault would page again at once.
        self.delivered.append(oid)

    def acknowledge_maintenance(self, note: str = "maintenance done", by: str = "operator") -> int:
        """Operator confirmation, as `dt ack` does it: stored as an action (who, why), applied by
        the loop at its next tick. Returns the action's id."""
        with self._actions_lock:  # the housekeeper must not queue it a second time
            aid = self.store.add_action("done", by, note, source="api")
            self._actions_seen.add(aid)
            self._actions.append(OperatorAction(aid, time.time(), "done", None, by, note, "api"))
        return aid

    def _take_actions(self) -> None:
        """Housekeeping: queue the operator actions the loop has not seen (never blocks the loop)."""
        with self._actions_lock:
            for a in self.store.actions(pending_only=True):
                if a.kind == "done" and a.id not in self._actions_seen:
                    self._actions_seen.add(a.id)
                    self._actions.append(a)

    def _apply_actions(self, t: float) -> None:
        """The loop: apply queued 'done' actions (machine transitions are the loop's alone)."""
        while self._actions:
            a = self._actions[0]
            esc = self.escalator
            if esc.state not in PAGING:
                result = f"ignored: the escalation was {esc.state}"
            elif a.request_id is not None and self._episode_of(a.request_id) != esc.episode:
                result = f"ignored: request {a.request_id} is not of the open episode {esc.episode}"
            else:
                episode = esc.episode
                self._applying = a
                try:
                    esc.acknowledge(t, note=a.note, by=a.by)  # records the action as applied, same transaction
                finally:
                    self._applying = None
                self._actions.popleft()  # applied: a failing write below must not judge it again
                self.store.outbox_ack_episode(episode)  # done implies delivered: stop republishing
                continue
            self.store.apply_action(a.id, result)
            log.info("operator action %d (%s by %s) %s", a.id, a.kind, a.by, result)
            self._actions.popleft()

    def _episode_of(self, request_id: int) -> int | None:
        item = self.store.outbox_get(request_id)
        return None if item is None else item.payload.get("episode")

    # --- health ------------------------------------------------------------------------------
    def _status(self) -> tuple[str, str | None]:
        """(running | degraded | halted, why): cheap, no I/O (the loop calls it every tick)."""
        esc = self.escalator
        if esc.state == "halted":
            return "halted", esc.halt_reason
        if self.store.write_errors_in_row:
            return "degraded", "store writes failing"
        if self.refused_in_row or self.driver_faults_in_row or self.mvs_refused_in_row:
            return "degraded", self.last_problem
        if not self._trusted() and self.cfg.halt.on_untrusted == "uncorrected":
            return "degraded", f"{esc.state}: commands sent uncorrected"
        return "running", None

    def health(self) -> dict[str, Any]:
        """What `.../health` carries: running / degraded / halted and why, the escalation state,
        the last tick, and the counters an operator looks at first."""
        status, reason = self._status()
        esc = self.escalator
        return {"status": status, "reason": reason, "escalation": esc.state, "episode": esc.episode,
                "last_tick": self._last_tick_wall, "ticks": self.ticks, "refused_in_row": self.refused_in_row,
                "driver_faults_in_row": self.driver_faults_in_row, "stale_measurements": self.stale_measurements,
                "mvs_refused": self.mvs_refused, "mvs_refused_in_row": self.mvs_refused_in_row,
                "camera_untested_s": (None if self._camera_refused_since is None
                                      else round(self._now() - self._camera_refused_since, 3)),
                "outbox_pending": self._pending_count(), "drivers": self._driver_counters(),
                # acks and 'done's on the bus without the service's signature: refused, not recorded
                "bus_refused": self.bus.refused if self.bus else 0,
                "bus_last_refused": self.bus.last_refused if self.bus else None,
                "pid": os.getpid(), "t": time.time()}

    def status_line(self) -> tuple[str, dict[str, Any]]:
        """The operator's one line (`dt run` logs it every `status_every_s`): ticks and their rate
        since the last line, status and escalation state, the time of the last command and the
        expanded uncertainty (95 %) of the position it reached; and the same as fields."""
        now, ticks = time.monotonic(), self.ticks
        then, before = self._status_mark
        self._status_mark = (now, ticks)
        rate = (ticks - before) / (now - then) if now > then else 0.0
        status, reason = self._status()
        f: dict[str, Any] = {"ticks": ticks, "rate_hz": round(rate, 2), "status": status, "reason": reason,
                             "escalation": self.escalator.state, "t_test_failures": self.failures}
        text = f"{ticks} ticks ({rate:.1f}/s), {status}" + (f" ({reason})" if reason else "") + \
            f", escalation {self.escalator.state}, Eq. 17 failed {self.failures}"
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
        self._health_due.set()
        self._poll_now.set()

    def _send_health(self) -> None:
        if self.bus:
            self.bus.publish_health(self.health())

    # --- housekeeping thread -----------------------------------------------------------------
    def _housekeep(self) -> None:
        period = self.cfg.bus.health_period_s
        next_health = next_prune = time.monotonic()
        next_status = next_health + (self.status_every_s or 0.0)
        watchdog = sdnotify.watchdog_period()
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                self._take_actions()
                if now >= next_health or self._health_due.is_set():
                    self._health_due.clear()
                    next_health = now + period
                    self._send_health()
                if now >= next_prune:
                    next_prune = now + self.cfg.retention.every_s
                    self.prune()
                if self.status_every_s and now >= next_status:
                    next_status = now + self.status_every_s
                    text, fields = self.status_line()
                    status_log.info("%s", text, extra={"fields": fields})
            except TwinError as exc:  # the store or bus is down: keep trying
                log.warning("housekeeping: %s", exc)
            except Exception:  # noqa: BLE001 - a defect here must not end paging or the watchdog
                log.exception("housekeeping failed")
            # The watchdog is fed only while the loop ticks: a wedged loop gets restarted. Never
            # after STOPPING=1 (close() takes the same lock to send it).
            with self._notify_lock:
                if watchdog and not self._stopping and time.monotonic() - self._last_tick_mono < watchdog:
                    sdnotify.notify("WATCHDOG=1")
            self._poll_now.wait(min(0.5, period, watchdog / 2 if watchdog else 0.5, self.status_every_s or 0.5))
            self._poll_now.clear()

    def _stop_housekeeping(self) -> None:
        self._stop.set()
        self._poll_now.set()
        self._housekeeper.join(timeout=2.0)

    def prune(self) -> int:
        """Apply the retention policy to the store's high-rate rows; returns rows deleted."""
        r = self.cfg.retention
        before = None if r.max_age_s is None else self._now() - r.max_age_s
        return self.store.prune(before_t=before, keep_rows=r.max_rows)

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

    def _idle(self) -> None:
        """A tick that moved nothing: on the simulated clock, let a period pass (or a run of
        refused commands would never end in simulated time)."""
        if self.world is not None and not self.cfg.realtime:
            self.world.idle(1.0 / self.cfg.rate_hz)

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

    def _trusted(self) -> bool:
        return self.escalator.state not in ("out_of_control", "maintenance_requested")

    def tick(self) -> None:
        t_now = self._now()
        self._apply_actions(t_now)
        target, v, step = self._next_target()
        if self.world is not None:
            self._inject_faults(self.world.t)
        esc = self.escalator
        policy = self.cfg.halt.on_untrusted
        if not self._trusted() and policy == "halt":
            esc.halt(f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)", t_now, sticky=True)
        if esc.state == "halted" and esc.halt_sticky:  # waits for the operator's 'done'
            self._idle()
            self._publish_health()
            return
        if self._camera_halt and esc.state != "halted":  # left by the operator's 'done': time afresh
            self._camera_halt, self._camera_refused_since = False, None
        if self._camera_halt:
            self._probe_camera(t_now)
            return
        cond = self._cond = self._conditions(step)
        try:
            if self._trusted() or policy == "correct":
                corr = self.corrector(target, v, cond)
            else:
                corr = self.corrector.uncorrected(target, v)
                self.uncorrected += 1
        except CorrectionFault as exc:
            self.faults_refused += 1
            self.refused_in_row += 1
            self.last_problem = f"command refused: {exc}"
            log.error("command refused, robot not moved: %s", exc)
            if self.refused_in_row >= self.cfg.halt.after_refused:
                esc.halt(f"every command refused for {self.refused_in_row} ticks; last: {exc}", t_now)
            self._idle()
            self._publish_health()
            return
        self.inst.robot.move_linear(corr.command, v)
        arrived = time.monotonic()  # the command has arrived: the arm stands where it was sent
        self.refused_in_row = self.driver_faults_in_row = 0
        if esc.state == "halted":
            esc.resume(t_now)
        if self.world is not None:  # simulation: the true error in GL, as `dt demo` scores it (target - truth)
            tw = self.twin
            e = tw.T_rdk.apply(corr.target) - tw.T_lt.apply(self.world.truth_in_tracker_frame())
            self._true_sq.append(float(np.sum(e ** 2)))
        t = self._now()
        x, y, z = corr.target
        self.store.put(CommandRow(t, x, y, z, speed=v))
        self.store.put(CorrectionRow(t, *corr.correction, *corr.u_tcp))
        self._last_corrected = (t, corr)
        camera = self.inst.camera
        assert camera is not None  # _make_instruments always builds one (drivers.camera names a driver)
        reading = read_exposed_after(camera, arrived)  # a streamed frame exposed mid-move saw the arm elsewhere
        self.ticks += 1
        self._last_tick_wall, self._last_tick_mono = time.time(), time.monotonic()
        if not reading.ok or reading.point is None:
            # nothing to test: counted and reported (degraded while it lasts), the arm is not moved again
            self.mvs_refused += 1
            self.mvs_refused_in_row += 1
            self.last_problem = f"MVS refused: {reading.refused}"
            log.info("MVS refused: %s", reading.refused)
            self._camera_untested(self.last_problem)
            self._publish_health()
            return
        self.mvs_refused_in_row = 0
        age = arrived - reading.host_time
        if age > self.cfg.max_measurement_age_s:
            self.stale_measurements += 1
            self.last_problem = (f"stale measurement: received {age * 1e3:.0f} ms before the command arrived "
                                 f"(max_measurement_age_s {self.cfg.max_measurement_age_s})")
            log.warning("MVS reading refused, not tested: %s", self.last_problem)
            self._camera_untested(self.last_problem)
            self._publish_health()
            return
        try:
            chk = self.monitor(corr.command, v, reading.point, cond)
        except CorrectionFault as exc:
            log.error("MVS value rejected: %s", exc)
            self._camera_untested(f"MVS value rejected: {exc}")
            return
        self._camera_refused_since = None
        self.store.put(MeasurementRow(t, *reading.point, *chk.diff))
        worst = int(np.argmax(np.abs(chk.t)))
        self.store.put(TTestRow(t, float(chk.t[worst]), None, float(np.min(chk.p_value)), chk.passed,
                                data={"t": chk.t.tolist()}))
        self.failures += int(not chk.passed)
        esc.observe(chk.passed, float(chk.t[worst]), t)
        done = time.monotonic()
        if self.latencies is not None:
            self.latencies.append(done - reading.host_time)
        mid = reading.quality.get("mid_exposure_host_s")
        if self.exposure_latencies is not None and mid is not None:
            self.exposure_latencies.append(done - mid)
        # The statistics travel with the next batch of rows: a restart resumes them.
        self.store.stage_state("escalation", esc.snapshot())
        if self.bus:
            self.bus.publish_telemetry({"t": t, "target": corr.target.tolist(), "command": corr.command.tolist(),
                                        "t_stat": chk.t.tolist(), "passed": chk.passed,
                                        "state": esc.state})
        self._publish_health()

    def _camera_untested(self, why: str) -> None:
        """A reading that could not be tested: after `halt.after_camera_refused_s` of nothing
        but these, halt (paged; the loop then stops the arm and probes the camera)."""
        t = self._now()
        if self._camera_refused_since is None:
            self._camera_refused_since = t
        limit = self.cfg.halt.after_camera_refused_s
        blind = t - self._camera_refused_since
        if blind >= limit and self.escalator.state != "halted":
            self._camera_halt = self.escalator.halt(
                f"no MVS reading tested for {blind:.1f} s (halt.after_camera_refused_s {limit:g} s); last: {why}", t)

    def _probe_camera(self, t_now: float) -> None:
        """Halted for the camera: the arm stands; one reading a tick, the first accepted resumes."""
        camera = self.inst.camera
        assert camera is not None
        reading = camera.read()
        if reading.ok:
            self._camera_halt, self._camera_refused_since, self.mvs_refused_in_row = False, None, 0
            self.escalator.resume(t_now)
            log.warning("the camera gives readings again: resumed")
        else:
            self.last_problem = f"MVS refused: {reading.refused}"
            self._idle()
        self._publish_health()

    def _driver_fault(self, exc: DriverError) -> None:
        self.driver_faults += 1
        self.driver_faults_in_row += 1
        self.last_problem = f"driver fault: {exc}"
        log.error("driver fault: %s", exc)
        if self.driver_faults_in_row >= self.cfg.halt.after_driver_faults and not self._stop.is_set():
            try:
                self.escalator.halt(f"driver fault {self.driver_faults_in_row} times in a row: {exc}", self._now())
            except StoreError as store_exc:
                log.error("halt not recorded, retried on the next fault: %s", store_exc)
        self._publish_health()

    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> dict:
        period = 1.0 / self.cfg.rate_hz
        t0 = self._now()
        next_t = time.monotonic()
        sdnotify.notify("READY=1")
        self._last_tick_mono = time.monotonic()
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
                else:
                    next_t = time.monotonic()
        return self.summary()

    def stop(self, *_: Any) -> None:
        """Stop the loop (a signal handler: only sets flags): the move in flight is aborted."""
        self._stop.set()
        self._poll_now.set()
        robot = getattr(getattr(self, "inst", None), "robot", None)
        abort = getattr(robot, "abort", None)
        if abort is not None:
            abort("the daemon is stopping")

    def summary(self) -> dict:
        out = {"ticks": self.ticks, "t_test_failures": self.failures, "refused_commands": self.faults_refused,
               "driver_faults": self.driver_faults, "uncorrected_commands": self.uncorrected,
               "stale_measurements": self.stale_measurements, "mvs_refused": self.mvs_refused,
               "state": self.escalator.state, "halt_reason": self.escalator.halt_reason,
               "maintenance_requests": len(self.requests), "requests_delivered": len(self.delivered),
               "store": str(self.store.path)}
        if self._true_sq:  # the simulated cell's truth: 3D RMS of target - where the arm went
            out["true_rms_mm"] = round(float(np.sqrt(np.mean(self._true_sq))) * 1e3, 5)
            out["true_n"] = len(self._true_sq)
        return out

    def close(self) -> None:
        with self._notify_lock:
            self._stopping = True
            sdnotify.notify("STOPPING=1")
        try:
            self.store.save_state("escalation", self.escalator.snapshot())
        except TwinError as exc:
            log.error("could not save state on close: %s", exc)
        self._stop_housekeeping()
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
