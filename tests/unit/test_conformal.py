"""The held-out conformal factor of the stated U (metrology.conformal) and the adaptive scale in service
(twin.adaptive): the factor is the split conformal quantile, grouped by target point; it makes a U
that is too small cover 95 % of new exchangeable positions; an old twin loads with factor 1; the
adaptive scale keeps a drifting stream's coverage in the band where a fixed scale falls below."""
import numpy as np
import pytest

from dt_kernel.errors import ConfigError, ModelError
from dt_runtime.metrology import conformal
from dt_runtime.metrology.conformal import ConformalScale
from dt_runtime.twin.adaptive import AdaptiveCoverage


def test_with_one_row_per_point_the_factor_is_the_ceil_n_plus_1_times_95_pct_smallest_score():
    rng = np.random.default_rng(0)
    for n in (19, 20, 39, 40, 100, 137):
        s = rng.exponential(1.0, n)
        c, m, ok = conformal.grouped_quantile(s, np.arange(n))
        k = int(np.ceil((n + 1) * 0.95))
        assert ok and m == n and c == np.sort(s)[k - 1]


def test_replicates_of_a_point_share_its_weight():
    # 40 points, 3 rows each: the factor is where the summed per-point coverage reaches ceil(41 * 0.95) = 39
    rng = np.random.default_rng(1)
    s = rng.exponential(1.0, (40, 3))
    g = np.repeat(np.arange(40), 3)
    c, n, ok = conformal.grouped_quantile(s.ravel(), g)
    assert ok and n == 40
    assert (s <= c).mean(axis=1).sum() >= 39
    below = np.sort(s.ravel())[np.sort(s.ravel()) < c]
    assert below.size == 0 or (s <= below.max()).mean(axis=1).sum() < 39  # the smallest such score


def test_too_few_points_give_no_guarantee_and_factor_one():
    r = np.ones((18, 3))
    sc = conformal.calibrate(r, np.full((18, 3), 0.5), np.arange(18))
    assert sc.method == "none" and np.all(sc.factor == 1.0) and "fewer than the 19" in sc.guarantee


def test_a_u_too_small_by_half_is_widened_to_cover_95_pct_of_new_points():
    rng = np.random.default_rng(2)
    sigma = np.array([1.0, 2.0, 0.5])
    U = 1.96 * sigma / 2  # the GUM budget understates the spread by half
    n, reps = 200, 3
    r = rng.normal(0, 1, (n, 1, 1)) * sigma * 0.6 + rng.normal(0, 1, (n, reps, 3)) * sigma * 0.8
    sc = conformal.calibrate(r.reshape(-1, 3), np.broadcast_to(U, (n * reps, 3)), np.repeat(np.arange(n), reps))
    assert sc.method == conformal.METHOD and sc.n == n and sc.rows == n * reps
    assert np.all(sc.factor == pytest.approx(2.0, rel=0.15))
    new = rng.normal(0, 1, (5000, 1)) * sigma * 0.6 + rng.normal(0, 1, (5000, 3)) * sigma * 0.8
    cov = (np.abs(new) <= sc.factor * U).mean(axis=0)
    assert np.all((cov >= 0.93) & (cov <= 0.975)), cov
    assert np.all((np.abs(new) <= U).mean(axis=0) < 0.7)  # the GUM U alone


def test_a_u_large_enough_is_never_shrunk():
    rng = np.random.default_rng(3)
    r = rng.normal(0, 1, (100, 3))
    sc = conformal.calibrate(r, np.full((100, 3), 4.0), np.arange(100))
    assert np.all(sc.raw < 1) and np.all(sc.factor == 1.0) and not sc.applied


def test_the_scale_round_trips_and_an_old_twin_reads_as_none():
    sc = ConformalScale(np.array([1.2, 1.0, 1.5]), np.array([1.2, 0.9, 1.5]), 62, 558, conformal.METHOD,
                        conformal.guarantee())
    back = ConformalScale.from_dict(sc.to_dict(), "twin.json")
    assert np.array_equal(back.factor, sc.factor) and back.n == 62 and back.method == sc.method
    assert ConformalScale().method == "none" and np.all(ConformalScale().factor == 1)
    with pytest.raises(ModelError, match="factor"):
        ConformalScale.from_dict({**sc.to_dict(), "factor": [0.5, 1, 1]}, "twin.json")


def _stream(seed, T=6000):
    """Errors whose spread grows slowly from 1 to 3 (the stated U = 1.96: 95 % at the start)."""
    rng = np.random.default_rng(seed)
    sd = np.linspace(1.0, 3.0, T)[:, None] * np.array([1.0, 0.8, 1.2])
    return rng.normal(0, 1, (T, 3)) * sd, np.broadcast_to(1.96 * np.array([1.0, 0.8, 1.2]), (T, 3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_adaptive_scale_keeps_window_coverage_in_the_band_through_drift(seed):
    e, U = _stream(seed)
    aci = AdaptiveCoverage()
    covered = np.empty(e.shape, dtype=bool)
    for t in range(len(e)):
        covered[t] = np.abs(e[t]) <= aci.stated(U[t])
        aci.update(covered[t])
    fixed = np.abs(e) <= U
    W = 500
    win = np.array([covered[i:i + W].mean(axis=0) for i in range(0, len(e) - W + 1, W)])
    win_fixed = np.array([fixed[i:i + W].mean(axis=0) for i in range(0, len(e) - W + 1, W)])
    assert np.all((win >= 0.90) & (win <= 0.99)), win.min(axis=0)
    assert np.all(win_fixed[-1] < 0.6)  # the fixed (calibrated) scale falls far below the band
    assert aci.n == len(e) and np.all(aci.scale > 2.5)  # it followed the spread (x 3)


def test_window_miss_rate_is_alpha_plus_the_change_of_log_scale_over_gamma_w():
    e, U = _stream(5, 2000)
    aci = AdaptiveCoverage(bounds=(1e-3, 1e3))  # never clipped: the identity is exact
    logs, miss = [np.log(aci.scale)], []
    for t in range(len(e)):
        c = np.abs(e[t]) <= aci.stated(U[t])
        miss.append(~c)
        logs.append(np.log(aci.update(c)))
    miss_a, logs_a = np.array(miss), np.array(logs)
    a, b = 300, 1100
    assert miss_a[a:b].mean(axis=0) == pytest.approx(0.05 + (logs_a[b] - logs_a[a]) / (0.05 * (b - a)), abs=1e-12)


def test_adaptive_bounds_state_and_bad_settings():
    aci = AdaptiveCoverage(scale=np.array([1.0, 1.0, 1.0]))
    for _ in range(50):
        aci.update(np.array([True, True, True]))
    assert np.all(aci.scale == 1.0)  # the floor: never below the calibrated U
    for _ in range(2000):
        aci.update(np.array([False, True, True]))
    assert aci.scale[0] == pytest.approx(20.0) and aci.misses.tolist() == [2000, 0, 0]
    back = AdaptiveCoverage.from_dict(aci.to_dict())
    assert np.array_equal(back.scale, aci.scale) and back.n == aci.n
    for bad in ({"alpha": 0.0}, {"gamma": -1.0}, {"bounds": (2.0, 1.0)}):
        with pytest.raises(ConfigError):
            AdaptiveCoverage(**bad)
