"""The escalation's re-referencing offer: failures that are one rigid shift of the set-up (and no
change of joint zeros) are offered for re-referencing instead of paging; a change of the arm,
an offer left unanswered past its bound, or one that stops being rigid, pages."""
from __future__ import annotations

import numpy as np
import pytest

from dt_kernel.errors import StateError
from dt_runtime.service.escalation import EscalationConfig, Escalator
from dt_runtime.service.rereference import MvsFrame, correction_of

U = np.full(3, 5e-5)  # 0.05 mm per axis
CFG = EscalationConfig(mode="window", window_n=12, window_k=8, suspect_k=3, confirm_n=1, rereference_bound=30)


def jacobian(q: np.ndarray) -> np.ndarray:
    """A 'robot' whose joints move the TCP differently at every pose (its 2 angles pick the
    directions): no joint offset looks like a translation of the set-up."""
    c, s = np.cos(q), np.sin(q)
    return 0.5 * np.stack([np.stack([c[:, 0], s[:, 0], 0 * c[:, 0]], axis=1),
                           np.stack([0 * c[:, 1], c[:, 1], s[:, 1]], axis=1)], axis=2)


def readings(n: int, seed: int, diff) -> list:
    rng = np.random.default_rng(seed)
    P = rng.uniform([0.6, -0.3, 0.2], [1.2, 0.3, 0.9], (n, 3))
    q = rng.uniform(-np.pi, np.pi, (n, 2))
    d = diff(P, q) + rng.normal(0, U[0], (n, 3))
    return [(P[i], d[i], U, q[i]) for i in range(n)]


def feed(esc: Escalator, rs: list, passed: bool = False, t0: int = 0) -> list[str]:
    return [esc.observe(passed, 9.0, float(t0 + i), r) for i, r in enumerate(rs)]


def shifted(P, q):
    omega, dt = np.array([0.0, 0.0, 3e-4]), np.array([1e-3, -2e-4, 0.0])
    return np.cross(omega, P) + dt


def test_a_rigid_shift_of_the_set_up_is_offered_with_its_evidence_not_paged():
    log = []
    esc = Escalator(CFG, on_transition=lambda *a: log.append(a), jacobian=jacobian)
    states = feed(esc, readings(10, 1, shifted))
    assert states[-1] == "rereference_offered" and "maintenance_requested" not in states
    src, dst, ev, _ = log[-1]
    assert (src, dst) == ("out_of_control", "rereference_offered") and ev["reason"] == "session shift: re-reference"
    s = ev["shift"]
    assert s["offer"] and s["rigid"] and not s["joint"]["explains"] and s["n"] == 9
    assert s["rotation_mrad"][2] == pytest.approx(0.3, abs=0.15)  # 9 readings of 0.05 mm noise
    # translation at the origin of GL: dt
    assert s["translation_mm"][:2] == pytest.approx([1.0, -0.2], abs=0.15)
    assert s["p_before"] < 1e-6 and s["p_after"] >= 0.01


def test_applying_the_offer_returns_to_nominal_and_the_correction_undoes_the_shift():
    esc = Escalator(CFG, jacobian=jacobian)
    rs = readings(10, 2, shifted)
    feed(esc, rs)
    offer = esc.rereference(t=100.0, note="camera knocked", by="op")
    assert esc.state == "nominal" and esc.offer is None and esc.window_failures == 0
    back = correction_of(offer)
    P = np.array([r[0] for r in rs])
    moved = P + shifted(P, None)
    assert np.max(np.abs(back.apply(moved) - P)) < 3 * U[0]  # within the noise of a 9-reading fit
    with pytest.raises(StateError, match="only applied in rereference_offered"):
        esc.rereference()


def test_a_change_of_the_arm_is_not_offered_it_pages():
    esc = Escalator(CFG, jacobian=jacobian)
    states = feed(esc, readings(10, 3, lambda P, q: jacobian(q) @ np.array([2e-3, -1e-3])))
    assert states[-1] == "maintenance_requested"
    assert esc.snapshot()["offer"] is None


def test_a_shift_a_joint_explains_as_well_waits_at_most_a_window_then_pages():
    def translating(q):  # joint 1 of this arm translates the TCP: indistinguishable from the set-up
        J = jacobian(q)
        J[:, :, 0] = [1.0, 0.0, 0.0]
        return J

    log = []
    esc = Escalator(CFG, on_transition=lambda *a: log.append(a), jacobian=translating)
    states = feed(esc, readings(40, 4, lambda P, q: np.tile([1e-3, 0, 0], (len(P), 1))))
    assert "rereference_offered" not in states and "maintenance_requested" in states
    confirmed = states.index("out_of_control") + CFG.confirm_n
    assert states.index("maintenance_requested") <= confirmed + CFG.window_n  # the wait is bounded
    ev = log[-1][2]
    assert ev["shift"]["rigid"] and ev["shift"]["joint"]["explains"] and ev["shift"]["joint"]["joints"][0] == 1
    assert "arm is not ruled out" in ev["reason"]


def test_a_joint_whose_motion_is_rigid_pages_at_once():
    # joint 1 of an arm turns the TCP about the vertical through the base: a rigid motion, which
    # no number of readings tells from a turned set-up; here the "joint angles" are the TCP itself
    def base_joint(q):
        J = np.zeros((len(q), 3, 2))
        J[:, :, 0] = np.cross([0.0, 0.0, 1.0], q)
        J[:, :, 1] = [[0.0, 0.0, 0.5]] * len(q)
        return J

    rng = np.random.default_rng(13)
    P = rng.uniform([0.6, -0.3, 0.2], [1.2, 0.3, 0.9], (12, 3))
    d = np.cross([0.0, 0.0, 1e-3], P) + rng.normal(0, U[0], P.shape)
    log = []
    esc = Escalator(CFG, on_transition=lambda *a: log.append(a), jacobian=base_joint)
    states = feed(esc, [(P[i], d[i], U, P[i]) for i in range(12)])
    assert states.index("maintenance_requested") == states.index("out_of_control") + CFG.confirm_n
    alt = log[-1][2]["shift"]["joint"]
    assert alt["nested"] and alt["explains"] and log[-1][2]["shift"]["rigid"]


def test_without_joint_angles_nothing_is_offered():
    esc = Escalator(CFG)  # no jacobian: a shift alone cannot rule out the arm
    assert feed(esc, readings(10, 5, shifted))[-1] == "maintenance_requested"


def test_an_offer_left_unanswered_pages_after_its_bound_and_one_that_stops_being_rigid_at_once():
    log = []
    esc = Escalator(CFG, on_transition=lambda *a: log.append(a), jacobian=jacobian)
    feed(esc, readings(10, 6, shifted))
    waited = esc.n_seen - esc.offered_at
    states = feed(esc, readings(40, 7, shifted), t0=10)
    assert states.index("maintenance_requested") + 1 + waited == CFG.rereference_bound
    assert "not applied" in log[-1][2]["reason"] and log[-1][2]["offer"]["offer"]
    esc2 = Escalator(CFG, jacobian=jacobian)
    feed(esc2, readings(10, 8, shifted))
    states = feed(esc2, readings(12, 9, lambda P, q: jacobian(q) @ np.array([3e-3, 2e-3])), t0=10)
    assert states[-1] == "maintenance_requested" and len(states) - states.index("maintenance_requested") > 1


def test_the_offer_survives_a_restart_and_a_halt():
    esc = Escalator(CFG, jacobian=jacobian)
    feed(esc, readings(10, 10, shifted))
    snap = esc.snapshot()
    again = Escalator(CFG, jacobian=jacobian)
    again.restore(snap)
    assert again.state == "rereference_offered" and again.offer == esc.offer
    again.halt("driver fault", 50.0)
    assert again.resume(51.0) and again.state == "rereference_offered"
    assert again.rereference(52.0)["translation_mm"] == esc.offer["translation_mm"]


def test_the_camera_frame_takes_the_offer_and_undoes_it():
    from dt_runtime.frames.registration import RigidTransform

    class T:  # the part of a twin MvsFrame touches
        T_mvs = RigidTransform(np.eye(3), np.array([1.0, 2.0, 3.0]))

    tw = T()
    f = MvsFrame(tw)  # type: ignore[arg-type]
    undo = f.apply({"translation_mm": [1.0, 0, 0], "rotation_mrad": [0, 0, 0]})
    assert tw.T_mvs.t == pytest.approx([0.999, 2.0, 3.0]) and f.to_dict()["mvs_rereferenced"]["count"] == 1
    saved = f.to_dict()["mvs_rereferenced"]
    undo()
    assert tw.T_mvs.t == pytest.approx([1.0, 2.0, 3.0]) and f.to_dict() == {}
    f.restore(saved)
    assert tw.T_mvs.t == pytest.approx([0.999, 2.0, 3.0])
    other = T()
    other.T_mvs = RigidTransform(np.eye(3), np.zeros(3))
    g = MvsFrame(other)  # type: ignore[arg-type]
    g.restore(saved)  # made on another twin's frame: not taken up
    assert other.T_mvs.t == pytest.approx([0, 0, 0])


def test_an_open_offer_is_untrusted_halts_under_the_policy_and_is_in_the_status_line():
    import threading

    from dt_runtime.service.counters import Counters
    from dt_runtime.service.health import StatusLine
    from dt_runtime.service.runtime_config import HaltConfig
    from dt_runtime.service.supervisor import Step, Supervisor

    esc = Escalator(CFG, jacobian=jacobian)
    feed(esc, readings(10, 11, shifted))
    n = Counters()
    sup = Supervisor(HaltConfig(), 0.1, esc, n, lambda: 5.0, threading.Event(), streaming=False,
                     store_failing=lambda: False)
    assert not sup.trusted() and sup.status() == ("degraded", "rereference_offered: commands sent uncorrected")
    text, fields = StatusLine(sup.status, n, esc, None, None)()
    assert "re-reference (dt ack --rereference)" in text and fields["rereference_offer"] == esc.offer
    halting = Supervisor(HaltConfig(on_untrusted="halt"), 0.1, esc, n, lambda: 5.0, threading.Event(),
                         streaming=False, store_failing=lambda: False)
    assert halting.next_step(6.0) is Step.WAIT and esc.state == "halted" and esc.halted_from == "rereference_offered"
    # applying the offer also ends the halt it caused
    assert esc.offer_open and esc.rereference(7.0)["n"] >= 6
    assert esc.state == "nominal" and esc.halt_reason is None and halting.next_step(8.0) is Step.MOVE
