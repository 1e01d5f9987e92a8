"""`dt run` streaming a path program: the plan (`plan_path`: the path interpolated at the
controller's rate, corrected offline and checked against the bounds before anything moves), and
its passes (`PathStreamer`): every set-point corrected in the loop, the moving arm tested against
the path by Eq. 17 with its servo lag learnt and compensated, a pass that stops halting the
daemon until the operator confirms, then resumed where the arm stands.

Passes, the lag, stops and resume, and what `.../health` carries: docs/streaming.md ("`dt run`
streaming a path program"). Units: SI (m, s).
"""
from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers import registry
from drivers.base import RigReading
from dt_kernel.errors import ConfigError, DataError
from dt_runtime.metrology.timing import TimedPath, compare_at
from dt_runtime.programs.lag import SETTLE_S, LagEstimate, compensate, estimate_lag, settled
from dt_runtime.programs.path import Setpoints, interpolate, read_path
from dt_runtime.programs.path_correct import correct_path
from dt_runtime.service.runtime_config import StreamSection
from dt_runtime.service.stream import PAUSE_AFTER_PERIODS, StreamProcess, StreamReport, run_stream
from dt_runtime.twin.bounds import Limits, check_path_bounds
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")
APPROACH_SPEED_M_S = 0.05  # the move to a pass's first command (a resume point may be anywhere)
LAG_WARN_RATIO = 3.0  # the lag model's u over Eq. 17's u above which the operator is told
MIN_LAG_READINGS = 20  # fewer tested positions on a moving arm: the lag is not learnt, the pass repeats


# --- built in the streaming process (module-level: StreamProcess pickles them) ---------------
def path_corrector(twin_dir: str, times: np.ndarray, speeds: np.ndarray, correct: bool = True,
                   joints: np.ndarray | None = None) -> Callable[[np.ndarray, float], np.ndarray]:
    """The correction law along the path (`Corrector.follow`) of the twin in `twin_dir` (loaded in
    the streaming process), or the target itself (`correct` False: an uncorrected stream).

    Parameters
    ----------
    twin_dir : str
        The twin's directory.
    times : ndarray
        (n,) s, the path times of the set-points streamed.
    speeds : ndarray
        (n,) m/s, their programmed speeds.
    correct : bool
        False: the command is the target (the correction is not trusted).
    joints : ndarray, optional
        (dof,) rad, the joints at the first set-point, when the twin reads joints.

    Returns
    -------
    callable
        `(target m, t s) -> command m`.
    """
    if not correct:
        return lambda target, t: target
    return Corrector(Twin.load(twin_dir)).follow(times, speeds, joints)


def streaming_robot(name: str, options: dict, source: str, start: np.ndarray, speed: float):
    """The robot driver `name` with `options`, active, the arm moved to `start` (closed again if
    that fails).

    Parameters
    ----------
    name : str
        The robot driver's kind (drivers.registry).
    options : dict
        Its options.
    source : str
        Names the runtime config in errors.
    start : ndarray
        (3,) m, robot frame: where the arm waits for the first set-point.
    speed : float
        m/s, the approach move's speed.

    Returns
    -------
    Driver
        The active driver.

    Raises
    ------
    TwinError
        ConfigError for an unknown driver or a bad option, DriverError if it cannot activate or move.
    """
    drv = registry.create("robot", name, options, source=source, key="drivers.robot")
    try:
        drv.activate()
        drv.move_linear(np.asarray(start, dtype=float), speed)
    except BaseException:
        drv.close()
        raise
    return drv


# --- the plan --------------------------------------------------------------------------------
@dataclass(frozen=True)
class PathPlan:
    """The path interpolated and corrected offline: set-points `sp`, their corrected commands
    (n, 3) m and joints (n, dof) rad or None."""

    file: Path
    sp: Setpoints
    commands: np.ndarray
    joints: np.ndarray | None

    @property
    def n(self) -> int:
        """The number of set-points."""
        return self.sp.n

    def where(self, k: int) -> str:
        """Set-point k as the operator reads it: 1-based, with its segment and time.

        Parameters
        ----------
        k : int
            0-based index (clipped to the last set-point).

        Returns
        -------
        str
            E.g. "set-point 157 of 627 (segment 2, t 1.248 s)".
        """
        k = min(k, self.n - 1)
        return f"set-point {k + 1} of {self.n} (segment {int(self.sp.segment[k])}, t {self.sp.t[k]:.3f} s)"


def plan_path(twin: Twin, file: Path, rate_hz: float, limits: Limits, source: str) -> PathPlan:
    """The path file read, interpolated at the controller's rate, corrected offline and checked
    against the bounded-correction rules (`twin.bounds.check_path_bounds`), before anything moves.

    Parameters
    ----------
    twin : Twin
        The daemon's twin.
    file : Path
        The path program (the `dt correct --path` format).
    rate_hz : float
        The controller's rate: the set-points' grid, Hz.
    limits : Limits
        The runtime config's bounds.
    source : str
        Names the runtime config in errors.

    Returns
    -------
    PathPlan
        The set-points, their corrected commands and joints.

    Raises
    ------
    ConfigError
        Naming `path.program` for anything the daemon would refuse later (an unreadable path, one
        the twin cannot correct, one outside the limits), or `path.kind` for a twin whose maps read
        conditions other than speed and joints.
    """
    try:
        program = read_path(file)
        sp = interpolate(program, rate_hz)
        corrected = correct_path(twin, program, sp)
    except (DataError, ConfigError) as exc:
        raise ConfigError(source, "path.program", str(file), f"a path the twin can correct ({exc})") from exc
    commands = np.array([r.command for r in corrected])
    why = check_path_bounds(limits, sp.p, commands)
    if why:
        raise ConfigError(source, "path.program", str(file), f"a path within the limits: {why}")
    extra = set(twin.needs) - {"speed", "joints"}
    if extra:
        raise ConfigError(source, "path.kind", "path", "a twin whose maps read TCP, speed and joints only: a streamed "
                          f"path is corrected in its own process without the cell's sensors (this twin reads "
                          f"{sorted(extra)}); run the path as a point program instead")
    joints = None if corrected[0].joints is None else np.array([r.joints for r in corrected])
    return PathPlan(file, sp, commands, joints)


# --- a pass -----------------------------------------------------------------------------------
@dataclass
class StreamState:
    """The path's state, as `.../health` carries it under `stream` and the summary under `path`."""

    n: int
    file: str
    state: str = "idle"  # idle | learning | streaming | stopped | done
    passes: int = 0  # passes completed to their last set-point
    pass_started: int = 0  # passes started (learning included)
    next: int = 0  # 0-based: the set-point the next pass starts at
    sent: int = 0  # set-points streamed since the start, every pass
    rerun: int = 0  # set-points streamed a second time after a stop (the arm had not reached them)
    tested: int = 0  # readings of the moving arm tested by Eq. 17
    learning_readings: int = 0  # readings of a learning pass (compared, not tested)
    timing_refused: int = 0  # readings refused: the timing term dominated
    outside_refused: int = 0  # readings outside the pass's time span (before its start, after its end)
    transient_refused: int = 0  # readings in the servo's transient after a step of the path's acceleration
    host_pauses: int = 0  # passes stopped by a host stall (the controller's watchdog) and resumed without a halt
    stopped: str = ""  # why the last pass ended early ("" when none did)
    rerun_from: str | None = None  # set at a stop: what the resume re-runs, in words (logged once, at the resume)
    lag: dict | None = None  # LagEstimate.to_dict() once learnt
    last: dict = field(default_factory=dict)  # the last pass's rate, jitter, correction cost, realtime

    def to_dict(self) -> dict[str, Any]:
        """The fields as a dict (JSON-ready: what the store's resume row and `.../health` carry)."""
        return dict(self.__dict__)


ReadingTest = Callable[[np.ndarray, float, np.ndarray, Conditions | None, float, np.ndarray, bool], Any]


@dataclass(frozen=True)
class StreamCell:
    """Where passes stream: the `twin` (and `twin_dir`, loaded again by a streaming process), the
    daemon's drivers `inst`, the simulated `world` (None on a real cell), the robot driver's
    kind and options (`robot`, built again by a streaming process) and the runtime config that
    names them in errors (`source`)."""

    twin: Twin
    twin_dir: Path
    inst: Any
    world: Any
    robot: tuple[str, dict]
    source: str


@dataclass(frozen=True)
class PassHooks:
    """What a pass asks of the daemon. `test(command, v, point, cond, s, u_extra, observe)`: Eq. 17
    of one reading at path time s (its `Check`, or None if the reading was rejected; `observe`
    False for a learning pass: compared, not fed to the escalation); `refused(reading)`: a reading
    the camera refused (counted, as a point program's); `stop()`: why the pass must end now (''
    to go on); `beat()`: every step of a pass (the watchdog, health); `u_reading`: a reading's
    standard uncertainty per axis, m."""

    test: ReadingTest
    refused: Callable[[RigReading], None]
    stop: Callable[[], str]
    beat: Callable[[], None]
    u_reading: np.ndarray


class PathStreamer:
    """Passes of `plan` for the daemon, its progress in `state`, on `cell`, asking `hooks`.

    Parameters
    ----------
    plan : PathPlan
        The path.
    state : StreamState
        Its state, updated in place (read by `.../health` and the status line).
    cfg : StreamSection
        The runtime config's `stream` section.
    rate_hz : float
        The controller's rate, Hz.
    cell : StreamCell
        The twin, the drivers and the simulated world.
    hooks : PassHooks
        What a pass asks of the daemon.

    Its methods run on the daemon's loop thread, except `cancel` (any thread, a signal handler).
    """

    def __init__(self, plan: PathPlan, state: StreamState, cfg: StreamSection, rate_hz: float, cell: StreamCell,
                 hooks: PassHooks):
        self.plan, self.state, self.cfg, self.rate_hz, self.hooks = plan, state, cfg, rate_hz, hooks
        self.twin, self.twin_dir, self.inst, self.world = cell.twin, cell.twin_dir, cell.inst, cell.world
        self.robot_choice, self.source = cell.robot, cell.source
        self.corrected = True
        self._pass_t0 = 0.0  # the path time of the running pass's first set-point
        self.u_reading = np.asarray(hooks.u_reading, dtype=float)
        self.lag: LagEstimate | None = None
        self.reference = TimedPath(plan.sp.t, plan.commands)  # where the arm should be, on the path's clock
        self.settled = settled(TimedPath(plan.sp.t, plan.sp.p))  # set-points out of the servo's transients
        self.proc: StreamProcess | None = None

    @property
    def u_lag(self) -> float:
        """The lag model's standard uncertainty per axis, m: what its fit left unexplained in the
        learning pass (3D RMS / sqrt 3: the follower's unmodelled dynamics, the timing's noise),
        where a compensated arm is known no better than that."""
        return 0.0 if self.lag is None else self.lag.rms_after_m / np.sqrt(3.0)

    @property
    def learning(self) -> bool:
        """The next corrected pass learns the servo lag (`stream.lag: learn`, not learnt yet)."""
        return self.cfg.lag == "learn" and self.lag is None

    def _targets(self) -> np.ndarray:
        """The targets streamed: the path, compensated for the learnt lag."""
        sp = self.plan.sp
        if self.lag is None:
            return sp.p
        return compensate(TimedPath(sp.t, sp.p), self.lag).p

    def run_pass(self, k0: int, corrected: bool = True) -> StreamReport:
        """Stream set-points k0 .. n-1 (the arm first moved to k0's command), testing the moving
        arm meanwhile; `state` is updated. On the simulated cell the pass runs in this process on
        the simulated clock; on any other it runs in a `StreamProcess` while this thread reads the
        camera `stream.monitor_hz` times a second.

        Parameters
        ----------
        k0 : int
            0-based set-point the pass starts at.
        corrected : bool
            False streams the targets as they are (the correction is not trusted:
            `halt.on_untrusted: uncorrected`), tested against them.

        Returns
        -------
        StreamReport
            Its `stopped` is empty if every set-point was sent.

        Raises
        ------
        TwinError
            The pass could not start (a driver, the twin), or the streaming process failed or
            gave no report in time.
        """
        st, sp = self.state, self.plan.sp
        learning = self.learning and corrected
        self.corrected = corrected
        self.reference = TimedPath(sp.t, self.plan.commands if corrected else sp.p)
        st.state, st.next, st.stopped = ("learning" if learning else "streaming"), k0, ""
        st.pass_started += 1
        targets = self._targets()
        self._pass_t0 = float(sp.t[k0])
        residuals: list[tuple[float, np.ndarray]] = []
        if self.world is not None:
            rep = self._pass_in_process(k0, targets, learning, residuals)
        else:
            rep = self._pass_in_child(k0, targets, learning, residuals)
        st.sent += rep.n_sent
        st.last = {k: rep.to_dict()[k] for k in ("rate_hz", "target_hz", "jitter_p99_ms", "overruns",
                                                  "correction_us_mean", "correction_us_p99", "realtime", "pauses",
                                                  "pause_max_ms", "skipped", "degraded", "host_gap_max_ms")}
        if rep.degraded:
            log.warning("the host could not keep %g Hz in this pass: %s", self.rate_hz, rep.degraded)
        if rep.stopped:
            st.state, st.stopped = "stopped", rep.stopped
            st.next = k0 + rep.n_sent
        else:
            st.state, st.next = "done", 0
            st.passes += 1
            if learning:
                self._learn(residuals)
        return rep

    # the simulated robot: in this process, on the simulated clock
    def _start(self, k0: int) -> np.ndarray:
        """Where the arm waits for a pass's first set-point: where the path has it then (set-point
        k0's corrected command, the target uncorrected), not the first command streamed (a
        feed-forward's is ahead of the path: the arm would start off it)."""
        return self.plan.commands[k0] if self.corrected else self.plan.sp.p[k0]

    def _pass_in_process(self, k0: int, targets: np.ndarray, learning: bool,
                         residuals: list[tuple[float, np.ndarray]]) -> StreamReport:
        sp, robot, world = self.plan.sp, self.inst.robot, self.world
        robot.move_linear(self._start(k0), APPROACH_SPEED_M_S)
        t_w0, period = world.t, 1.0 / self.rate_hz
        every = max(1, int(round(self.rate_hz / self.cfg.monitor_hz)))
        correct = (Corrector(self.twin).follow(sp.t[k0:], sp.programmed[k0:],
                                               None if self.plan.joints is None else self.plan.joints[k0])
                   if self.corrected else (lambda target, t: target))

        def progress(j: int) -> None:
            self.state.next = k0 + j
            self.hooks.beat()
            if j % every == 0:
                reading = self.inst.camera.read()
                # set-point j - 1 of the pass (meant for sp.t[k0 + j - 1]) was applied at t_w0 + j periods
                self._reading(reading, lambda r: float(sp.t[k0]) + (r.t - t_w0) - period, learning, residuals)

        return run_stream(sp.t[k0:], targets[k0:], correct, robot, self.rate_hz, self.cfg.lookahead_s,
                          self.cfg.gain, progress=progress, paced=False,
                          cancelled=self.hooks.stop)

    # any other robot: its own process
    def _pass_in_child(self, k0: int, targets: np.ndarray, learning: bool,
                       residuals: list[tuple[float, np.ndarray]]) -> StreamReport:
        sp, cfg = self.plan.sp, self.cfg
        name, options = self.robot_choice
        start = self._start(k0)
        robot = self.inst.robot
        robot.deactivate()  # the child's driver takes the connection and the controller's registers
        try:
            proc = self.proc = StreamProcess(
                functools.partial(path_corrector, str(self.twin_dir), sp.t[k0:], sp.programmed[k0:], self.corrected,
                                  None if self.plan.joints is None else self.plan.joints[k0]),
                functools.partial(streaming_robot, name, options, self.source, start, APPROACH_SPEED_M_S),
                sp.t[k0:], targets[k0:], self.rate_hz, cfg.lookahead_s, cfg.gain, cfg.rt_priority,
                host_timeout_s=cfg.host_timeout_s)
            period = 1.0 / cfg.monitor_hz
            last_t0, waited = float("nan"), -np.inf  # the schedule's origin, and when it last moved (the path waited)
            try:
                proc.heartbeat()
                while not proc.done(period):
                    proc.heartbeat()
                    self.hooks.beat()
                    if self.hooks.stop():
                        proc.cancel()
                    self.state.next = k0 + proc.sent
                    t0 = proc.t0
                    if proc.sent == 0 or not np.isfinite(t0):
                        continue  # still setting up (loading the twin, the approach move)
                    reading = self.inst.camera.read()
                    now = time.monotonic()
                    if np.isfinite(last_t0) and t0 != last_t0:
                        waited = now
                    last_t0 = t0
                    # the loop behind its schedule (the path is about to wait there) or the arm restarting after
                    # a wait: the arm is not where the schedule has it, a servo transient (counted, not tested)
                    behind = (now - t0) * self.rate_hz - proc.sent > PAUSE_AFTER_PERIODS + 1
                    if reading.ok and (behind or now - waited < SETTLE_S):
                        self.state.transient_refused += 1
                        continue
                    self._reading(reading, functools.partial(_on_host_clock, float(sp.t[k0]) - t0), learning,
                                  residuals)
                # the approach move and the twin's loading come first: bounded by the path's own duration
                rep = proc.result(timeout=60.0 + float(sp.t[-1] - sp.t[k0]))
            finally:
                proc.kill()
                self.proc = None
        finally:
            robot.activate()
        return rep

    def _reading(self, reading: RigReading, path_time: Callable[[RigReading], float], learning: bool,
                 residuals: list[tuple[float, np.ndarray]]) -> None:
        """One camera reading of the moving arm: placed on the path's clock, compared, tested."""
        st, cfg = self.state, self.cfg
        if not reading.ok or reading.point is None:
            self.hooks.refused(reading)
            return
        s = path_time(reading)
        cmp = compare_at(self.reference, s, cfg.u_time_s, self.u_reading, cfg.max_timing_ratio)
        if not cmp.ok:
            if "outside the path" in (cmp.refused or ""):
                st.outside_refused += 1
            else:
                st.timing_refused += 1
                log.info("reading refused: %s", cmp.refused)
            return
        k = min(int(np.searchsorted(self.plan.sp.t, s)), self.plan.n - 1)
        if not self.settled[k] or s < self._pass_t0 + SETTLE_S:  # a resumed pass starts at speed from rest
            st.transient_refused += 1
            return
        v = float(self.plan.sp.programmed[k])
        cond = None if self.plan.joints is None else Conditions(joints=self.plan.joints[k])
        u_extra = cmp.u_timing if self.lag is None else np.sqrt(cmp.u_timing ** 2 + self.u_lag ** 2)
        chk = self.hooks.test(cmp.commanded, v, reading.point, cond, s, u_extra, not learning)
        if chk is None:
            return
        if learning:
            st.learning_readings += 1
            residuals.append((s, chk.diff - chk.predicted))
        else:
            st.tested += 1

    def _learn(self, residuals: list[tuple[float, np.ndarray]]) -> None:
        """The lag from a learning pass's residuals: an arm lagging by a along the path shows
        e_MVS larger by a c' (GL), so the Eq. 17 residual diff - pred is -(a c' + b c'')."""
        if len(residuals) < MIN_LAG_READINGS:
            log.warning("the servo lag is not learnt: %d readings of the moving arm in the learning pass (need %d); "
                        "the next pass learns again", len(residuals), MIN_LAG_READINGS)
            return
        s = np.array([r[0] for r in residuals])
        rho_robot = np.array([r[1] for r in residuals]) @ self.twin.T_rdk.R  # GL -> robot axes (R^T rho)
        measured = self.reference.sample(self.reference.p, s) + rho_robot
        order = np.argsort(s)
        self.lag = estimate_lag(self.reference, s[order], measured[order])
        self.state.lag = self.lag.to_dict()
        ratio = self.u_lag / float(np.max(self.u_reading))
        if ratio > LAG_WARN_RATIO:  # the test of the moving arm is that much less sensitive than a static one's
            self.state.lag["warning"] = (
                f"the lag model leaves {1e3 * self.lag.rms_after_m:.3f} mm (RMS) unexplained, {ratio:.1f} x Eq. 17's "
                "own uncertainty: the moving arm is tested that much less sharply; slow the path, raise the servo's "
                "gain or look-ahead smoothing, or check the camera's timing (stream.u_time_s)")
            log.warning("%s", self.state.lag["warning"])
        log.warning("servo lag learnt from %d readings: %.2f +- %.2f ms (RMS %.3f -> %.3f mm); later passes are "
                    "compensated", self.lag.n, 1e3 * self.lag.tau_s, 1e3 * self.lag.u_tau_s,
                    1e3 * self.lag.rms_before_m, 1e3 * self.lag.rms_after_m)

    def restore(self, stored: dict | None) -> int:
        """Take back the resume point and the learnt lag a previous run of the same path stored.

        Parameters
        ----------
        stored : dict or None
            The stored `StreamState.to_dict()`, None when there is none.

        Returns
        -------
        int
            The set-point the next pass starts at; 0 when the stored state is of another path
            (file or length differ) or none.
        """
        st = self.state
        if not stored or stored.get("file") != st.file or stored.get("n") != st.n:
            return 0
        if self.cfg.lag == "learn" and stored.get("lag"):
            try:
                self.lag = LagEstimate.from_dict(stored["lag"])
                st.lag = self.lag.to_dict()
            except (KeyError, TypeError, ValueError) as exc:
                log.warning("the stored servo lag is unreadable (%s): learnt again", exc)
        k = int(stored.get("next", 0))
        if 0 < k < st.n:
            log.warning("the last run of this path stopped before %s: resuming there", self.plan.where(k))
            st.next, st.rerun_from = k, " (where the last run stopped)"
            return k
        return 0

    def resume_point(self, position: np.ndarray | None, k0: int, k_stop: int) -> int:
        """Where the next pass starts after a stop: the set-point of the stretch k0 .. k_stop
        whose command is nearest the arm.

        Parameters
        ----------
        position : ndarray or None
            (3,) m, where the arm stands (the controller's TCP); None when unknown.
        k0 : int
            The stopped pass's first set-point.
        k_stop : int
            The first set-point not sent.

        Returns
        -------
        int
            The set-point to resume at; `k_stop` when the position is unknown or not finite.
        """
        if position is None or not np.all(np.isfinite(position)) or k_stop <= k0:
            return k_stop
        d = np.linalg.norm(self.plan.commands[k0:k_stop + 1] - position, axis=1)
        return k0 + int(np.argmin(d))

    def cancel(self) -> None:
        """Ask a streaming process's pass to stop before its next send (any thread; no wait)."""
        if self.proc is not None:
            self.proc.cancel()


def _on_host_clock(offset: float, reading: RigReading) -> float:
    """A reading's mid-exposure on the host's monotonic clock (its receipt when not stated) plus
    `offset`: the pass's first set-point's path time minus its scheduled host time."""
    mid = reading.quality.get("mid_exposure_host_s")
    return offset + (float(mid) if mid is not None else float(reading.host_time))


def check_streaming_robot(name: str, source: str) -> None:
    """Check on its class, before anything is opened, that the robot driver `name` streams
    set-points (drivers.base.SetpointStreamer).

    Parameters
    ----------
    name : str
        `drivers.robot.kind`.
    source : str
        Names the runtime config in errors.

    Raises
    ------
    ConfigError
        The driver is unknown or does not stream set-points.
    """
    cls = registry.driver_class("robot", name, source=source, key="drivers.robot.kind")
    if not all(callable(getattr(cls, m, None)) for m in ("start_stream", "stream", "stop_stream", "stream_status")):
        raise ConfigError(source, "drivers.robot.kind", name, "a robot driver that streams set-points "
                          "(drivers.base.SetpointStreamer: the simulated and ur_rtde drivers do) for path.kind 'path'")


__all__ = ["PassHooks", "PathPlan", "PathStreamer", "StreamCell", "StreamState", "check_streaming_robot",
           "path_corrector", "plan_path", "streaming_robot"]
