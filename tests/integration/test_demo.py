"""`dt demo --quick` end to end through the CLI: one JSON object, the paper's figures met."""
import json
import shutil

import pytest

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS

KEYS = {"precision_before_mm", "precision_after_mm", "improvement_pct", "true_rms_uncorrected_mm",
        "true_rms_corrected_mm", "true_error_reduction_pct", "coverage_95"}


@pytest.fixture(scope="module")
def quick(quick_demo):
    return quick_demo


def test_prints_exactly_one_json_object_with_the_contract_keys(quick):
    rc, stdout, out = quick
    assert rc == 0
    summary = json.loads(stdout)  # the whole of stdout is one object
    assert KEYS <= summary.keys()
    assert set(summary["coverage_95"]) == {"x", "y", "z"}
    assert json.loads((out / "summary.json").read_text()) == summary
    assert (out / "report.html").stat().st_size > 10_000
    assert (out / "model" / "twin.json").exists()


def test_quick_demo_meets_the_papers_figures(quick):
    s = json.loads(quick[1])
    assert s["improvement_pct"] >= 77.8
    assert s["true_error_reduction_pct"] >= 75.0
    # 28 validation points: one miss is 3.6 %, so the quick run can only show 96.4 % or 100 %;
    # the 90-99 % figure is measured by the full demo (docs/results.md).
    assert all(0.9 <= c <= 1.0 for c in s["coverage_95"].values())
    t3 = s["table3_as_is"]["e_lt_doe"]
    assert t3["x"]["std_mm"] > t3["y"]["std_mm"] > 0.15  # Table 3 scale, x largest


def test_unreachable_plan_targets_are_reported_before_anything_moves(tmp_path, capsys):
    for name in ("demo.yaml", "cell.yaml", "plan_quick.yaml", "plan_paper.yaml"):
        shutil.copy(CONFIGS / name, tmp_path / name)
    (tmp_path / "scenarios").mkdir()
    shutil.copy(CONFIGS / "scenarios" / "paper_default.yaml", tmp_path / "scenarios")
    (tmp_path / "plan_quick.yaml").write_text(
        (CONFIGS / "plan_quick.yaml").read_text() + "center_m: [1.9, 0.0, 0.55]\n")
    rc = main(["demo", "--quick", "--json", "--no-progress", "--config", str(tmp_path / "demo.yaml"),
               "--out", str(tmp_path / "out")])
    out = capsys.readouterr()
    assert rc == 2
    err = json.loads(out.out)["error"]
    assert "unreachable" in err and "target #" in err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_per_position_uncertainty_is_checked_inside_and_outside_the_calibrated_volume(quick):
    s = json.loads(quick[1])
    chk = s["coverage_check"]
    assert chk["inside"]["n"] >= 100 and chk["outside"]["n"] >= 100  # distinct targets each
    assert set(s["coverage_95_outside"]) == {"x", "y", "z"}
    assert all(0.85 <= c <= 1.0 for c in s["coverage_95_outside"].values())
    assert s["u_ratio_outside_inside"] > 1.0  # extrapolation states a larger uncertainty
    assert chk["inside"]["flagged_inside_fraction"] == 1.0 and chk["outside"]["flagged_inside_fraction"] == 0.0
    lo, hi = chk["outside"]["distance_mm"]
    assert 40.0 <= lo and hi <= 160.0  # the band, measured at the corrected commands


def test_the_saved_twin_states_the_uncertainty_of_each_corrected_position(quick, tmp_path):
    import numpy as np

    from dt_runtime.twin.twin import Twin

    twin = Twin.load(quick[2] / "model")
    assert twin.volume is not None and twin.position_u is not None
    pts = np.array(json.loads((quick[2] / "summary.json").read_text())["coverage_check"]["inside"]["distance_mm"])
    assert pts[0] < 0
    # A DOE-interior target and one 150 mm beyond the hull's +z face.
    inside_t = np.array([0.9, 0.0, 0.55])
    c_in = twin.correct(inside_t, 0.5)
    far_t = inside_t + np.array([0.0, 0.0, 0.0])
    while twin.volume.distance(far_t)[0] < 0.15:
        far_t = far_t + np.array([0.0, 0.0, 0.01])
    c_out = twin.correct(far_t, 0.5)
    assert c_in.inside and not c_out.inside and c_out.distance_m > 0.1
    assert np.all(c_out.U > c_in.U)
    labels = [c.label for c in c_in.budget.components]
    assert "lambda sigma_GP(c)" in labels and "kappa d(c)" in labels and "s(r_LT)" not in labels
    k_in = next(c for c in c_in.budget.components if c.label == "kappa d(c)")
    assert np.all(k_in.u == 0)  # no extrapolation term inside the hull
    # An older twin (no volume, no per-position data) still loads and states its global U.
    old = tmp_path / "old"
    shutil.copytree(quick[2] / "model", old)
    meta = json.loads((old / "twin.json").read_text())
    del meta["volume"], meta["position_uncertainty"]
    (old / "twin.json").write_text(json.dumps(meta))
    legacy = Twin.load(old).correct(inside_t, 0.5)
    assert legacy.inside and legacy.budget is None
    assert np.allclose(legacy.U, twin.uncertainty.tcp_c.U) and np.allclose(legacy.command, c_in.command)


def test_seed_2_passes_and_its_coverage_check_states_what_it_reached(tmp_path, capsys, caplog):
    """Seed 2's outside check once stopped the demo ("only 184 of 400 corrected commands
    reached"): from a far target the arm flips its elbow and many spare commands need a joint
    beyond its limit. The check states its coverage over the targets reached, and the validity
    block names why those positions are not covered (the point-noise camera: the arm's path and
    the check are the same as with the image pipeline, in 16 s of CPU instead of 19)."""
    rc = main(["demo", "--quick", "--seed", "2", "--camera", "sim_point", "--json", "--no-progress",
               "--out", str(tmp_path)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)
    outside = s["coverage_check"]["outside"]
    assert 100 <= outside["n"] < 200 and outside["n_requested"] == 200
    v = s["validity"]
    check = next(c for c in v["checks"] if c["check"] == "coverage_outside")
    assert v["status"] == "fail" and check["status"] == "fail" and check["n_requested"] == 200
    assert check["cause"].startswith("a joint configuration the DOE never measured")
    assert "validity: NOT VALID" in caplog.text  # --json: stdout is the object, the line is logged (stderr)


def test_a_negative_seed_is_refused_with_a_message(tmp_path, capsys):
    from dt_kernel.errors import ConfigError
    from dt_runtime.workflows.demo import run_demo

    with pytest.raises(SystemExit) as exc:
        main(["demo", "--quick", "--seed", "-1", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--seed: -1: a seed is a non-negative integer" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="seed"):  # the library refuses it too, before anything runs
        run_demo(tmp_path, quick=True, seed=-1)
    assert not any(tmp_path.iterdir())


@pytest.mark.soak
@pytest.mark.parametrize("seed", [0, 3, 4, 5, 6, 7, 11, 42])
def test_any_seed_runs_to_its_verdict(seed, tmp_path, capsys):
    """Every seed writes its summary and report and exits 0 (about 25 s of CPU each): a command
    the arm cannot reach from where it stands is skipped and listed (seed 42's corrected
    validation: 27 of 28), a coverage check states what it reached, and the verdict says whether
    the stated uncertainty held (seed 3's outside check: NOT VALID, a joint configuration the DOE
    never measured)."""
    rc = main(["demo", "--quick", "--seed", str(seed), "--json", "--no-progress", "--out", str(tmp_path)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)
    assert s["validity"]["status"] in ("ok", "warn", "fail") and (tmp_path / "report.html").is_file()
    assert s["n_validation"] >= 26 and s["coverage_check"]["inside"]["n"] >= 150
