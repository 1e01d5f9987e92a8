"""Escalation of in-service Eq. 17 t-test outcomes to a maintenance request: the state machine
(`EscalationMachine`: nominal, suspect, out_of_control, maintenance_requested, halted), the
`Escalator` that feeds it the window and CUSUM statistics of the failure indicator, and the
false-alarm bounds of a configuration (`false_alarm_rates`).

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

SNAPSHOT_VERSION = 2  # 2 added halted, halt_reason, halt_sticky, halted_from, episode (1 still loads)

#: States that page: entering one opens an episode whose maintenance requests must be delivered.
PAGING = ("maintenance_requested", "halted")

TransitionCallback = Callable[[str, str, dict[str, Any], float], None]


class EscalationConfig(Frozen):
    """The `escalation` section of the runtime YAML (docs/service.md, "The escalation machine").

    `mode`: which statistic raises the alarm (`window`, `cusum`, `either`, `both`); `alpha`: the
    per-test significance level of the t-test feeding the machine; `window_n`, `window_k`,
    `suspect_k`: the window's length and the failures in it that alarm or raise suspicion;
    `cusum_k`, `cusum_h`, `suspect_h`: the CUSUM's reference value and its alarm and suspicion
    thresholds; `confirm_n`: further alarmed tests before out_of_control pages; `recover_passes`:
    passes in a row before suspect clears; `last_t_kept`: t values kept as evidence;
    `tests_per_day`: for `false_alarm_rates`. Counts are tests, not seconds; an inconsistent or
    unbounded value raises ValueError (a ConfigError through dt_kernel.config).
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
        if self.confirm_n < 0 or self.recover_passes < 1:
            raise ValueError("need confirm_n >= 0 and recover_passes >= 1")
        # Bounded counts: a typo such as confirm_n 1e9 would silently switch paging off.
        for key, value, most in (("window_n", self.window_n, 10_000), ("confirm_n", self.confirm_n, 1_000),
                                 ("recover_passes", self.recover_passes, 100_000),
                                 ("last_t_kept", self.last_t_kept, 1_000)):
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
    maintenance_requested = State()

    raise_suspicion = nominal.to(suspect)
    clear = suspect.to(nominal)
    lose_control = suspect.to(out_of_control)
    regain = out_of_control.to(suspect)
    request = out_of_control.to(maintenance_requested)
    halted = State()
    halt = (nominal.to(halted) | suspect.to(halted) | out_of_control.to(halted)
            | maintenance_requested.to(halted))
    resume_nominal = halted.to(nominal)
    resume_suspect = halted.to(suspect)
    resume_out_of_control = halted.to(out_of_control)
    resume_maintenance_requested = halted.to(maintenance_requested)
    acknowledge = maintenance_requested.to(nominal) | halted.to(nominal)


STATES = ("nominal", "suspect", "out_of_control", "maintenance_requested", "halted")


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

    Not thread-safe: the daemon's loop alone feeds and moves it.
    """

    def __init__(self, config: EscalationConfig | None = None,
                 on_transition: TransitionCallback | None = None):
        self.config = config or EscalationConfig()
        self.on_transition = on_transition
        self.machine = EscalationMachine()
        self._reset_stats()
        self.n_seen = 0
        self.episode = 0  # paging episodes opened so far (entries into maintenance_requested or halted)
        self.halt_reason: str | None = None
        self.halt_sticky = False
        self.halted_from: str | None = None

    def _reset_stats(self) -> None:
        c = self.config
        self._window: deque[int] = deque(maxlen=c.window_n)
        self.cusum = 0.0
        self.consecutive_passes = 0
        self.confirm_count = 0
        self._last_t: deque[float | None] = deque(maxlen=c.last_t_kept)

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> str:
        """The machine's state: one of `STATES`."""
        # the machine's value (every state's value is its id): read every tick, ~10x cheaper than
        # building the configuration's set
        return self.machine.current_state_value

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
                t: float | None = None) -> str:
        """Feed one t-test outcome; the transitions it fires are reported to `on_transition`.

        Parameters
        ----------
        passed : bool
            The test passed (p >= alpha).
        t_value : float, optional
            The test's t (kept as evidence; None or non-finite is kept as None).
        t : float, optional
            Daemon time, s (default: the number of tests seen so far).

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
                self._fire("request", t, rule)
            return self.state
        if state == "out_of_control":
            if rule is None:
                self.confirm_count = 0
                self._fire("regain", t, rule)
            else:
                self.confirm_count += 1
                if self.confirm_count >= c.confirm_n:
                    self._fire("request", t, rule)
        return self.state

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
        }

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Resume from a `snapshot()` (no transition is reported: nothing changed).

        Parameters
        ----------
        snapshot : dict
            A snapshot of version 1 or `SNAPSHOT_VERSION`.

        Raises
        ------
        StateError
            The snapshot is of another version, names an unknown state or lacks a key.
        """
        try:
            if snapshot.get("version") not in (1, SNAPSHOT_VERSION):
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
            if state == "halted" and self.halted_from not in STATES[:4]:
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
