"""The daemon as a composition root, part by part: the one supervisor's halt / trust / camera
policy for the point loop and the path loop, a transition reaching the health reporter and the
bus as an event (no callback into the daemon), the parts closed newest first (also when one fails
to open), and the status view the query answers read."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.base import RigReading
from dt_kernel.errors import DriverError
from dt_runtime.fabric import BusConfig
from dt_runtime.service.answers import answers
from dt_runtime.service.counters import Counters
from dt_runtime.service.daemon import Parts
from dt_runtime.service.escalation import EscalationConfig, Escalator
from dt_runtime.service.events import ActionQueued, Events, HealthDue, RequestsQueued, Transition
from dt_runtime.service.health import CellStatus, HealthReporter
from dt_runtime.service.housekeeping import Housekeeper
from dt_runtime.service.paging import Paging
from dt_runtime.service.runtime_config import HaltConfig
from dt_runtime.service.store import Store
from dt_runtime.service.supervisor import Step, Supervisor


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _supervisor(streaming: bool = False, **halt) -> tuple[Supervisor, Escalator, Counters, _Clock, threading.Event]:
    esc, n, clock, stop = Escalator(EscalationConfig()), Counters(), _Clock(), threading.Event()
    sup = Supervisor(HaltConfig(**halt), 0.1, esc, n, clock, stop, streaming=streaming, store_failing=lambda: False)
    return sup, esc, n, clock, stop


def _fail_until_untrusted(esc: Escalator) -> None:
    for i in range(200):
        if esc.state in ("out_of_control", "maintenance_requested"):
            return
        esc.observe(False, 10.0, float(i))
    raise AssertionError(f"still {esc.state}")


_BLIND = RigReading(None, 0.0, refused="rigid body 'tool' not tracked")
_SEEN = RigReading(np.array([0.1, 0.2, 0.3]), 0.0)


# --- the supervisor: both loops ask the same policy ---------------------------------------------
@pytest.mark.parametrize("streaming", [False, True])
def test_refused_commands_halt_then_the_point_loop_retries_and_a_path_waits(streaming):
    sup, esc, n, _, _ = _supervisor(streaming, after_refused=3)
    for _ in range(2):
        sup.refused(ValueError("correction 50 mm exceeds the bound"), 1.0)
    assert esc.state == "nominal"
    assert sup.status() == ("degraded", "command refused: correction 50 mm exceeds the bound")
    sup.refused(ValueError("again"), 2.0)
    assert esc.state == "halted" and not esc.halt_sticky and "every command refused for 3 ticks" in esc.halt_reason
    # a point program tries the next command (it resumes when one goes through); a path waits
    assert sup.next_step(3.0) is (Step.WAIT if streaming else Step.MOVE)
    sup.moved(3.0)
    assert esc.state == "nominal" and n.refused_in_row == 0 and sup.status() == ("running", None)


@pytest.mark.parametrize("streaming", [False, True])
def test_an_untrusted_correction_follows_halt_on_untrusted_in_both_loops(streaming):
    sup, esc, n, _, _ = _supervisor(streaming)  # default: uncorrected
    _fail_until_untrusted(esc)
    assert not sup.trusted() and not sup.corrects() and sup.next_step(1.0) is Step.MOVE
    assert sup.status() == ("degraded", f"{esc.state}: commands sent uncorrected")
    sup, esc, _, _, _ = _supervisor(streaming, on_untrusted="correct")
    _fail_until_untrusted(esc)
    assert sup.corrects() and sup.next_step(1.0) is Step.MOVE
    sup, esc, _, _, _ = _supervisor(streaming, on_untrusted="halt")
    _fail_until_untrusted(esc)
    assert sup.pass_stop().endswith("the correction is not trusted (halt.on_untrusted: halt)")
    assert sup.next_step(1.0) is Step.WAIT  # a sticky halt: only the operator's 'done' leaves it
    assert esc.state == "halted" and esc.halt_sticky and sup.pass_stop().startswith("halted: ")
    sup.moved(2.0)
    assert esc.state == "halted" and sup.next_step(2.0) is Step.WAIT


@pytest.mark.parametrize("streaming", [False, True])
def test_a_silent_camera_halts_the_arm_stands_and_the_first_accepted_reading_resumes(streaming):
    sup, esc, n, clock, _ = _supervisor(streaming, after_camera_refused_s=5.0)
    sup.camera_refused(_BLIND)
    assert n.mvs_refused == 1 and n.camera_refused_since == 0.0 and sup.status()[0] == "degraded"
    clock.t = 6.0
    sup.camera_refused(_BLIND)
    assert esc.state == "halted" and "no MVS reading tested for 6.0 s" in esc.halt_reason
    assert sup.next_step(6.0) is Step.PROBE and sup.pass_stop().startswith("halted: ")
    assert not sup.probed(_BLIND, 7.0) and esc.state == "halted" and sup.next_step(7.0) is Step.PROBE
    assert sup.probed(_SEEN, 8.0)
    assert esc.state == "nominal" and n.camera_refused_since is None and sup.next_step(8.0) is Step.MOVE


def test_a_camera_halt_left_by_the_operator_is_timed_afresh():
    sup, esc, n, clock, _ = _supervisor(after_camera_refused_s=1.0)
    clock.t = 2.0
    n.camera_refused_since = 0.0
    sup.untested("MVS refused")
    assert sup.camera_halt and esc.state == "halted"
    esc.acknowledge(3.0, note="cleaned the lens", by="ana")
    assert sup.next_step(3.0) is Step.MOVE and not sup.camera_halt and n.camera_refused_since is None


def test_a_stale_or_refused_reading_is_not_tested_a_fresh_one_is():
    sup, _, n, _, _ = _supervisor()
    arrived = 100.0
    assert not sup.usable(RigReading(np.zeros(3), 0.0, host_time=arrived - 0.5), arrived)
    assert n.stale_measurements == 1 and "stale measurement: received 500 ms" in n.last_problem
    assert not sup.usable(_BLIND, arrived) and n.mvs_refused_in_row == 1
    assert sup.usable(RigReading(np.zeros(3), 0.0, host_time=arrived - 0.05), arrived) and n.mvs_refused_in_row == 0
    sup.rejected(ValueError("NaN"))
    assert n.camera_refused_since is not None
    sup.tested()
    assert n.camera_refused_since is None


def test_driver_faults_halt_after_the_limit_but_not_while_stopping():
    sup, esc, n, _, stop = _supervisor(after_driver_faults=2)
    stop.set()
    sup.driver_fault(DriverError("link down"))
    sup.driver_fault(DriverError("link down"))
    assert esc.state == "nominal" and n.driver_faults == 2 and sup.pass_stop() == "the daemon is stopping"
    sup, esc, n, _, _ = _supervisor(after_driver_faults=2)
    sup.driver_fault(DriverError("link down"))
    sup.driver_fault(DriverError("link down"))
    assert esc.state == "halted" and "driver fault 2 times in a row" in esc.halt_reason
    sup.pass_done(5, corrected=False)
    assert n.ticks == 5 and n.uncorrected == 5 and n.driver_faults_in_row == 0


def test_a_stopped_pass_halts_sticky_with_its_reason():
    sup, esc, n, _, _ = _supervisor(streaming=True)
    sup.pass_stopped("path stopped at set-point 3 of 9: protective stop")
    assert esc.state == "halted" and esc.halt_sticky and n.last_problem.startswith("path stopped")
    assert sup.next_step(1.0) is Step.WAIT


# --- events: a transition reaches its subscribers -----------------------------------------------
class _Bus:
    """What the daemon's bus does with events, recorded."""

    refused, last_refused, state = 0, None, "connected"

    def __init__(self) -> None:
        self.states: list[dict] = []
        self.health: list[dict] = []
        self.wakes = 0

    def on_transition(self, event: Transition) -> None:
        self.states.append(event.payload())
        if event.requests:
            self.wakes += 1

    def on_requests(self, event: RequestsQueued) -> None:
        self.wakes += 1

    def publish_health(self, payload: dict) -> bool:
        self.health.append(payload)
        return True


def test_a_transition_reaches_the_bus_and_the_health_reporter_as_an_event(tmp_path):
    events, bus = Events(), _Bus()
    events.subscribe(Transition, bus.on_transition)
    events.subscribe(RequestsQueued, bus.on_requests)
    with Store(tmp_path / "dt.sqlite") as store:
        paging = Paging(EscalationConfig(), BusConfig(), store, events)
        esc, n = paging.escalator, Counters()
        sup = Supervisor(HaltConfig(), 0.1, esc, n, lambda: 5.0, threading.Event(), streaming=False,
                         store_failing=lambda: False)
        reporter = HealthReporter(sup.status, esc, n, store, lambda: 5.0, None, bus, events, stream=lambda: None)
        due: list[HealthDue] = []
        events.subscribe(HealthDue, due.append)
        hk = Housekeeper(threading.Event(), events, take_actions=paging.take_actions, send_health=reporter.send,
                         prune=lambda: 0, status_line=lambda: ("", {}), last_tick_mono=lambda: 0.0,
                         health_period_s=1.0, prune_every_s=60.0, status_every_s=None)
        reporter.changed()
        assert len(due) == 1 and hk._health_due.is_set()
        reporter.changed()
        assert len(due) == 1  # no change: nothing due
        hk._health_due.clear()
        esc.halt("the operator pressed stop", 5.0)
        # recorded first, then emitted: the bus published the state and was woken for the request
        assert [t["dst"] for t in store.transitions()] == ["halted"]
        assert bus.states == [{"src": "nominal", "dst": "halted", "t": 5.0,
                               "evidence": bus.states[0]["evidence"]}] and bus.wakes == 1
        assert len(due) == 2 and hk._health_due.is_set()  # a transition forces health
        reporter.send()
        assert bus.health[-1]["status"] == "halted" and bus.health[-1]["reason"] == "the operator pressed stop"
        assert len(paging.requests) == 1 and store.outbox_of_episode(esc.episode)
        hk.poll_now.clear()
        events.emit(ActionQueued(7))
        assert hk.poll_now.is_set()  # an operator's 'done' wakes the housekeeping thread


def test_a_done_sends_health_again_after_it_acknowledged_the_episodes_requests(tmp_path):
    # the transition's health went out before the outbox acks: after `dt ack --store` the dashboard
    # kept showing "requests not acknowledged 1" while dt status said acknowledged
    events, bus = Events(), _Bus()
    with Store(tmp_path / "dt.sqlite") as store:
        paging = Paging(EscalationConfig(), BusConfig(), store, events)
        esc, n = paging.escalator, Counters()
        sup = Supervisor(HaltConfig(), 0.1, esc, n, lambda: 5.0, threading.Event(), streaming=False,
                         store_failing=lambda: False)
        reporter = HealthReporter(sup.status, esc, n, store, lambda: 5.0, None, bus, events, stream=lambda: None)
        sent: list[int] = []
        events.subscribe(HealthDue, lambda _e: sent.append(reporter.health()["outbox_pending"]))
        esc.halt("the operator pressed stop", 5.0)
        assert store.outbox_pending() and sent[-1] == len(store.outbox_pending())
        store.add_action("done", "kim", "checked", source="cli")
        paging.take_actions()
        paging.apply_actions(6.0)
        assert esc.state == "nominal" and not store.outbox_pending()
        assert sent[-1] == 0  # the last health due counts no request pending


# --- parts: closed newest first, whatever happens -------------------------------------------------
def test_a_part_that_fails_to_open_closes_those_opened_before_in_reverse_order():
    closed: list[str] = []

    def start(parts: Parts) -> None:
        parts.callback(closed.append, "store")
        parts.callback(closed.append, "bus")
        parts.callback(lambda: closed.append("server") or 1 / 0)  # a close that fails: the rest still close
        parts.callback(closed.append, "drivers")
        raise DriverError("the camera does not answer")  # the next part fails to open

    parts = Parts()
    with pytest.raises(DriverError):
        try:
            start(parts)
        except BaseException:
            parts.close()
            raise
    assert closed == ["drivers", "server", "bus", "store"]
    parts.close()
    assert len(closed) == 4  # closed once


# --- the status view feeds the answers ------------------------------------------------------------
class _View:
    def health(self) -> dict:
        return {"status": "degraded", "reason": "MVS refused", "escalation": "suspect", "episode": 2, "ticks": 40,
                "last_tick": 1.5e9, "pid": 42}

    def open_requests(self) -> list:
        from dt_runtime.service.store import OutboxItem

        return [OutboxItem(3, 100.0, "dt/c/r/maintenance/request", {"uid": "u3", "group": "maintenance",
                                                                    "kind": "t_test", "episode": 2, "reason": "x"}, 2)]

    def latest_requests(self, limit: int) -> list:
        return [{"id": 3, "limit": limit}]

    def latest_tests(self, limit: int) -> list:
        return [{"t": 1.0, "passed": False, "limit": limit}]

    def t_test_failures(self) -> int:
        return 9

    def escalation(self) -> str:
        return "suspect"


def test_the_answers_read_the_status_view_only():
    a = answers(_View(), {"twin_sha256": "0123456789abcdef", "calibrated": "2026-01-01"})
    s = a["status"]()
    assert {k: s[k] for k in ("status", "reason", "escalation", "episode", "ticks", "t_test_failures",
                               "open_requests", "oldest_open_created", "twin_sha256")} == {
        "status": "degraded", "reason": "MVS refused", "escalation": "suspect", "episode": 2, "ticks": 40,
        "t_test_failures": 9, "open_requests": 1, "oldest_open_created": 100.0, "twin_sha256": "0123456789ab"}
    r = a["requests"]()
    assert r["open"] == [{"id": 3, "created": 100.0, "attempts": 2, "uid": "u3", "group": "maintenance",
                          "kind": "t_test", "episode": 2, "reason": "x"}]
    assert r["latest"] == [{"id": 3, "limit": 10}] and r["escalation"] == "suspect"
    assert a["tests"]()["tests"][0]["limit"] == 10 and a["health"]()["ticks"] == 40
    assert a["provenance"]()["calibrated"] == "2026-01-01"


def test_the_daemons_status_view_reads_its_store_counters_and_machine(tmp_path):
    with Store(tmp_path / "dt.sqlite") as store:
        esc, n, events = Escalator(EscalationConfig()), Counters(), Events()
        sup = Supervisor(HaltConfig(), 0.1, esc, n, lambda: 0.0, threading.Event(), streaming=False,
                         store_failing=lambda: False)
        reporter = HealthReporter(sup.status, esc, n, store, lambda: 0.0, None, None, events, stream=lambda: None)
        view = CellStatus(reporter, store, n, esc)
        store.outbox_add_many([("dt/c/r/maintenance/request", {"uid": "u1", "episode": 1})])
        n.failures = 4
        s = answers(view, {"twin_sha256": "ab" * 32, "calibrated": None})["status"]()
        assert s["open_requests"] == 1 and s["t_test_failures"] == 4 and s["status"] == "running"
        assert view.escalation() == "nominal" and view.health()["outbox_pending"] == 1
