"""The daemon's one supervisor: when the arm may move, whether the correction is trusted, when
refusals, driver faults or a silent camera halt, and what the status is; the point loop
(`Daemon.tick`) and the path loop (`Daemon._run_path`) ask it the same questions.

Halts: `halt.after_refused` commands refused in a row, `halt.after_driver_faults` driver faults
in a row, no MVS reading tested for `halt.after_camera_refused_s`, or `out_of_control` /
`rereference_offered` / `maintenance_requested` under `halt.on_untrusted: halt` (sticky: only the operator's 'done'
leaves it). A camera halt stands the arm and probes the camera once a step; the first accepted
reading resumes. The point loop retries after a non-sticky halt (the first command that goes
through resumes); a path waits for the operator after any halt.
"""
from __future__ import annotations

import enum
import logging
import threading
from collections.abc import Callable

from drivers.base import RigReading
from dt_kernel.errors import DriverError
from dt_runtime.service.counters import Counters
from dt_runtime.service.escalation import Escalator
from dt_runtime.service.runtime_config import HaltConfig
from dt_runtime.service.store import StoreError

log = logging.getLogger("dt.run")

#: States in which the twin's correction is not trusted (`halt.on_untrusted` says what is done).
UNTRUSTED = ("out_of_control", "rereference_offered", "maintenance_requested")


class Step(enum.Enum):
    """What the loop does next."""

    MOVE = "move"  # command the next target (a point, or a pass of the path)
    WAIT = "wait"  # halted until the operator's 'done': the arm stands
    PROBE = "probe"  # halted for the camera: the arm stands, the camera is read once


class Supervisor:
    """The halt / trust / camera policy of one daemon over its `escalator` and `counters`.

    Parameters
    ----------
    halt : HaltConfig
        The runtime config's `halt` section.
    max_measurement_age_s : float
        How long before a command's arrival a reading may have been received and still be tested.
    escalator : Escalator
        The machine (its transitions are recorded and emitted by `service.paging`).
    counters : Counters
        The daemon's counters, written here for every refusal, fault and untested reading.
    now : callable
        The daemon's clock (s).
    stopping : threading.Event
        Set when the daemon stops.
    streaming : bool
        True for a path program: any halt waits for the operator.
    store_failing : callable
        True while the store's writes fail (the status is degraded).
    """

    def __init__(self, halt: HaltConfig, max_measurement_age_s: float, escalator: Escalator, counters: Counters,
                 now: Callable[[], float], stopping: threading.Event, *, streaming: bool,
                 store_failing: Callable[[], bool]):
        self.halt, self.max_age_s, self.escalator, self.counters = halt, max_measurement_age_s, escalator, counters
        self.now, self.stopping, self.streaming, self.store_failing = now, stopping, streaming, store_failing
        self.camera_halt = False  # halted because the camera gave no usable reading (resumes on one)

    # --- trust and the next step ---------------------------------------------------------------
    def trusted(self) -> bool:
        """The correction is trusted (not `out_of_control`, `rereference_offered` nor `maintenance_requested`:
        until re-referenced, a rigid shift of the set-up is not told apart from one of the arm's base)."""
        return self.escalator.state not in UNTRUSTED

    def corrects(self) -> bool:
        """Commands are corrected: trusted, or `halt.on_untrusted: correct`."""
        return self.trusted() or self.halt.on_untrusted == "correct"

    def _halts_untrusted(self) -> bool:
        return not self.trusted() and self.halt.on_untrusted == "halt"

    def next_step(self, t: float) -> Step:
        """Before a command (or a pass) at daemon time `t`: move, wait for the operator, or probe
        the camera. An untrusted correction under `halt.on_untrusted: halt` halts (sticky) here.

        Parameters
        ----------
        t : float
            Daemon time, s.

        Returns
        -------
        Step
            What the loop does now.
        """
        esc = self.escalator
        if self._halts_untrusted():
            esc.halt(f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)", t, sticky=True)
        if self.camera_halt and esc.state != "halted":  # left by the operator's 'done': time afresh
            self.camera_halt, self.counters.camera_refused_since = False, None
        if self.camera_halt:
            return Step.PROBE
        if esc.state == "halted" and (esc.halt_sticky or self.streaming):
            return Step.WAIT
        return Step.MOVE

    def pass_stop(self) -> str:
        """Why a pass must end now ('' to go on): the daemon stopping, or a halt (the camera's:
        the arm must not move unmonitored; a sticky one)."""
        if self.stopping.is_set():
            return "the daemon is stopping"
        esc = self.escalator
        if esc.state == "halted":
            return f"halted: {esc.halt_reason}"
        if self._halts_untrusted():
            return f"{esc.state}: the correction is not trusted (halt.on_untrusted: halt)"
        return ""

    # --- commands ------------------------------------------------------------------------------
    def refused(self, exc: Exception, t: float) -> None:
        """A command the correction refused (the robot not moved): counted and logged; after
        `halt.after_refused` in a row, halt.

        Parameters
        ----------
        exc : Exception
            The refusal (a CorrectionFault).
        t : float
            Daemon time, s.

        Raises
        ------
        StoreError
            The halt could not be recorded (the machine stays; the next refusal tries again).
        """
        n = self.counters
        n.refused += 1
        n.refused_in_row += 1
        n.last_problem = f"command refused: {exc}"
        log.error("command refused, robot not moved: %s", exc)
        if n.refused_in_row >= self.halt.after_refused:
            self.escalator.halt(f"every command refused for {n.refused_in_row} ticks; last: {exc}", t)

    def moved(self, t: float) -> None:
        """A command went through: the runs of refusals and faults end, a (non-sticky) halt resumes.

        Parameters
        ----------
        t : float
            Daemon time, s.

        Raises
        ------
        StoreError
            The resume could not be recorded.
        """
        n = self.counters
        n.refused_in_row = n.driver_faults_in_row = 0
        if self.escalator.state == "halted":
            self.escalator.resume(t)

    def pass_done(self, n_sent: int, corrected: bool) -> None:
        """A pass ended: its set-points counted, the run of driver faults ends.

        Parameters
        ----------
        n_sent : int
            Set-points it sent.
        corrected : bool
            Whether they were corrected (else also counted as uncorrected).
        """
        n = self.counters
        n.ticked(n_sent)
        if not corrected:
            n.uncorrected += n_sent
        n.driver_faults_in_row = 0

    def pass_stopped(self, why: str) -> None:
        """A pass ended early: a sticky halt, until the operator's 'done'.

        Parameters
        ----------
        why : str
            Where and why it stopped, and what the operator does (the halt's reason).

        Raises
        ------
        StoreError
            The halt could not be recorded.
        """
        self.counters.last_problem = why
        log.error("%s", why)
        self.escalator.halt(why, self.now(), sticky=True)

    def driver_fault(self, exc: DriverError) -> None:
        """A driver failed: counted and logged; after `halt.after_driver_faults` in a row, halt
        (not while stopping; a halt the store cannot record is logged and tried at the next fault).

        Parameters
        ----------
        exc : DriverError
            The driver's error.
        """
        n = self.counters
        n.driver_faults += 1
        n.driver_faults_in_row += 1
        n.last_problem = f"driver fault: {exc}"
        log.error("driver fault: %s", exc)
        if n.driver_faults_in_row >= self.halt.after_driver_faults and not self.stopping.is_set():
            try:
                self.escalator.halt(f"driver fault {n.driver_faults_in_row} times in a row: {exc}", self.now())
            except StoreError as store_exc:
                log.error("halt not recorded, retried on the next fault: %s", store_exc)

    # --- the camera ----------------------------------------------------------------------------
    def usable(self, reading: RigReading, arrived: float) -> bool:
        """Whether a point program's reading may be tested: the camera gave a point, received
        at most `max_measurement_age_s` before the command arrived. A refused or stale reading is
        counted and may halt (`untested`).

        Parameters
        ----------
        reading : RigReading
            The camera's reading after the move.
        arrived : float
            When the command arrived, host monotonic clock, s.

        Returns
        -------
        bool
            True if it may be tested.
        """
        if not reading.ok or reading.point is None:
            self.camera_refused(reading)
            return False
        self.accepted()
        age = arrived - reading.host_time
        if age > self.max_age_s:
            n = self.counters
            n.stale_measurements += 1
            n.last_problem = (f"stale measurement: received {age * 1e3:.0f} ms before the command arrived "
                              f"(max_measurement_age_s {self.max_age_s})")
            log.warning("MVS reading refused, not tested: %s", n.last_problem)
            self.untested(n.last_problem)
            return False
        return True

    def accepted(self) -> None:
        """The camera gave a point: its run of refusals ends."""
        self.counters.mvs_refused_in_row = 0

    def camera_refused(self, reading: RigReading) -> None:
        """A reading the camera driver refused: nothing to test; counted (degraded while it lasts,
        a halt after `halt.after_camera_refused_s`).

        Parameters
        ----------
        reading : RigReading
            The refused reading (its `refused` says why).
        """
        n = self.counters
        n.mvs_refused += 1
        n.mvs_refused_in_row += 1
        n.last_problem = f"MVS refused: {reading.refused}"
        log.info("MVS refused: %s", reading.refused)
        self.untested(n.last_problem)

    def rejected(self, exc: Exception) -> None:
        """The monitor rejected a reading's value: not tested (`untested`).

        Parameters
        ----------
        exc : Exception
            The monitor's refusal (a CorrectionFault).
        """
        log.error("MVS value rejected: %s", exc)
        self.untested(f"MVS value rejected: {exc}")

    def tested(self) -> None:
        """A reading was tested: the camera's silence ends."""
        self.counters.camera_refused_since = None

    def untested(self, why: str) -> None:
        """A reading that could not be tested: after `halt.after_camera_refused_s` of nothing
        but these (daemon clock), halt (paged; the loop then stands the arm and probes the camera).

        Parameters
        ----------
        why : str
            Why it was not tested (in the halt's reason).

        Raises
        ------
        StoreError
            The halt could not be recorded.
        """
        n = self.counters
        t = self.now()
        if n.camera_refused_since is None:
            n.camera_refused_since = t
        limit = self.halt.after_camera_refused_s
        blind = t - n.camera_refused_since
        if blind >= limit and self.escalator.state != "halted":
            self.camera_halt = self.escalator.halt(
                f"no MVS reading tested for {blind:.1f} s (halt.after_camera_refused_s {limit:g} s); last: {why}", t)

    def probed(self, reading: RigReading, t: float) -> bool:
        """Halted for the camera: the probe's reading; an accepted one resumes the halt.

        Parameters
        ----------
        reading : RigReading
            The camera's reading.
        t : float
            Daemon time, s.

        Returns
        -------
        bool
            True if it was accepted (the halt resumed).

        Raises
        ------
        StoreError
            The resume could not be recorded.
        """
        n = self.counters
        if reading.ok:
            self.camera_halt, n.camera_refused_since, n.mvs_refused_in_row = False, None, 0
            self.escalator.resume(t)
            log.warning("the camera gives readings again: resumed")
            return True
        n.last_problem = f"MVS refused: {reading.refused}"
        return False

    # --- status --------------------------------------------------------------------------------
    def status(self) -> tuple[str, str | None]:
        """(running | degraded | halted, why): cheap, no I/O (the loop asks every tick)."""
        esc = self.escalator
        if esc.state == "halted":
            return "halted", esc.halt_reason
        if self.store_failing():
            return "degraded", "store writes failing"
        if self.counters.in_trouble():
            return "degraded", self.counters.last_problem
        if not self.trusted() and self.halt.on_untrusted == "uncorrected":
            return "degraded", f"{esc.state}: commands sent uncorrected"
        return "running", None
