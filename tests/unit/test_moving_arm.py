"""A moving arm: readings compared with the path at their mid-exposure time, the timing term of
their uncertainty (metrology.timing), and the servo lag learnt and removed (programs.lag)."""
from __future__ import annotations

import numpy as np
import pytest

from dt_kernel.errors import DataError
from dt_runtime.metrology.timing import TimedPath, compare_at
from dt_runtime.programs.lag import compensate, estimate_lag

RATE = 500.0  # Hz


def circle(speed_m_s: float, radius: float = 0.1, seconds: float = 3.0, rate: float = RATE) -> TimedPath:
    t = np.arange(0.0, seconds, 1.0 / rate)
    a = speed_m_s / radius * t
    return TimedPath(t, np.column_stack([0.6 + radius * np.cos(a), radius * np.sin(a), 0.5 + 0 * t]))


def follow(path: TimedPath, T: float, substeps: int = 10) -> np.ndarray:
    """A first-order servo follower x' = (c - x) / T tracking the streamed set-points (each held
    for its period), integrated exactly per substep; its position at each set-point time."""
    x = path.p[0].copy()
    out = np.empty_like(path.p)
    dt = np.diff(path.t, append=path.t[-1] + path.t[1] - path.t[0]) / substeps
    for i, c in enumerate(path.p):
        out[i] = x
        for _ in range(substeps):
            x = c + (x - c) * np.exp(-dt[i] / T)
    return out


def test_a_timed_path_is_checked_and_interpolated():
    with pytest.raises(DataError, match="must increase: set-point 2"):
        TimedPath(np.array([0.0, 1.0, 1.0]), np.zeros((3, 3)))
    with pytest.raises(DataError, match="non-finite"):
        TimedPath(np.array([0.0, 1.0]), np.array([[0, 0, 0], [np.nan, 0, 0]]))
    with pytest.raises(DataError, match="n >= 2"):
        TimedPath(np.array([0.0]), np.zeros((1, 3)))
    p = TimedPath(np.array([0.0, 0.5, 1.5]), np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.2, 0]]))
    c, v = p.at(0.25)
    assert np.allclose(c, [0.05, 0, 0]) and np.allclose(v, [0.2, 0, 0])
    c, v = p.at(1.0)
    assert np.allclose(c, [0.1, 0.1, 0]) and np.allclose(v, [0, 0.2, 0])
    with pytest.raises(DataError, match="outside the path"):
        p.at(1.6)


def test_the_timing_term_widens_a_moving_reading_and_refuses_when_it_dominates():
    p = circle(0.25)
    rest = TimedPath(np.array([0.0, 1.0]), np.array([[0.6, 0, 0.5], [0.6, 0, 0.5]]))
    r = compare_at(rest, 0.5, u_time_s=1e-3, u_reading=20e-6)
    assert r.ok and np.allclose(r.u_timing, 0) and np.allclose(r.u_total, 20e-6)  # at rest: as a point
    r = compare_at(p, 1.0, u_time_s=0.1e-3, u_reading=50e-6)
    assert r.ok and np.allclose(r.u_timing, np.abs(r.velocity) * 0.1e-3)
    assert np.isclose(np.linalg.norm(r.velocity), 0.25, rtol=1e-3)
    assert np.allclose(r.u_total, np.hypot(50e-6, r.u_timing))
    r = compare_at(p, 1.0, u_time_s=2e-3, u_reading=50e-6)  # 0.5 mm of timing against 50 um
    assert not r.ok and "timing dominates" in r.refused and "250 mm/s" in r.refused
    r = compare_at(p, 5.0, u_time_s=0.1e-3, u_reading=50e-6)
    assert not r.ok and "outside the path" in r.refused
    with pytest.raises(DataError, match="u_time_s"):
        compare_at(p, 1.0, u_time_s=float("nan"), u_reading=50e-6)


def test_eq17_holds_its_level_on_a_moving_arm_only_with_the_timing_term():
    """Readings of an arm moving at 250 mm/s, each exposed at a time known to 0.4 ms (u_t) and
    measured with 50 um per axis: tested at the mid-exposure time with the timing term, 95 % of
    the |t| stay within 1.96; without it far fewer (the t-test would cry wolf on a healthy arm)."""
    rng = np.random.default_rng(7)
    p = circle(0.25)
    u_t, u_r = 0.4e-3, 50e-6
    t_nom = rng.uniform(0.2, 2.8, 4000)
    t_true = t_nom + rng.normal(0, u_t, t_nom.size)
    with_term, without = [], []
    for tn, tt in zip(t_nom, t_true):
        truth, _ = p.at(tt)
        m = truth + rng.normal(0, u_r, 3)
        r = compare_at(p, tn, u_t, u_r, max_timing_ratio=10.0)
        with_term.append(np.abs((m - r.commanded) / r.u_total) <= 1.96)
        without.append(np.abs((m - r.commanded) / u_r) <= 1.96)
    cov_with, cov_without = float(np.mean(with_term)), float(np.mean(without))
    assert 0.94 <= cov_with <= 0.96, cov_with
    assert cov_without < 0.90, cov_without


@pytest.mark.parametrize("speed", [0.1, 0.25, 0.5])
def test_the_servo_lag_is_learnt_from_one_pass_and_fed_forward(speed):
    """A first-order follower with an 8 ms time constant on a 100 mm circle, each set-point held
    for its 2 ms period (a zero-order hold: 1 ms more of lag): estimate_lag finds 9 ms, and the
    compensated path streamed to the same follower leaves under a hundredth of the path error."""
    T = 8e-3
    p = circle(speed)
    arm = follow(p, T)
    lag = estimate_lag(p, p.t, arm)
    expected = T + 0.5 / RATE
    assert abs(lag.tau_s - expected) < 0.02 * expected and lag.u_tau_s < 0.01 * expected
    on = p.t >= 0.5
    before = np.sqrt(np.mean(np.sum((arm - p.p)[on] ** 2, axis=1)))
    arm2 = follow(compensate(p, lag), T)
    after = np.sqrt(np.mean(np.sum((arm2 - p.p)[on] ** 2, axis=1)))
    assert np.isclose(before, speed * expected, rtol=0.05)  # the lag's error: v tau
    assert after < 0.01 * before, (before, after)
    assert lag.to_dict()["tau_ms"] == pytest.approx(9.0, rel=0.02)


@pytest.mark.parametrize("speed", [0.1, 0.25])
def test_a_servo_follower_is_inverted_not_only_shifted(speed):
    """sim.servo's follower (servoj: look-ahead 30 ms, gain 1200, under-damped) on the circle: the
    fit finds a = T and b + a^2 = 1/K, and the feed-forward d + T d' + d''/K leaves under a
    twentieth of the path error a plain time shift by T leaves (its (1/K - T^2/2) d'' on the curve)."""
    from sim.servo import ServoFollower

    def servo(path):
        f, out = ServoFollower(path.p[0], 0.03, 1200.0), np.empty_like(path.p)
        for i, c in enumerate(path.p):
            out[i], _ = f.step(c, 1.0 / RATE)
        return out

    p = circle(speed)
    lag = estimate_lag(p, p.t, servo(p))
    assert lag.tau_s == pytest.approx(0.03, rel=0.01) and lag.accel_s2 == pytest.approx(1 / 1200.0, rel=0.02)
    on = p.t >= 0.5

    def rms(x):
        return np.sqrt(np.mean(np.sum((x - p.p)[on] ** 2, axis=1)))

    shifted, inverted = rms(servo(compensate(p, lag.tau_s))), rms(servo(compensate(p, lag)))
    assert inverted < 0.2 * shifted and inverted < 0.01 * rms(servo(p)), (shifted, inverted)


def test_the_servo_is_identified_and_inverted_through_the_acceleration_steps(tmp_path):
    """A line-arc-line path at 500 mm/s with the trapezoid's acceleration steps, through sim.servo's
    follower (look-ahead 30 ms, gain 1200) at 125 Hz: the pass identifies the follower (T, 1/K)
    within 1 %, and its inverse as the feed-forward leaves under a fifth of what the series
    e = a c' + b c'' fitted by least squares to the same pass leaves (the transients after each
    step bias that fit), and on the jerk-limited profile less again."""
    from dt_runtime.programs.lag import LagEstimate
    from dt_runtime.programs.path import interpolate, read_path
    from sim.servo import ServoFollower

    def servo(commands, start):  # the arm waits where the path starts, not at a feed-forward's first command
        f, out = ServoFollower(start, 0.03, 1200.0), np.empty_like(commands)
        for i, c in enumerate(commands):
            out[i], _ = f.step(c, 1.0 / 125.0)
        return out

    text = ("start: [820, -75, 550]\nspeed: 500\nacceleration: 4000\n{}segments:\n"
            "  - line: {{to: [950, -75, 550]}}\n  - arc: {{via: [1025, 0, 550], to: [950, 75, 550]}}\n"
            "  - line: {{to: [820, 75, 550]}}\n")
    left = {}
    for name, extra in (("trapezoid", ""), ("s_curve", "jerk: 40000\n")):
        (tmp_path / f"{name}.yaml").write_text(text.format(extra))
        sp = interpolate(read_path(tmp_path / f"{name}.yaml"), 125.0)
        p = TimedPath(sp.t, sp.p)
        lag = estimate_lag(p, p.t, servo(p.p, p.p[0]), max_lag_s=0.2)
        assert lag.servo is not None
        T, w, delay = lag.servo
        assert T + delay == pytest.approx(0.03, rel=0.01) and w == pytest.approx(1 / 1200.0, rel=0.01)
        keep = p.t >= 0.2  # the series fit as estimate_lag's first step does it
        v = np.gradient(p.p, p.t, axis=0)
        A = np.column_stack([v[keep].ravel(), np.gradient(v, p.t, axis=0)[keep].ravel()])
        (a, b), *_ = np.linalg.lstsq(A, (p.p - servo(p.p, p.p[0]))[keep].ravel(), rcond=None)
        series = LagEstimate(a, 0, b + a * a, 0, lag.n, 0, 0)

        def rms(x, p=p):
            return np.sqrt(np.mean(np.sum((x - p.p) ** 2, axis=1)))

        left[name] = rms(servo(compensate(p, lag).p, p.p[0]))
        assert left[name] < 0.2 * rms(servo(compensate(p, series).p, p.p[0])), name
    assert left["s_curve"] < left["trapezoid"] < 50e-6, left


def test_estimate_lag_refuses_too_little_data():
    p = circle(0.25)
    with pytest.raises(DataError, match="at least 10"):
        estimate_lag(p, p.t[:20], p.p[:20])
    with pytest.raises(DataError, match="finite time >= 0"):
        compensate(p, -1.0)
    still = TimedPath(p.t, np.repeat(p.p[:1], p.t.size, axis=0))
    with pytest.raises(DataError, match="moves and changes speed"):
        estimate_lag(still, p.t, still.p)


def test_settled_marks_the_transient_after_each_step_of_the_acceleration():
    """A trapezoid along x: accelerate for 0.1 s, cruise 1 s, decelerate 0.1 s; the readings in
    the 0.2 s after each of the four steps of its acceleration are in the servo's transient."""
    from dt_runtime.programs.lag import SETTLE_S, settled

    t = np.arange(0.0, 1.6, 1.0 / RATE)
    a, v = 1.0, 0.1
    x = np.where(t < 0.1, 0.5 * a * t ** 2, 0.005 + v * (t - 0.1))
    x = np.where(t > 1.1, 0.005 + v + v * (t - 1.1) - 0.5 * a * (t - 1.1) ** 2, x)
    x = np.where(t > 1.2, x[np.searchsorted(t, 1.2)], x)
    ok = settled(TimedPath(t, np.column_stack([x, 0 * t, 0 * t])))
    assert not ok[np.searchsorted(t, 0.05)] and not ok[np.searchsorted(t, 0.25)]  # the ramp and after it
    assert ok[np.searchsorted(t, 0.1 + SETTLE_S + 0.05)] and ok[np.searchsorted(t, 1.0)]  # cruising, settled
    assert not ok[np.searchsorted(t, 1.15)] and not ok[np.searchsorted(t, 1.35)]  # the stop and after it
    assert ok[-1]  # standing still long after
    still = TimedPath(t, np.zeros((t.size, 3)) + 0.5)
    assert settled(still).all()


def test_a_stored_lag_estimate_reads_back_the_same():
    from dt_runtime.programs.lag import LagEstimate

    e = LagEstimate(0.0303, 3e-5, 7.9e-4, 3e-5, 278, 3.03e-3, 8.4e-5, (0.0302, 8.3e-4, 1e-4))
    back = LagEstimate.from_dict(e.to_dict())
    assert np.allclose(back.servo, e.servo, rtol=1e-12)
    old = {k: v for k, v in e.to_dict().items() if k != "servo"}  # stored by a version without the model
    assert LagEstimate.from_dict(old).servo is None
    assert np.allclose([back.tau_s, back.u_tau_s, back.accel_s2, back.u_accel_s2, back.rms_before_m,
                        back.rms_after_m], [e.tau_s, e.u_tau_s, e.accel_s2, e.u_accel_s2, e.rms_before_m,
                                            e.rms_after_m], rtol=1e-12) and back.n == e.n
