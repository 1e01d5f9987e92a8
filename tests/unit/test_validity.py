"""The validity block (dt_runtime.analysis.validity): a stated uncertainty that does not cover the
errors is flagged with its likely cause, an honest one passes, a few targets cannot condemn it,
and Eq. 17 passing where the coverage fails is called out. Synthetic, seeded samples: every check
here takes milliseconds (the end-to-end flags are in test_deploy_effects.py and test_demo.py)."""
import numpy as np
import pytest

from dt_runtime.cli.demo import human
from dt_runtime.models.effects import Inputs
from dt_runtime.analysis import validity
from dt_runtime.analysis.validity import Eq17Rates, Sample, assess

U = np.array([60e-6, 30e-6, 45e-6])  # m, a per-position U(TCP_c) of the quick demo's size


def _targets(n_points: int, reps: int, rng) -> np.ndarray:
    pts = rng.uniform([0.6, -0.3, 0.2], [1.2, 0.3, 0.9], (n_points, 3))
    return np.repeat(pts, reps, axis=0)


def _ref(rng, n=200, temperature=(20.0, 22.0)) -> Inputs:
    """The DOE's conditions: elbow up, wrist positive, an hour at 20-22 deg C."""
    q = np.tile([0.1, 0.5, 0.8, 0.0, 0.7, 0.0], (n, 1)) + rng.normal(0, 0.05, (n, 6))
    return Inputs(commanded=rng.uniform(0.5, 1.0, (n, 3)), joints=q, t=np.linspace(0, 3600, n),
                  temperature=np.linspace(*temperature, n))


def _honest(rng, target: np.ndarray) -> np.ndarray:
    return rng.normal(0, 1, target.shape) * U / 1.96


def test_an_honest_uncertainty_passes(rng=np.random.default_rng(1)):
    tgt = _targets(200, 1, rng)
    v = assess([Sample("inside", "200 random targets", "true errors (simulator)", _honest(rng, tgt),
                       np.tile(U, (200, 1)), Inputs(commanded=tgt))], _ref(rng))
    assert v["status"] == "ok", v["line"]
    c = v["checks"][0]
    assert all(0.9 <= a["coverage"] <= 0.99 or a["status"] == "ok" for a in c["axes"].values())
    assert v["line"].startswith("validity: OK") and "cause" not in c


def test_a_u_covering_a_fifth_after_the_shop_warmed_fails_with_a_time_dependent_cause(rng=np.random.default_rng(2)):
    tgt = _targets(14, 2, rng)  # the quick plan: 14 points, 2 replications
    err = _honest(rng, tgt) * 0.3 + np.array([-86e-6, 0.0, -48e-6])  # the thermal demo's offsets (x, z)
    cond = Inputs(commanded=tgt, joints=np.tile([0.1, 0.5, 0.8, 0.0, 0.7, 0.0], (28, 1)),
                  t=np.linspace(3900, 4200, 28), temperature=np.linspace(25.6, 26.9, 28))
    v = assess([Sample("validation", "the 28 corrected validation positionings", "true errors (simulator)", err,
                       np.tile(U, (28, 1)), cond)], _ref(rng), campaign="out/thermal/campaign")
    c = v["checks"][0]
    assert v["status"] == "fail" and c["status"] == "fail"
    assert c["axes"]["x"]["status"] == "fail" and c["axes"]["z"]["status"] == "fail" and c["axes"]["y"]["status"] == "ok"
    # the interval is over the 14 distinct targets: replicates share their point's model error
    assert c["n"] == 28 and c["n_distinct"] == 14 and c["axes"]["x"]["interval_95"][1] < 0.9
    assert c["cause"] == "the model misses a time-dependent effect"
    assert "the temperature changed: 25.6-26.9 °C here, 20.0-22.0 °C during the DOE" in c["evidence"]
    assert "measured 5 min to 10 min after the DOE ended" in c["evidence"]
    assert "dt diagnose" in c["advice"] and "--campaign out/thermal/campaign --effects geometric,thermal" in c["advice"]
    line = v["line"]
    assert line.startswith("validity: NOT VALID: U(TCP_c) covers x ") and "likely cause: the model misses a time" in line


def test_misses_in_a_joint_configuration_the_doe_never_measured_are_named(rng=np.random.default_rng(3)):
    n = 200
    tgt = _targets(n, 1, rng)
    q = np.tile([0.1, 0.5, 0.8, 0.0, 0.7, 0.0], (n, 1))
    flipped = np.arange(n) < 150
    q[flipped, 2] *= -1  # elbow down: the seed-2 demo's arm after a far target
    err = _honest(rng, tgt)
    err[flipped] += 5 * U  # the map of elbow up is wrong there
    v = assess([Sample("outside", "200 random targets 50-150 mm outside the DOE hull", "true errors (simulator)",
                       err, np.tile(U, (n, 1)), Inputs(commanded=tgt, joints=q), requested=400, outside_hull=True)],
               _ref(rng))
    c = v["checks"][0]
    assert c["status"] == "fail" and c["n_requested"] == 400
    assert c["cause"].startswith("a joint configuration the DOE never measured")
    assert "150 of 200 positions were reached in (q3-,q5+)" in c["evidence"]
    assert "(the DOE's: (q3+,q5+))" in c["evidence"]


def test_a_shortfall_a_few_targets_cannot_establish_is_a_warning_not_a_failure(rng=np.random.default_rng(4)):
    tgt = _targets(14, 2, rng)
    err = np.zeros((28, 3))
    err[:3, 1] = 2 * U[1]  # 25 of 28 inside in y: 89 %, below the band, interval reaching it
    v = assess([Sample("validation", "28 positionings", "true errors (simulator)", err, np.tile(U, (28, 1)),
                       Inputs(commanded=tgt))], _ref(rng))
    c = v["checks"][0]
    assert c["axes"]["y"]["status"] == "warn" and c["status"] == "warn" and v["status"] == "warn"
    assert c["cause"].startswith("none found in the data: possibly chance with 14 targets")
    assert v["line"].startswith("validity: WARNING")


def test_a_uncertainty_far_larger_than_the_errors_is_a_warning(rng=np.random.default_rng(5)):
    tgt = _targets(800, 1, rng)
    v = assess([Sample("inside", "800 targets", "true errors (simulator)", _honest(rng, tgt) * 0.2,
                       np.tile(U, (800, 1)), Inputs(commanded=tgt))])
    c = v["checks"][0]
    assert c["status"] == "warn" and all(a["interval_95"][0] > 0.99 for a in c["axes"].values())
    assert "larger than the errors need" in c["finding"]


def test_eq17_passing_where_the_coverage_fails_is_called_out(rng=np.random.default_rng(6)):
    tgt = _targets(14, 2, rng)
    err = np.tile(3 * U, (28, 1))  # every position outside its U
    s = Sample("validation", "the 28 corrected validation positionings", "true errors (simulator)", err,
               np.tile(U, (28, 1)), Inputs(commanded=tgt))
    v = assess([s], None, ("validation", Eq17Rates(np.ones((28, 3), bool), np.array([0.13e-3, 0.06e-3, 0.09e-3]))))
    eq = v["checks"][1]
    assert eq["check"] == "eq17_vs_coverage" and eq["status"] == "fail"
    assert "in service the t-test would not notice" in eq["finding"]
    assert "Eq. 20: x 0.130 mm" in eq["evidence"] and "x 0.180 mm RMS" in eq["evidence"]
    assert "Eq. 17 passes x 100.0 %, y 100.0 %, z 100.0 % there" in v["line"]
    # and the other way: Eq. 17 failing where U covers the truth would raise false alarms
    ok = Sample("validation", "28 positionings", "true errors (simulator)", np.zeros((28, 3)), np.tile(U, (28, 1)),
                Inputs(commanded=tgt))
    passed = np.ones((28, 3), bool)
    passed[:20, 0] = False
    v = assess([ok], None, ("validation", Eq17Rates(passed, U)))
    assert v["checks"][1]["status"] == "fail" and "false maintenance requests" in v["checks"][1]["finding"]


def test_nothing_to_check_says_so():
    v = assess([], unchecked="the campaign has no validation phase")
    assert v["status"] == "unchecked" and v["checks"] == []
    assert v["line"] == "validity: NOT CHECKED: the campaign has no validation phase"


@pytest.mark.parametrize("p, n, status", [(0.5, 14, "fail"), (0.857, 14, "warn"), (1.0, 14, "ok"), (0.995, 200, "ok"),
                                          (0.95, 28, "ok"), (1.0, 1000, "warn")])
def test_axis_status_follows_the_interval_against_the_band(p, n, status):
    assert validity.axis_status(p, n)[0] == status


def test_the_demos_last_line_is_the_validity_line(rng=np.random.default_rng(7)):
    tgt = _targets(14, 2, rng)
    v = assess([Sample("validation", "the 28 corrected validation positionings", "true errors (simulator)",
                       np.tile(3 * U, (28, 1)), np.tile(U, (28, 1)), Inputs(commanded=tgt))])
    s = {"precision_before_mm": 0.447, "precision_after_mm": 0.114, "improvement_pct": 74.4,
         "true_rms_uncorrected_mm": 0.252, "true_rms_corrected_mm": 0.104, "true_error_reduction_pct": 58.6,
         "coverage_95": {"x": 0.0, "y": 0.0, "z": 0.0}, "n_validation": 28,
         "t_test_eq17": {"pass_fraction_all_axes": 1.0}, "validity": v, "twin": "out/thermal/model"}
    lines = human(s).splitlines()
    assert "at the 28 corrected validation positionings" in lines[2]  # not "inside the DOE volume"
    assert lines[-2] == "wrote out/thermal/report.html, out/thermal/summary.json and the twin out/thermal/model"
    assert lines[-1] == v["line"] and lines[-1].startswith("validity: NOT VALID")


def test_an_ok_with_every_error_covered_says_why_it_is_ok_and_what_100_percent_means(rng=np.random.default_rng(8)):
    # 28 targets all covered: 100.0 % against the band 90-99 % printed as a bare OK before
    tgt = _targets(28, 1, rng)
    v = assess([Sample("validation", "the 28 validation targets", "true errors (simulator)",
                       _honest(rng, tgt) * 0.3, np.tile(U, (28, 1)), Inputs(commanded=tgt))])
    assert v["status"] == "ok", v["line"]
    assert "100.0 %" in v["line"] and "above the band" in v["line"] and "28 distinct targets" in v["line"]
    assert "conservative" in v["line"]


def test_an_ok_within_the_band_adds_nothing(rng=np.random.default_rng(1)):
    tgt = _targets(200, 1, rng)
    v = assess([Sample("inside", "200 random targets", "true errors (simulator)", _honest(rng, tgt),
                       np.tile(U, (200, 1)), Inputs(commanded=tgt))], _ref(rng))
    assert all(a["coverage"] <= 0.99 for a in v["checks"][0]["axes"].values())  # 94.5, 93.5, 93.5 %
    assert v["line"].endswith("in every check (1)")


def test_a_stored_ok_line_is_restated_with_the_words_for_a_coverage_above_the_band(rng=np.random.default_rng(8)):
    tgt = _targets(28, 1, rng)
    v = assess([Sample("validation", "the 28 validation targets", "true errors (simulator)",
                       _honest(rng, tgt) * 0.3, np.tile(U, (28, 1)), Inputs(commanded=tgt))])
    old = dict(v, line=v["line"].split("; ")[0])  # as a summary written before said it: a bare OK
    assert "above the band" not in old["line"] and "above the band" in validity.restated(old)
    assert validity.restated({"status": "unchecked", "line": "validity: NOT CHECKED: x"}) == "validity: NOT CHECKED: x"
