"""Escalation: false-alarm rate under the null, detection delay, restore, acknowledge."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dt_runtime.service.escalation import (EscalationConfig, EscalationMachine, Escalator,
                                   false_alarm_rates)
from dt_runtime.service.store import Store
from dt_kernel.config import validate
from dt_kernel.errors import ConfigError, StateError

TARGET_PER_DAY = 0.1
DAY = 86_400


def run(esc: Escalator, failed: np.ndarray, t0: int = 0) -> list[str]:
    return [esc.observe(not bool(f), t_value=3.0 if f else 0.4, t=float(t0 + i))
            for i, f in enumerate(failed)]


def test_defaults_meet_the_false_alarm_target_analytically():
    r = false_alarm_rates()
    assert r["requests_per_day_bound"] < TARGET_PER_DAY / 2
    assert r["window_per_day"] == pytest.approx(0.0077, rel=0.05)
    assert r["cusum_per_day"] == pytest.approx(0.0114, rel=0.05)
    assert r["cusum_arl0"] > 30 * DAY


def test_isolated_false_alarms_never_escalate_in_one_simulated_day():
    log = []
    esc = Escalator(on_transition=lambda *a: log.append(a))
    failed = np.random.default_rng(20240601).random(DAY) < 0.05  # null: alpha = 0.05
    run(esc, failed)
    requests = sum(1 for a in log if a[1] == "maintenance_requested")
    assert requests <= TARGET_PER_DAY * 1  # i.e. none in one day
    assert sum(1 for a in log if a[1] == "out_of_control") == 0
    assert 0 < sum(1 for a in log if a[1] == "suspect") < 200  # suspicion is logged, not paged
    # each suspicion that cleared returned to nominal: the log is a consistent path
    for (s1, d1, *_), (s2, _d2, *_) in zip(log, log[1:]):
        assert d1 == s2


def test_analytic_bound_matches_simulation_for_a_loose_config():
    # A deliberately sensitive config (many onsets per day) checks the bound's arithmetic;
    # confirm_n is at its maximum (1000 tests: no alarm holds that long under the null) so every alarm onset shows as one out_of_control entry, no request.
    for mode, extra in (("window", {}), ("cusum", {"cusum_h": 2.0, "suspect_h": 1.0})):
        cfg = EscalationConfig(mode=mode, window_k=5, suspect_k=3, confirm_n=1000, **extra)
        bound = false_alarm_rates(cfg)["requests_per_day_bound"]
        log = []
        esc = Escalator(cfg, on_transition=lambda *a: log.append(a))
        rng = np.random.default_rng(7)
        for day in range(1):
            run(esc, rng.random(DAY) < 0.05, t0=day * DAY)
        onsets = sum(1 for a in log if a[1] == "out_of_control")
        assert 0.5 * bound < onsets <= 1.25 * bound, (mode, onsets, bound)


@pytest.mark.parametrize("p_fail, max_delay", [(1.0, 9), (0.7, 20), (0.5, 40)])
def test_sustained_fault_escalates_within_bounded_measurements(p_fail, max_delay):
    esc = Escalator()
    rng = np.random.default_rng(3)
    run(esc, rng.random(600) < 0.05)  # some nominal history first
    assert esc.state in ("nominal", "suspect")
    states = run(esc, rng.random(200) < p_fail, t0=600)
    delay = states.index("maintenance_requested") + 1
    assert delay <= max_delay
    assert set(states[delay:]) == {"maintenance_requested"}  # stays until acknowledged


def test_transitions_carry_evidence_and_path():
    log = []
    esc = Escalator(on_transition=lambda *a: log.append(a))
    run(esc, np.ones(9, bool))
    path = [(a[0], a[1]) for a in log]
    assert path == [("nominal", "suspect"), ("suspect", "out_of_control"),
                    ("out_of_control", "maintenance_requested")]
    ev = log[1][2]
    assert ev["rule"] in ("cusum", "window", "both") and ev["cusum"] >= 4.5
    assert ev["last_t"] == [3.0] * 5 and ev["window_failures"] == ev["n_seen"]
    json.dumps(ev)  # JSON-ready for the Store and the Bus
    assert log[-1][3] == 8.0  # time stamp passed through


def test_transient_burst_regains_control_without_request():
    log = []
    esc = Escalator(on_transition=lambda *a: log.append(a))
    burst = np.array([1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0] + [0] * 40, bool)
    run(esc, burst)
    dsts = [a[1] for a in log]
    assert "out_of_control" in dsts and "maintenance_requested" not in dsts
    assert esc.state == "nominal" and dsts[-1] == "nominal"


def test_acknowledge_returns_to_nominal_and_resets():
    log = []
    esc = Escalator(on_transition=lambda *a: log.append(a))
    run(esc, np.ones(12, bool))
    assert esc.state == "maintenance_requested"
    esc.acknowledge(t=100.0, note="gearbox replaced")
    assert esc.state == "nominal" and esc.cusum == 0 and esc.window_failures == 0
    assert log[-1][:2] == ("maintenance_requested", "nominal")
    assert log[-1][2]["note"] == "gearbox replaced" and log[-1][3] == 100.0
    with pytest.raises(StateError):
        esc.acknowledge()


def test_restore_after_restart_resumes_the_same_state(tmp_path):
    db = tmp_path / "twin.db"
    rng = np.random.default_rng(11)
    outcomes = np.concatenate([rng.random(300) < 0.05, np.ones(7, bool)])
    ref = Escalator()
    ref_states = run(ref, outcomes)
    assert ref.state == "out_of_control"  # mid-confirmation: the interesting case
    with Store(db) as store:
        esc = Escalator(on_transition=lambda s, d, ev, t: store.record_transition(s, d, ev, t))
        run(esc, outcomes[:305])
        store.save_state("escalation", esc.snapshot())
    with Store(db) as store:  # "daemon restart"
        esc2 = Escalator()
        esc2.restore(store.load_state()["data"])
        transitions = store.transitions()
    assert esc2.state == ref_states[304]
    states2 = run(esc2, outcomes[305:], t0=305)
    assert states2 == ref_states[305:]
    assert esc2.snapshot() == ref.snapshot()
    assert transitions[-1]["dst"] == ref_states[304]
    # The state machine itself resumed (not only a label): events follow from there.
    esc2.observe(False)
    esc2.observe(False)
    assert esc2.state == "maintenance_requested"


def test_restore_rejects_garbage_and_config_validates():
    with pytest.raises(StateError):
        Escalator().restore({"version": 1, "state": "exploded"})
    with pytest.raises(ConfigError):
        validate(EscalationConfig, {"window_k": 30, "window_n": 20}, "runtime.yaml")
    with pytest.raises(ConfigError):
        validate(EscalationConfig, {"windw_n": 20}, "runtime.yaml")
    sm = EscalationMachine()
    with pytest.raises(sm.TransitionNotAllowed):
        sm.send("acknowledge")
