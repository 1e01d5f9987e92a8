import numpy as np
import pytest

from dt_runtime.metrology import uncertainty as unc

from dt_kernel.units import M_PER_MM as MM  # noqa: E402  (the tests below read MM as metres per mm)


def paper_inputs(n=1000):
    """The paper's Table 2 / Table 4 / Sect. 3.1 / Sect. 3.3 figures (large dof assumed)."""
    return unc.MetrologyInputs(
        reprod_tcp=np.array([0.0037, 0.0059, 0.0072]) * MM, reprod_tcp_dof=n, resol_tcp=1e-6,
        reg_lt=(np.zeros(3), np.array([0.046, 0.042, 0.032]) * MM, n),
        reg_mvs=(np.zeros(3), np.array([0.080, 0.070, 0.042]) * MM, n),
        u_lt=0.0004 * MM,
        res_lt=(np.zeros(3), np.array([0.037, 0.034, 0.079]) * MM, n),
        res_mvs_lt=(np.zeros(3), np.array([0.069, 0.061, 0.093]) * MM, n),
        reprod_mvs=np.array([0.023, 0.019, 0.028]) * MM, reprod_mvs_dof=n, resol_mvs=5e-6,
        registration_term="spread")


def test_paper_eq19_and_eq18_are_reproduced():
    inp = paper_inputs()
    U19 = unc.budget_e_lt_hat(inp).expanded() / MM
    assert U19 == pytest.approx([0.117, 0.108, 0.170], abs=0.004)
    U18 = unc.budget_tcp_corrected(inp).expanded() / MM
    assert U18 == pytest.approx([0.118, 0.109, 0.171], abs=0.004)
    U22 = unc.budget_e_mvs_lt_hat(inp).expanded() / MM
    assert U22 == pytest.approx([0.230, 0.204, 0.214], rel=0.1)


def test_welch_satterthwaite_two_equal_components():
    b = unc.Budget("b", (unc.Component.type_a("a", 1.0, 10), unc.Component.type_a("b", 1.0, 10)))
    assert b.effective_dof() == pytest.approx([20, 20, 20])


def test_coverage_factors():
    assert unc.coverage_factor(float("inf")) == pytest.approx(1.959964, abs=1e-5)
    assert unc.coverage_factor(5.0) == pytest.approx(2.5706, abs=1e-4)


def test_budget_table_has_labels_and_shares():
    rows = unc.budget_tcp_corrected(paper_inputs()).table()
    labels = [r["component"] for r in rows]
    assert "reprod_TCP" in labels and "s(r_LT)" in labels and "u_LT" in labels
    shares = np.array([r["share_pct"] for r in rows[:-1]])
    assert shares.sum(axis=0) == pytest.approx([100, 100, 100], abs=0.1)


def test_t_test_false_alarm_rate_is_alpha_under_the_null():
    rng = np.random.default_rng(0)
    u1, u2 = np.array([1.0, 2.0, 0.5]), np.array([0.5, 1.0, 1.0])
    n = 20000
    diff = rng.normal(0, u1, (n, 3))
    pred = rng.normal(0, u2, (n, 3))
    tt = unc.t_test(diff, pred, u1, u2, 1e6, 1e6)
    rate = 1 - tt.passed.mean(axis=0)
    assert np.all((rate > 0.03) & (rate < 0.07))


def test_precision_figures():
    b = unc.budget_e_mvs_lt_hat(paper_inputs())
    pf = unc.precision_figures(np.array([0.628, 0.479, 0.288]) * MM, b)
    assert pf["before_avg_mm"] == pytest.approx(2 * (0.628 + 0.479 + 0.288) / 3)
    assert 70 < pf["improvement_pct"] < 85


def test_transform_mode_propagates_the_fitted_registration_only():
    import dataclasses
    lit = paper_inputs(n=100)
    tr = dataclasses.replace(lit, registration_term="transform")
    u_lit = unc.budget_e_lt_hat(lit).combined()
    u_tr = unc.budget_e_lt_hat(tr).combined()
    s_reg, s_res = np.array([0.046, 0.042, 0.032]) * MM, np.array([0.037, 0.034, 0.079]) * MM
    assert u_tr == pytest.approx(np.sqrt(s_reg ** 2 / 100 + s_res ** 2 + (0.0004 * MM) ** 2), rel=1e-9)
    assert np.all(u_tr < u_lit)
