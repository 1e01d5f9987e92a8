"""The point loop's speed-ups compute the same numbers as the code they replace (issue 23):
Eq. 17 with its budgets fixed once, the quantiles through scipy.special, the simulated arm's
kinematics computed once per joint state."""
import numpy as np
from scipy import stats

from dt_runtime.metrology import uncertainty as unc


def test_the_prepared_eq17_test_is_scipy_stats_t_test_bit_for_bit():
    rng = np.random.default_rng(3)
    u_diff, u_pred = rng.uniform(20e-6, 80e-6, 3), rng.uniform(10e-6, 50e-6, 3)
    dof_diff, dof_pred = np.array([12.0, np.inf, 40.0]), np.array([7.0, 30.0, np.inf])
    plan = unc.TTestPlan.of(u_diff, u_pred, dof_diff, dof_pred, 0.05)
    for _ in range(50):
        diff, pred = rng.normal(0, 1e-4, 3), rng.normal(0, 5e-5, 3)
        tt = plan(diff, pred)
        # the formula as it was written with scipy.stats
        u = np.sqrt(u_diff ** 2 + u_pred ** 2)
        t = (np.atleast_2d(diff) - np.atleast_2d(pred)) / u
        d = np.where(np.isfinite(plan.dof), plan.dof, 1e12)
        assert np.array_equal(tt.t, t)
        assert np.array_equal(tt.p_value, 2 * stats.t.sf(np.abs(t), d))
        assert np.array_equal(tt.t_crit, stats.t.ppf(0.975, d))
        assert np.array_equal(tt.passed, np.abs(t) <= stats.t.ppf(0.975, d))
    same = unc.t_test(diff, pred, u_diff, u_pred, dof_diff, dof_pred)
    assert np.array_equal(same.p_value, tt.p_value) and np.array_equal(same.dof, tt.dof)


def test_the_coverage_factor_is_the_student_t_quantile_bit_for_bit():
    dof = np.array([1.0, 2.0, 3.7, 9.0, 57.2, 1e4, np.inf, 0.3])
    k = unc.coverage_factor(dof)
    want = np.where(np.isfinite(dof), stats.t.ppf(0.975, np.where(np.isfinite(dof), np.maximum(dof, 1), 1)),
                    stats.norm.ppf(0.975))
    assert np.array_equal(k, want)
    assert k[-2] == stats.norm.ppf(0.975) and abs(k[1] - 4.30265272975) < 1e-10  # t(0.975, 2)


def test_the_simulated_arm_computes_fk_once_per_joint_state_and_the_same_numbers():
    from sim.kinematics import Arm  # a test may use sim; dt_runtime code may not

    cached, fresh = Arm(), Arm()
    try:
        rng = np.random.default_rng(0)
        qs = rng.uniform(-1, 1, (4, 6))
        for q in [qs[0], qs[1], qs[0], qs[0].copy(), qs[2], qs[3], qs[2]]:
            p, R = cached.fk(q)
            J = cached.jacobian(q)
            fresh._q = None  # forget: reset the joints and compute anew
            p0, R0 = fresh.fk(q)
            fresh._q = None
            assert np.array_equal(p, p0) and np.array_equal(R, R0)
            assert np.array_equal(J, fresh.jacobian(q))
            p[:] = 0.0  # the caller's copy: the cache is not touched
            assert np.array_equal(cached.fk(q)[0], p0)
        # the warm-started IK lands where a fresh arm's does, and the target is reached
        target = np.array([0.9, 0.1, 0.6])
        q1 = cached.ik(target, q_seed=cached.ik(np.array([0.9, 0.0, 0.7])))
        fresh._q = None
        assert np.linalg.norm(fresh.fk(q1)[0] - target) < 1e-6
    finally:
        cached.close()
        fresh.close()
