"""The streaming loop: a path's set-points corrected and handed to the controller at its rate.

`run_stream` is the loop itself: set-point k is sent at its scheduled time t0 + k / rate (an
absolute schedule: a late tick does not shift the ones after it), and set-point k + 1 is corrected
right after, in the slack before its own time, so the correction's cost never delays a send. The
wait is a sleep to `spin_s` before the deadline and then a spin on the monotonic clock (a sleep
alone wakes 0.05-1 ms late); the garbage collector is held off while it runs (a collection is a
pause of milliseconds). Nothing in the loop touches the store, the bus or the camera: the caller
gets the report, and a `progress` callable (a shared counter, never blocking) if it wants one.

`StreamProcess` runs the loop in its own process, so the GIL of the daemon (its bus, store and
camera threads) cannot stall it: the child builds the corrector and the driver from picklable
factories, asks for real-time scheduling (SCHED_FIFO, when the user may: `realtime` in the report
says whether it got it; see docs/streaming.md for granting it), streams, and sends the report
back. Its progress (set-points sent) is a shared integer the parent reads without a lock.
More, and the benchmark: docs/streaming.md ("The streaming loop"). Units: SI (m, s).
"""
from __future__ import annotations

import contextlib
import gc
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.base import WatchdogStop
from dt_kernel.errors import DriverError, TwinError

Corrector = Callable[[np.ndarray, float], np.ndarray]  # (target m, t s) -> command m


@dataclass
class StreamReport:
    """What a streamed path did. Times in ms or us as named; `lateness_*`: send time minus its
    scheduled time; `jitter_*`: the period between two sends minus the nominal period."""

    target_hz: float
    n_planned: int
    n_sent: int
    rate_hz: float  # set-points sent per second of the stream's duration
    lateness_p99_ms: float
    lateness_max_ms: float
    jitter_p99_ms: float
    jitter_max_ms: float
    overruns: int  # ticks that started more than one period after their scheduled time
    correction_us_mean: float
    correction_us_p99: float
    send_us_p99: float
    stopped: str = ""  # why the stream ended early ("" when every set-point was sent)
    realtime: bool = False  # the loop ran with real-time scheduling
    pauses: int = 0  # ticks so late that the path waited at the set-point (the schedule moved on by the delay)
    pause_max_ms: float = 0.0  # the longest of those waits
    skipped: int = 0  # set-points not sent: the host sent every m-th while a tick took longer than a period
    degraded: str = ""  # what the host could not keep and what the loop did instead, in words ("" when nothing)
    host_stalled: bool = False  # the stream ended because the host stalled (refused right after a long wait)
    host_gap_max_ms: float = float("nan")  # the longest silence of the daemon seen (StreamProcess with host_timeout_s)
    commands: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)  # (n_sent, 3) m, NaN: skipped
    sent_at: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # (n_sent,) s from t0, NaN: skipped

    def to_dict(self) -> dict[str, Any]:
        """The figures as a dict, without the arrays `commands` and `sent_at`."""
        return {k: v for k, v in self.__dict__.items() if k not in ("commands", "sent_at")}


@contextlib.contextmanager
def _gc_held() -> Iterator[None]:
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _p99(x: np.ndarray) -> float:
    return float(np.percentile(x, 99)) if x.size else float("nan")


PAUSE_AFTER_PERIODS = 2.0  # a tick later than this many periods: the path waits at its set-point (docs/streaming.md)
STRIDE_MAX = 8  # at most every 8th set-point while the host is slow (within the controller's watchdog)
_COST_TICKS = 8  # a tick's cost: the median of the last 8 (a one-off stall is a wait, not a slow host)


def run_stream(times: np.ndarray, targets: np.ndarray, correct: Corrector, driver: Any, rate_hz: float,
               lookahead_s: float = 0.1, gain: float = 300.0, spin_s: float = 3e-4,
               progress: Callable[[int], None] | None = None, clock: Callable[[], float] = time.perf_counter,
               paced: bool = True, started: Callable[[float], None] | None = None,
               cancelled: Callable[[], str] | None = None, adapt: bool = True) -> StreamReport:
    """Stream `targets` (n, 3), m, meant for `times` (n,), s, each corrected by `correct`, to a
    driver that declares drivers.base.SetpointStreamer, at `rate_hz` (the controller's rate: the
    set-points must be on that grid). `paced=False` sends as fast as the loop can (the baseline a
    benchmark sets the paced rate against). A DriverError from the driver (protective stop, the
    controller's watchdog) ends the stream early with its reason in `stopped`. `started(t0)` is
    told the schedule's origin on `clock` (set-point k is due at t0 + k / rate_hz) before the first
    send, and again whenever the path waited (below); `cancelled()`, checked before every send,
    returns why the host ends the stream ("" to go on): both are a shared value's read or write,
    never a wait. Runs on the caller's thread, with the garbage collector held off; the driver's
    `stop_stream` is called however it ends.

    When the host cannot keep the rate (`adapt`, paced): a tick more than PAUSE_AFTER_PERIODS
    late (the process was not scheduled) is sent late and the schedule moves on by the delay (the
    path waits at that set-point: catching up would make the target jump by v times the delay);
    while a tick's work (send and correction) takes longer than a period, the loop sends the
    set-point due when it is done, skipping the ones between (the path keeps its time, the
    controller holds each set-point for the cycles between). `degraded` says what it did and why.

    Parameters
    ----------
    times : ndarray
        (n,) s, the path time each target is meant for.
    targets : ndarray
        (n, 3) m, robot frame.
    correct : callable
        `(target m, t s) -> command m`, called once per set-point sent, in the slack before it.
    driver : SetpointStreamer
        An active robot driver that streams set-points.
    rate_hz : float
        The controller's rate, Hz.
    lookahead_s : float
        The servo's look-ahead, s (passed to `start_stream`).
    gain : float
        The servo's gain (passed to `start_stream`).
    spin_s : float
        How long before a deadline the sleep ends and the spin starts, s.
    progress : callable, optional
        `progress(k)` after each send: k set-points passed (must not block).
    clock : callable
        The schedule's clock, s (`time.perf_counter`; the streaming process uses `time.monotonic`).
    paced : bool
        False: send as fast as the loop can (lateness and jitter are then NaN).
    started : callable, optional
        `started(t0)` once the schedule's origin is fixed, and after each wait.
    cancelled : callable, optional
        Why to stop now ("" to go on), checked before every send.
    adapt : bool
        Wait and skip when the host cannot keep the rate (False: every set-point, late or not).

    Returns
    -------
    StreamReport
        What was sent, when, and at what cost; `stopped` says why it ended early.

    Raises
    ------
    TwinError
        `times` and `targets` disagree in length or are empty. A DriverError of `start_stream` or
        an exception of `correct` propagates; one of `stream` ends the stream early instead.
    """
    times, targets = np.asarray(times, dtype=float), np.asarray(targets, dtype=float)
    n = times.size
    if targets.shape != (n, 3) or n == 0:
        raise TwinError(f"a stream needs n times and n x 3 targets, got {times.shape} and {targets.shape}")
    period = 1.0 / rate_hz
    adapt = adapt and paced
    commands = np.full((n, 3), np.nan)
    lateness, sent_at, corr_ns, send_ns = (np.full(n, np.nan) for _ in range(4))
    stopped, k, host_stalled = "", 0, False
    waits: list[tuple[int, float]] = []  # (set-point, s) where the path waited
    strides: list[tuple[int, int, float]] = []  # (set-point, stride, tick s) where the loop skipped
    # The first set-point is corrected before the controller's program starts: its watchdog counts
    # from start_stream, and a first correction (cold caches, a loaded host) can outlast it.
    c0 = time.perf_counter_ns()
    commands[0] = correct(targets[0], times[0])
    corr_ns[0] = time.perf_counter_ns() - c0
    try:
        with _gc_held():  # the collection before the program starts, not between its start and the first send
            driver.start_stream(rate_hz, lookahead_s, gain)
            t0 = t_first = clock() + 0.5 * period  # the controller's watchdog counts from its program's start
            if started is not None:
                started(t0)
            ticks = np.zeros(_COST_TICKS)  # the last ticks' work (send, next correction), s
            while True:
                due = t0 + k * period
                why = cancelled() if cancelled is not None else ""
                if why:
                    stopped = f"set-point {k + 1} of {n} not sent: {why}"
                    break
                if paced:
                    while (left := due - clock()) > spin_s:
                        time.sleep(left - spin_s)
                    while clock() < due:
                        pass
                now = clock()
                if adapt and now - due > PAUSE_AFTER_PERIODS * period:
                    waits.append((k, now - due))
                    t0, due = t0 + (now - due), now
                    if started is not None:
                        started(t0)
                s0 = time.perf_counter_ns()
                try:
                    driver.stream(commands[k], times[k])
                except DriverError as exc:
                    stopped = f"set-point {k + 1} of {n} refused: {exc}"
                    if isinstance(exc, WatchdogStop):  # the controller gave up on a host that stalled: not the cell
                        host_stalled = True
                        if waits and k - waits[-1][0] <= 0.5 * rate_hz:
                            stopped += (f" (the streaming process had not been scheduled for "
                                        f"{1e3 * waits[-1][1]:.0f} ms before it)")
                    break
                send_ns[k] = time.perf_counter_ns() - s0
                sent_at[k], lateness[k] = now, now - due
                if progress is not None:
                    progress(k + 1)
                if k == n - 1:
                    k = n
                    break
                cost = float(np.median(ticks))
                step = min(int(np.ceil(cost / period)), STRIDE_MAX) if adapt and cost > period else 1
                nxt = min(k + step, n - 1)
                if step > 1:
                    strides.append((k + 1, nxt - k, cost))
                c0 = time.perf_counter_ns()
                commands[nxt] = correct(targets[nxt], times[nxt])
                corr_ns[nxt] = time.perf_counter_ns() - c0
                ticks[k % _COST_TICKS] = (send_ns[k] + corr_ns[nxt]) * 1e-9
                k = nxt
    finally:
        with contextlib.suppress(DriverError):
            driver.stop_stream()
    rep = _stream_report(rate_hz, n, k, commands, sent_at - t_first, lateness, corr_ns, send_ns, stopped, paced,
                  waits, strides)
    rep.host_stalled = host_stalled
    return rep


def _stream_report(rate_hz: float, n: int, k: int, commands: np.ndarray, sent_at: np.ndarray, lateness: np.ndarray,
            corr_ns: np.ndarray, send_ns: np.ndarray, stopped: str, paced: bool,
            waits: list[tuple[int, float]], strides: list[tuple[int, int, float]]) -> StreamReport:
    """The report of a stream that passed k of n set-points."""
    period = 1.0 / rate_hz
    idx = np.flatnonzero(np.isfinite(sent_at[:k]))  # the set-points sent
    at, late = sent_at[idx], lateness[idx]
    # a send's gap minus the periods it was meant to span (a skipped set-point's included)
    jit = np.abs(np.diff(at) - np.diff(idx) * period) if paced else np.zeros(0)
    span = at[-1] - at[0] if idx.size > 1 else float("nan")
    corr = corr_ns[:k][np.isfinite(corr_ns[:k])]
    said = []
    if waits:
        w = max(x[1] for x in waits)
        said.append(f"the path waited {len(waits)} time(s), up to {1e3 * w:.0f} ms, first at set-point "
                    f"{waits[0][0] + 1} of {n}: the streaming process was not scheduled for that long (more than "
                    f"{PAUSE_AFTER_PERIODS:g} periods of {1e3 * period:g} ms)")
    skipped = int(k - idx.size) if k > 0 else 0
    if strides:
        m, c = max(x[1] for x in strides), max(x[2] for x in strides)
        said.append(f"{skipped} of {n} set-points skipped from set-point {strides[0][0] + 1} on (every {m}th at "
                    f"most): a tick took up to {1e3 * c:.1f} ms, longer than the {1e3 * period:g} ms period; the path "
                    "kept its time at a lower rate")
    return StreamReport(
        target_hz=float(rate_hz), n_planned=int(n), n_sent=int(k),
        rate_hz=float((idx.size - 1) / span) if idx.size > 1 and span > 0 else float("nan"),
        lateness_p99_ms=1e3 * _p99(np.abs(late)) if paced else float("nan"),
        lateness_max_ms=1e3 * float(np.max(np.abs(late))) if paced and idx.size else float("nan"),
        jitter_p99_ms=1e3 * _p99(jit), jitter_max_ms=1e3 * float(jit.max()) if jit.size else float("nan"),
        overruns=int(np.sum(late > period)) if paced else 0,
        correction_us_mean=float(corr.mean() / 1e3) if corr.size else float("nan"),
        correction_us_p99=_p99(corr) / 1e3, send_us_p99=_p99(send_ns[idx]) / 1e3,
        stopped=stopped, pauses=len(waits), pause_max_ms=1e3 * max((x[1] for x in waits), default=0.0),
        skipped=skipped, degraded="; ".join(said), commands=commands[:k].copy(), sent_at=sent_at[:k].copy())


def _realtime(priority: int) -> bool:
    """SCHED_FIFO for this process when the user may (root, CAP_SYS_NICE or an rtprio limit)."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (PermissionError, OSError):
        return False


def _child(conn, sent, t0, cancel, beat, host_timeout_s, make_corrector, make_driver, times, targets, rate_hz,
           lookahead_s, gain, rt_priority, paced) -> None:  # pragma: no cover (runs in the child; tested through it)
    parent = os.getppid()
    try:
        correct, driver = make_corrector(), make_driver()
        rt = _realtime(rt_priority)  # after the set-up: loading a model at real-time priority would starve the host

        def progress(k: int) -> None:
            sent.value = k  # an aligned store to shared memory: no lock, never blocks

        def started(at: float) -> None:
            t0.value = at

        gap = [float("nan")]  # the longest silence of the daemon seen, s

        def cancelled() -> str:
            # a shared value, a clock and a system call: about a microsecond, never a wait
            if cancel.value:
                return "the host stopped the stream"
            if os.getppid() != parent:
                return "the daemon that started the stream is gone"
            last = beat.value
            if last > 0:
                quiet = time.monotonic() - last
                gap[0] = quiet if not quiet <= gap[0] else gap[0]
                if host_timeout_s is not None and quiet > host_timeout_s:
                    return (f"the daemon gave no sign for {quiet:.2f} s (host_timeout_s {host_timeout_s:g}): the "
                            "moving arm is not monitored")
            return ""

        try:
            # time.monotonic: CLOCK_MONOTONIC, the clock the parent reads too (a reading's host time)
            rep = run_stream(times, targets, correct, driver, rate_hz, lookahead_s, gain, progress=progress,
                             clock=time.monotonic, paced=paced, started=started, cancelled=cancelled)
        finally:
            with contextlib.suppress(Exception):
                driver.close()
        rep.realtime, rep.host_gap_max_ms = rt, 1e3 * gap[0]
        _report(conn, ("ok", rep), rep.stopped or f"{rep.n_sent} set-points sent")
    except BaseException as exc:  # noqa: BLE001 (reported to the parent, which raises it)
        _report(conn, ("error", f"{type(exc).__name__}: {exc}"), f"{type(exc).__name__}: {exc}")
    finally:
        conn.close()


def _report(conn, message: tuple[str, Any], what: str) -> None:
    """Send the child's report to the daemon; when the daemon is gone (killed: its end of the pipe
    closed), say so in one line on stderr and end quietly, not with a BrokenPipe traceback from
    each send."""
    try:
        conn.send(message)
    except (BrokenPipeError, ConnectionResetError, EOFError, OSError):
        import sys

        print(f"dt stream (pid {os.getpid()}): the daemon is gone, its report not delivered ({what})",
              file=sys.stderr, flush=True)


class StreamProcess:
    """`run_stream` in its own (spawned) process. `make_corrector` and `make_driver` are
    picklable callables (module-level functions or functools.partial of them) that build the
    corrector and the active streaming driver in the child. `sent` is the progress and `t0` the
    schedule's origin on CLOCK_MONOTONIC (time.monotonic here too: set-point k is due at t0 + k /
    rate_hz; NaN until the first is due), readable at any time; `cancel()` asks the loop to stop
    before its next send (the driver's stop_stream then stops the arm), and so does the loop by
    itself when the parent is gone or, with `host_timeout_s`, has not called `heartbeat()` for that
    long (a SIGSTOPped or frozen daemon no longer monitors the arm); `result(timeout)` waits for
    the report (TwinError if the child failed or did not answer in time: it is then killed)."""

    def __init__(self, make_corrector: Callable[[], Corrector], make_driver: Callable[[], Any],
                 times: np.ndarray, targets: np.ndarray, rate_hz: float, lookahead_s: float = 0.1,
                 gain: float = 300.0, rt_priority: int = 10, paced: bool = True, host_timeout_s: float | None = None):
        ctx = mp.get_context("spawn")
        self._sent = ctx.Value("q", 0, lock=False)
        self._t0 = ctx.Value("d", float("nan"), lock=False)
        self._cancel = ctx.Value("b", 0, lock=False)
        self._beat = ctx.Value("d", 0.0, lock=False)
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child, name="dt-stream", daemon=True, args=(
            send, self._sent, self._t0, self._cancel, self._beat, host_timeout_s, make_corrector, make_driver,
            np.asarray(times, dtype=float), np.asarray(targets, dtype=float), rate_hz, lookahead_s, gain, rt_priority,
            paced))
        self._proc.start()
        send.close()

    @property
    def sent(self) -> int:
        """Set-points sent so far (read without a lock, any thread)."""
        return int(self._sent.value)

    @property
    def t0(self) -> float:
        """The schedule's origin on CLOCK_MONOTONIC, s; NaN until the first set-point is due."""
        return float(self._t0.value)

    def cancel(self) -> None:
        """Ask the loop to stop before its next send (no wait; any thread, a signal handler too)."""
        self._cancel.value = 1

    def heartbeat(self) -> None:
        """The parent is alive and monitoring: with `host_timeout_s`, the loop stops the stream
        when no heartbeat came for that long (a stalled or frozen daemon: the moving arm is not
        monitored any more); the first heartbeat arms the check."""
        self._beat.value = time.monotonic()

    def done(self, timeout: float = 0.0) -> bool:
        """Whether the report is ready (or the child is gone).

        Parameters
        ----------
        timeout : float
            Wait at most this long, s.

        Returns
        -------
        bool
            True once the report can be read with `result` (or the child is gone).
        """
        return bool(self._recv.poll(timeout)) or not self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        """The streaming process's id (a supervisor's watchdog, or a test stalling it)."""
        return self._proc.pid

    def result(self, timeout: float) -> StreamReport:
        """The child's report, waiting for it.

        Parameters
        ----------
        timeout : float
            Wait at most this long, s; then the child is killed.

        Returns
        -------
        StreamReport
            The report, `realtime` saying whether the child got SCHED_FIFO.

        Raises
        ------
        TwinError
            No report within `timeout` (the child is killed), the child died, or it failed
            (its exception's type and message).
        """
        if not self._recv.poll(timeout):
            self._proc.kill()
            self._proc.join(5)
            raise TwinError(f"the streaming process gave no report within {timeout} s (killed;"
                            f" {self.sent} set-points had been sent)")
        try:
            status, payload = self._recv.recv()
        except EOFError:
            self._proc.join(5)
            raise TwinError(f"the streaming process died (exit code {self._proc.exitcode}) after"
                            f" {self.sent} set-points") from None
        self._proc.join(5)
        if status != "ok":
            raise TwinError(f"the streaming process failed: {payload}")
        return payload

    def kill(self) -> None:
        """Kill the child if it still runs and reap it (waits at most 5 s)."""
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(5)
