"""Escalation of in-service Eq. 17 t-test outcomes to a maintenance request: the state machine
(`EscalationMachine`: nominal, suspect, out_of_control, rereference_offered,
maintenance_requested, halted), the `Escalator` that feeds it the window and CUSUM statistics of
the failure indicator, and the false-alarm bounds of a configuration (`false_alarm_rates`).

Failures that are one rigid shift of the set-up (`analysis.deployment.rigid_shift` of the failing
readings) offer re-referencing (`rereference_offered`) before they page; a change that is not
rigid pages as before.

States, rules, episodes and the false-alarm numbers: docs/service.md ("The escalation machine").
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from fractions import Fraction
from typing import Any, Literal

import numpy as np
from pydantic import model_validator
from statemachine import State, StateMachine
from statemachine.exceptions import TransitionNotAllowed

from dt_kernel.config import Frozen
from dt_kernel.errors import StateError

# 2 added halted, halt_reason, halt_sticky, halted_from, episode; 3 the re-referencing offer (1, 2 still load)
SNAPSHOT_VERSION = 3

#: States that page: entering one opens an episode whose maintenance requests must be delivered.
PAGING = ("maintenance_requested", "halted")

TransitionCallback = Callable[[str, str, dict[str, Any], float], None]
# one tested reading: position, difference from the prediction, u (m, GL axes) and the joint angles (rad) or None
Reading = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]
Jacobian = Callable[[np.ndarray], np.ndarray]  # (n, dof) joint angles -> (n, 3, dof) position Jacobian, GL axes


class EscalationConfig(Frozen):
    """The `escalation` section of the runtime YAML (docs/service.md, "The escalation machine").

    `mode`: which statistic raises the alarm (`window`, `cusum`, `either`, `both`); `alpha`: the
    per-test significance level of the t-test feeding the machine; `window_n`, `window_k`,
    `suspect_k`: the window's length and the failures in it that alarm or raise suspicion;
    `cusum_k`, `cusum_h`, `suspect_h`: the CUSUM's reference value and its alarm and suspicion
    thresholds; `confirm_n`: further alarmed tests before out_of_control pages; `recover_passes`:
    passes in a row before suspect clears; `last_t_kept`: t values kept as evidence;
    `tests_per_day`: for `false_alarm_rates`; `rereference`: offer re-referencing instead of
    paging when the failing readings are one rigid shift of the set-up; `rereference_bound`:
    tests after such an offer before it pages anyway. Counts are tests, not seconds; an
    inconsistent or unbounded value raises ValueError (a ConfigError through dt_kernel.config).
    """

    mode: Literal["window", "cusum", "either", "both"] = "either"
    alpha: float = 0.05           # per-test significance level of the t-test feeding us
    window_n: int = 20
    window_k: int = 9
    suspect_k: int = 5
    cusum_k: float = 0.25
    cusum_h: float = 4.5
    suspect_h: float = 2.5
    confirm_n: int = 3
    recover_passes: int = 10
    last_t_kept: int = 5
    tests_per_day: float = 86_400.0   # for false_alarm_rates (1 test per second)
    # Failures that are one rigid shift of the set-up (a knocked camera rig, a re-mounted base):
    # offer re-referencing first; if it is not applied within `rereference_bound` tests while the
    # alarm goes on, page anyway (an offer never silences a fault for long).
    rereference: bool = True
    rereference_bound: int = 300

    @model_validator(mode="after")
    def _check(self) -> EscalationConfig:
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if not 1 <= self.suspect_k <= self.window_k <= self.window_n:
            raise ValueError("need 1 <= suspect_k <= window_k <= window_n")
        if not 0 < self.cusum_k < 1:
            raise ValueError("cusum_k must be in (0, 1) (failure indicator is 0 or 1)")
        if not 0 < self.suspect_h <= self.cusum_h:
            raise ValueError("need 0 < suspect_h <= cusum_h")
        if self.confirm_n < 0 or self.recover_passes < 1 or self.rereference_bound < 1:
            raise ValueError("need confirm_n >= 0, recover_passes >= 1 and rereference_bound >= 1")
        # Bounded counts: a typo such as confirm_n 1e9 would silently switch paging off.
        for key, value, most in (("window_n", self.window_n, 10_000), ("confirm_n", self.confirm_n, 1_000),
                                 ("recover_passes", self.recover_passes, 100_000),
                                 ("last_t_kept", self.last_t_kept, 1_000),
                                 ("rereference_bound", self.rereference_bound, 100_000)):
            if value > most:
                raise ValueError(f"{key} = {value} is above the allowed {most} (tests, not seconds)")
        if not (math.isfinite(self.cusum_h) and self.cusum_h <= 1_000):
            raise ValueError(f"cusum_h = {self.cusum_h} must be finite and <= 1000")
        return self


class EscalationMachine(StateMachine):
    """The states and the events between them (python-statemachine); `Escalator` sends the events."""

    nominal = State(initial=True)
    suspect = State()
    out_of_control = State()
    rereference_offered = State()
    maintenance_requested = State()

    raise_suspicion = nominal.to(suspect)
    clear = suspect.to(nominal)
    lose_control = suspect.to(out_of_control)
    regain = out_of_control.to(suspect) | rereference_offered.to(suspect)
    offer = out_of_control.to(rereference_offered)
    request = out_of_control.to(maintenance_requested) | rereference_offered.to(maintenance_requested)
    rereferenced = rereference_offered.to(nominal)
    halted = State()
    halt = (nominal.to(halted) | suspect.to(halted) | out_of_control.to(halted)
            | rereference_offered.to(halted) | maintenance_requested.to(halted))
    resume_nominal = halted.to(nominal)
    resume_suspect = halted.to(suspect)
    resume_out_of_control = halted.to(out_of_control)
    resume_rereference_offered = halted.to(rereference_offered)
    resume_maintenance_requested = halted.to(maintenance_requested)
    acknowledge = maintenance_requested.to(nominal) | halted.to(nominal)


STATES = ("nominal", "suspect", "out_of_control", "rereference_offered", "maintenance_requested", "halted")


class Escalator:
    """Feeds t-test outcomes to an `EscalationMachine` and keeps its statistics.

    Parameters
    ----------
    config : EscalationConfig, optional
        The thresholds (defaults if None).
    on_transition : callable, optional
        `on_transition(src, dst, evidence, t)`, called after every transition; if it raises,
        the machine is put back where it was and the exception propagates (the daemon records
        the transition in the store there: it counts only once recorded).
    jacobian : callable, optional
        The arm's position Jacobian at joint angles (`Jacobian`): with it a shift that one
        joint's zero offset explains as well is not offered (it pages: it may be the arm).
        Without it (or readings without joint angles) nothing is offered: a fitted shift alone
        cannot tell a knocked instrument from a changed arm.

    Not thread-safe: the daemon's loop alone feeds and moves it.
    """

    def __init__(self, config: EscalationConfig | None = None,
                 on_transition: TransitionCallback | None = None, jacobian: Jacobian | None = None):
        self.config = config or EscalationConfig()
        self.on_transition = on_transition
        self.jacobian = jacobian
        self.machine = EscalationMachine()
        self._reset_stats()
        self.n_seen = 0
        self.episode = 0  # paging episodes opened so far (entries into maintenance_requested or halted)
        self.halt_reason: str | None = None
        self.halt_sticky = False
        self.halted_from: str | None = None
        self.offer: dict[str, Any] | None = None  # the open re-referencing offer (its fitted shift)
        self.offered_at: int | None = None  # n_seen when it was made

    def _reset_stats(self) -> None:
        c = self.config
        self._window: deque[int] = deque(maxlen=c.window_n)
        self._readings: deque[Reading | None] = deque(maxlen=c.window_n)  # beside _window; not persisted
        self.cusum = 0.0
        self.consecutive_passes = 0
        self.confirm_count = 0
        self._last_t: deque[float | None] = deque(maxlen=c.last_t_kept)

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> str:
        """The machine's state: one of `STATES`."""
        return next(iter(self.machine.configuration)).id

    @property
    def window_failures(self) -> int:
        """Failures among the last `window_n` tests."""
        return sum(self._window)

    def _alarm(self) -> str | None:
        c = self.config
        w = self.window_failures >= c.window_k
        s = self.cusum >= c.cusum_h
        fired = {"window": w, "cusum": s, "either": w or s, "both": w and s}[c.mode]
        if not fired:
            return None
        return "both" if (w and s) else ("window" if w else "cusum")

    def _suspicious(self) -> bool:
        c = self.config
        return (self.window_failures >= c.suspect_k or self.cusum >= c.suspect_h
                or self._alarm() is not None)

    def evidence(self, rule: str | None = None) -> dict[str, Any]:
        """What a transition carries as its evidence (JSON-ready).

        Parameters
        ----------
        rule : str, optional
            The rule that fired (`window`, `cusum` or `both`), None for none.

        Returns
        -------
        dict
            Window failures and length, thresholds, CUSUM, mode, rule, confirmation count,
            passes in a row, the last t values and the number of tests seen.
        """
        c = self.config
        return {
            "window_failures": self.window_failures, "window_len": len(self._window),
            "window_n": c.window_n, "window_k": c.window_k,
            "cusum": round(self.cusum, 6), "cusum_h": c.cusum_h, "mode": c.mode,
            "rule": rule, "confirm_count": self.confirm_count,
            "consecutive_passes": self.consecutive_passes,
            "last_t": list(self._last_t), "n_seen": self.n_seen,
        }

    def evidence_of_halt(self) -> dict[str, Any]:
        """The halt's reason, whether it is sticky and the state it interrupted (None when not halted)."""
        return {"halt_reason": self.halt_reason, "halt_sticky": self.halt_sticky,
                "halted_from": self.halted_from}

    def _fire(self, event: str, t: float, rule: str | None, extra: dict[str, Any] | None = None,
              before: dict[str, Any] | None = None) -> None:
        """Move the machine and report it; put it back if the report raises (class docstring).
        `before`: the snapshot to return to, when the caller changed more than the state."""
        before = self.snapshot() if before is None else before
        src = self.state
        self.machine.send(event)
        if self.state in PAGING and src not in PAGING:
            self.episode += 1
        if self.on_transition is None:
            return
        try:
            self.on_transition(src, self.state, self.evidence(rule) | (extra or {}), t)
        except BaseException:
            self.restore(before)
            raise

    # ------------------------------------------------------------------ input
    def observe(self, passed: bool, t_value: float | None = None,
                t: float | None = None, reading: Reading | None = None) -> str:
        """Feed one t-test outcome; the transitions it fires are reported to `on_transition`.

        Parameters
        ----------
        passed : bool
            The test passed (p >= alpha).
        t_value : float, optional
            The test's t (kept as evidence; None or non-finite is kept as None).
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).
        reading : tuple, optional
            (position, difference, u, q): the reading's position, its measured-minus-predicted
            difference and Eq. 17's standard uncertainty per axis (m, GL axes), and the arm's
            joint angles (rad, or None). With enough failing ones in the window, an alarm that is
            one rigid shift of the set-up and no joint's offset offers re-referencing
            (`rereference_offered`) instead of paging (`shift`).

        Returns
        -------
        str
            The state after this test. While halted only the statistics move.

        Raises
        ------
        Exception
            Whatever `on_transition` raises (StoreError in the daemon); the machine is then
            where it was before the transition.
        """
        c = self.config
        t = float(self.n_seen if t is None else t)
        x = 0 if passed else 1
        self.n_seen += 1
        self._window.append(x)
        self._readings.append(reading)
        self.cusum = max(0.0, self.cusum + x - c.cusum_k)
        self.consecutive_passes = self.consecutive_passes + 1 if passed else 0
        self._last_t.append(None if t_value is None or not math.isfinite(t_value)
                            else round(float(t_value), 4))
        rule = self._alarm()
        state = self.state
        if state == "halted":  # statistics go on; the state waits for resume/acknowledge
            return state
        if state == "nominal":
            if self._suspicious():
                self._fire("raise_suspicion", t, rule)
                state = "suspect"
        elif state == "suspect":
            if not self._suspicious() and self.consecutive_passes >= c.recover_passes:
                self._fire("clear", t, rule)
                return self.state
        if state == "suspect" and rule is not None:
            self.confirm_count = 0
            self._fire("lose_control", t, rule)
            if c.confirm_n == 0:
                self._escalate(t, rule)
            return self.state
        if state == "out_of_control":
            if rule is None:
                self.confirm_count = 0
                self._fire("regain", t, rule)
            else:
                self.confirm_count += 1
                if self.confirm_count >= c.confirm_n:
                    self._escalate(t, rule)
        elif state == "rereference_offered":
            self._offered(t, rule)
        return self.state

    # ------------------------------------------------------------------ re-referencing
    def shift(self) -> dict[str, Any] | None:
        """Whether the failing readings of the window are one rigid shift of the set-up
        (`analysis.deployment.rigid_shift`) that no single joint's zero offset explains as well
        (`analysis.deployment.joint_alternative`), JSON-ready: `rigid`, `offer` (rigid, and the
        arm ruled out), `translation_mm`, `rotation_mrad`, `p_before`, `p_after`, `n`, `joint`
        (the best single-joint fit, or None without the joint angles), `text`; None with fewer
        failing readings than a rigid fit needs.

        Returns
        -------
        dict or None
        """
        from dt_runtime.analysis.deployment import MIN_SHIFT_READINGS, joint_alternative, rigid_shift

        failing = [r for x, r in zip(self._window, self._readings) if x and r is not None]
        if len(failing) < MIN_SHIFT_READINGS:
            return None
        P, d, u = (np.array([r[k] for r in failing], dtype=float) for k in range(3))
        s = rigid_shift(P, d, u)
        out: dict[str, Any] = {
            "rigid": bool(s.rigid), "offer": False,
            "translation_mm": [round(float(v), 4) for v in s.translation_mm],
            "rotation_mrad": [round(float(v), 4) for v in s.rotation_mrad], "p_before": float(s.p_before),
            "p_after": float(s.p_after), "n": int(s.n), "joint": None, "text": s.text}
        if not s.rigid:
            return out
        if self.jacobian is None or any(r[3] is None for r in failing):
            out["text"] += ("; the joint angles are not known, so a changed arm is not ruled out: "
                            "not offered")
            return out
        alt = joint_alternative(self.jacobian(np.array([r[3] for r in failing], dtype=float)), d, u, s.chi2_after, P)
        out["joint"] = alt
        which = (f"zero offset(s) of joint(s) {', '.join(map(str, alt['joints']))} "
                 f"({', '.join(f'{v:+.3f}' for v in alt['dq_mrad'])} mrad)")
        if alt["explains"]:
            out["text"] += (f"; but {which} explain them about as well (chi^2 {alt['margin']:+.1f} above the "
                            f"shift's, {alt['needed']:.1f} needed): the arm may have changed, not offered")
        else:
            out["offer"] = True
            out["text"] += (f"; changed joint zeros do not explain them (best: {which}, chi^2 {alt['margin']:+.1f} "
                            f"above the shift's)")
        return out

    def _escalate(self, t: float, rule: str | None) -> None:
        """The alarm is confirmed: offer re-referencing when the failures are one rigid shift (and
        `rereference` is on), else page."""
        c = self.config
        shift = self.shift() if c.rereference else None
        alt = None if shift is None else shift["joint"]
        if (shift is not None and shift["rigid"] and not shift["offer"] and alt is not None and alt["margin"] > 0
                and not alt["nested"] and self.confirm_count - c.confirm_n < c.window_n):
            # the shift fits better than the joints, not yet by enough: more failing readings may
            # tell them apart (not when the joints' motion is itself rigid: joint 1's); at most
            # `window_n` further alarmed tests, then it pages
            return
        if shift is not None and shift["offer"]:
            before = self.snapshot()
            self.offer, self.offered_at = shift, self.n_seen
            self._fire("offer", t, rule, {"shift": shift, "reason": "session shift: re-reference"}, before=before)
            return
        extra = {"reason": "repeated Eq. 17 t-test failures"
                 + ("" if shift is None else "; one rigid shift of the set-up, but the arm is not ruled out"
                    if shift["rigid"] else "; not one rigid shift of the set-up: the arm changed")}
        self._fire("request", t, rule, extra | ({"shift": shift} if shift is not None else {}))

    def _offered(self, t: float, rule: str | None) -> None:
        """An offer is open: the failures ended (back to suspect), turned into a change that is not
        rigid, or went on for `rereference_bound` tests without the offer applied (both page)."""
        if rule is None:
            before = self.snapshot()
            self.offer = self.offered_at = None
            self.confirm_count = 0
            self._fire("regain", t, rule, before=before)
            return
        shift = self.shift()
        waited = self.n_seen - (self.offered_at if self.offered_at is not None else self.n_seen)
        if shift is not None and not shift["offer"]:
            reason = ("repeated Eq. 17 t-test failures, no longer a rigid shift of the set-up alone: "
                      "the arm may have changed")
        elif waited >= self.config.rereference_bound:
            reason = (f"re-referencing offered {waited} tests ago and not applied; the failures go on "
                      f"(escalation.rereference_bound {self.config.rereference_bound})")
        else:
            return
        before = self.snapshot()
        offer = self.offer
        self.offer = self.offered_at = None
        self._fire("request", t, rule, {"reason": reason, "offer": offer}
                   | ({"shift": shift} if shift is not None else {}), before=before)

    def rereference(self, t: float | None = None, note: str | None = None, by: str | None = None) -> dict[str, Any]:
        """The operator applied the offered re-referencing: rereference_offered (or a halt it
        caused) -> nominal, statistics reset.

        Parameters
        ----------
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).
        note : str, optional
            Why, as the operator said it (kept in the evidence).
        by : str, optional
            Who (kept in the evidence).

        Returns
        -------
        dict
            The offer applied (its fitted shift, `shift`).

        Raises
        ------
        StateError
            No offer is open (the escalation is not in rereference_offered).
        """
        if not self.offer_open:
            raise StateError("re-referencing is only applied in rereference_offered, the escalation is in "
                             f"{self.state}")
        assert self.offer is not None
        t = float(self.n_seen if t is None else t)
        before = self.snapshot()
        offer = self.offer
        ev = self.evidence(None) | {"rereferenced": True, "shift": offer, "note": note, "by": by}
        halted = self.state == "halted"  # the offer halted the arm (halt.on_untrusted: halt): that halt ends too
        if halted:
            ev |= self.evidence_of_halt()
            self.halt_reason, self.halt_sticky, self.halted_from = None, False, None
        self._reset_stats()
        self.offer = self.offered_at = None
        self._fire("acknowledge" if halted else "rereferenced", t, None, ev, before=before)
        return offer

    @property
    def offer_open(self) -> bool:
        """A re-referencing offer can be applied: in rereference_offered, or halted from it."""
        return self.offer is not None and (self.state == "rereference_offered" or (
            self.state == "halted" and self.halted_from == "rereference_offered"))

    def halt(self, reason: str, t: float | None = None, *, sticky: bool = False) -> bool:
        """Enter `halted` for `reason`; an existing halt keeps its first reason.

        Parameters
        ----------
        reason : str
            Why, in words (published on `.../health` and in the maintenance request).
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).
        sticky : bool
            Only `acknowledge` leaves it, not `resume`.

        Returns
        -------
        bool
            True if this was a transition (False when already halted).
        """
        if self.state == "halted":
            return False
        t = float(self.n_seen if t is None else t)
        before = self.snapshot()
        self.halted_from, self.halt_reason, self.halt_sticky = self.state, str(reason), bool(sticky)
        self._fire("halt", t, None, self.evidence_of_halt(), before=before)
        return True

    def resume(self, t: float | None = None) -> bool:
        """The cause of a non-sticky halt cleared: back to the state it interrupted.

        Parameters
        ----------
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).

        Returns
        -------
        bool
            True if this was a transition (False when not halted, or the halt is sticky).
        """
        if self.state != "halted" or self.halt_sticky:
            return False
        t = float(self.n_seen if t is None else t)
        before = self.snapshot()
        target, reason = self.halted_from or "nominal", self.halt_reason
        self.halted_from, self.halt_reason = None, None
        self._fire(f"resume_{target}", t, None, {"resumed_from_halt": reason}, before=before)
        return True

    def acknowledge(self, t: float | None = None, note: str | None = None,
                    by: str | None = None) -> None:
        """Maintenance was done: maintenance_requested or halted -> nominal, statistics reset.

        Parameters
        ----------
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).
        note : str, optional
            Why, as the operator said it (kept in the evidence).
        by : str, optional
            Who (kept in the evidence).

        Raises
        ------
        StateError
            The machine is in neither maintenance_requested nor halted.
        """
        if self.state not in PAGING:
            raise StateError(f"acknowledge is only allowed in {' or '.join(PAGING)}, "
                             f"the escalation is in {self.state}")
        t = float(self.n_seen if t is None else t)
        before = self.snapshot()
        ev = self.evidence(None) | {"acknowledged": True, "note": note, "by": by} | (
            self.evidence_of_halt() if self.state == "halted" else {})
        self._reset_stats()
        self.halt_reason, self.halt_sticky, self.halted_from = None, False, None
        self.offer = self.offered_at = None
        try:
            self._fire("acknowledge", t, None, ev, before=before)
        except TransitionNotAllowed as exc:  # pragma: no cover - guarded above
            raise StateError(str(exc)) from exc

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict[str, Any]:
        """The machine's state and statistics, JSON-ready, for `restore` after a restart."""
        return {
            "version": SNAPSHOT_VERSION, "state": self.state, "window": list(self._window),
            "cusum": self.cusum, "consecutive_passes": self.consecutive_passes,
            "confirm_count": self.confirm_count, "last_t": list(self._last_t),
            "n_seen": self.n_seen, "episode": self.episode, "halt_reason": self.halt_reason,
            "halt_sticky": self.halt_sticky, "halted_from": self.halted_from,
            "offer": self.offer, "offered_at": self.offered_at,
        }

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Resume from a `snapshot()` (no transition is reported: nothing changed).

        Parameters
        ----------
        snapshot : dict
            A snapshot of version 1, 2 or `SNAPSHOT_VERSION`.

        Raises
        ------
        StateError
            The snapshot is of another version, names an unknown state or lacks a key.
        """
        try:
            if snapshot.get("version") not in (1, 2, SNAPSHOT_VERSION):
                raise ValueError(f"snapshot version {snapshot.get('version')!r}")
            state = snapshot["state"]
            if state not in STATES:
                raise ValueError(f"unknown state {state!r}")
            self.machine = EscalationMachine(start_value=state)
            self._reset_stats()
            self._window.extend(int(bool(v)) for v in snapshot["window"])
            self.cusum = float(snapshot["cusum"])
            self.consecutive_passes = int(snapshot["consecutive_passes"])
            self.confirm_count = int(snapshot["confirm_count"])
            self._last_t.extend(snapshot.get("last_t", []))
            self.n_seen = int(snapshot["n_seen"])
            self.episode = int(snapshot.get("episode", 0))
            self.halt_reason = snapshot.get("halt_reason")
            self.halt_sticky = bool(snapshot.get("halt_sticky", False))
            self.halted_from = snapshot.get("halted_from")
            self.offer = snapshot.get("offer")
            self.offered_at = None if snapshot.get("offered_at") is None else int(snapshot["offered_at"])
            if state == "halted" and self.halted_from not in STATES[:-1]:
                raise ValueError(f"halted from unknown state {self.halted_from!r}")
        except (KeyError, TypeError, ValueError) as exc:
            raise StateError(f"cannot restore escalation snapshot: {exc}") from exc


# ---------------------------------------------------------------------- false-alarm numbers
def _binom_sf(k: int, n: int, p: float) -> float:
    """P(Bin(n, p) >= k)."""
    if k <= 0:
        return 1.0
    return float(sum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(k, n + 1)))


def _cusum_chain(c: EscalationConfig) -> tuple[int, int, int]:
    frac = Fraction(c.cusum_k).limit_denominator(1000)
    d = frac.denominator
    up, down = (1 - frac) * d, frac * d  # integer steps on the grid 1/d
    return int(up), int(down), math.ceil(c.cusum_h * d - 1e-9)


def false_alarm_rates(config: EscalationConfig | None = None) -> dict[str, float]:
    """Upper bounds of false alarm onsets under the null (docs/service.md, "The escalation machine").

    Parameters
    ----------
    config : EscalationConfig, optional
        The thresholds (defaults if None); `tests_per_day` turns rates per test into rates per day.

    Returns
    -------
    dict
        `window_per_test`, `window_per_day`, `cusum_per_test` (stationary upcrossing rate of
        `cusum_h`), `cusum_per_day`, `cusum_arl0` (tests from S = 0 to an alarm) and
        `requests_per_day_bound` (the bound for the configured `mode`).
    """
    c = config or EscalationConfig()
    p = c.alpha
    w = p * _binom_sf(c.window_k - 1, c.window_n - 1, p)
    up, down, H = _cusum_chain(c)
    # Chain on S in grid units, capped far above H (mass there is negligible).
    cap = H + 40 * up
    P = np.zeros((cap + 1, cap + 1))
    for s in range(cap + 1):
        P[s, min(cap, s + up)] += p
        P[s, max(0, s - down)] += 1 - p
    # Stationary distribution: solve pi (P - I) = 0 with sum(pi) = 1.
    A = np.vstack([(P.T - np.eye(cap + 1)), np.ones(cap + 1)])
    b = np.zeros(cap + 2)
    b[-1] = 1.0
    pi = np.linalg.lstsq(A, b, rcond=None)[0]
    s_rate = float(sum(pi[s] * p for s in range(H) if s + up >= H))
    # ARL0 from 0: expected steps to reach >= H.
    Q = np.eye(H)
    for s in range(H):
        if s + up < H:
            Q[s, s + up] -= p
        Q[s, max(0, s - down)] -= 1 - p
    arl0 = float(np.linalg.solve(Q, np.ones(H))[0])
    n = c.tests_per_day
    bound = {"window": w, "cusum": s_rate, "either": w + s_rate,
             "both": min(w, s_rate)}[c.mode]
    return {"window_per_test": w, "window_per_day": w * n, "cusum_per_test": s_rate,
            "cusum_per_day": s_rate * n, "cusum_arl0": arl0,
            "requests_per_day_bound": bound * n}
