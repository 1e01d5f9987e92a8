"""`dt compare` engine and report: figures of merit against numpy, the worst cell names an
injected regional error, the Eq. 17 failure fraction separates a consistent model from one that
misses an offset, the report is written, bad input fails clearly. Seeded, synthetic, fast."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dt_kernel.errors import DataError, ModelError
from dt_runtime.analysis.compare import AS_IS, EXPECTED_ANY_AXIS, compare
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.reports.compare_report import write_compare_report

SIGMA = 50e-6  # measurement noise, m
LO, HI = np.array([0.3, -0.4, 0.2]), np.array([0.9, 0.4, 0.8])
X_INJECT = LO[0] + 0.7 * (HI[0] - LO[0])  # inside the top third of x: region cells 'x+,..'


def true_error(P: np.ndarray) -> np.ndarray:
    """A smooth error map of about 1 mm (m)."""
    return 3e-3 * np.column_stack([0.3 * np.sin(4 * P[:, 0]) + 0.1 * P[:, 1],
                                   0.2 * np.cos(3 * P[:, 1]), 0.25 * P[:, 2] - 0.1 * P[:, 0]])


def make(seed: int, n: int = 300, u: bool = True, extra=None, payload=None) -> Dataset:
    rng = np.random.default_rng(seed)
    P = rng.uniform(LO, HI, (n, 3))
    E = true_error(P) + rng.normal(0, SIGMA, (n, 3))
    if extra is not None:
        E = E + extra(P)
    return Dataset(commanded=P, error=E, u=np.full((n, 3), SIGMA) if u else None,
                   speed=rng.choice([0.1, 0.25, 0.5], n),
                   payload=rng.choice([0.0, 5.0, 10.0], n) if payload is None else np.full(n, payload),
                   temperature=np.linspace(20, 24, n) + rng.normal(0, 0.1, n),
                   t=np.linspace(0, 3600, n), joints=rng.uniform(-np.pi, np.pi, (n, 6)),
                   lines=np.arange(2, n + 2))


@pytest.fixture(scope="module")
def gp_dir(tmp_path_factory):
    """A well-specified model (GP on the TCP, the true noise), fitted once, saved and reloaded by
    compare. Hyperparameters are fixed (standardised logs: length scale 1 input std, signal
    variance 1, the known noise) so the fixture builds only the posterior: the optimiser is
    test_gp's business, and it costs seconds."""
    ds = make(1)
    ys = ds.error.std(0)
    thetas = [np.array([0.0, 0.0, 0.0, 0.0, 2 * np.log(SIGMA / ys[j])]) for j in range(3)]
    d = tmp_path_factory.mktemp("models") / "gp_tcp"
    HybridModel((), gp_inputs="tcp").fit(ds, thetas=thetas).save(d)
    return d


@pytest.fixture(scope="module")
def flat_dir(tmp_path_factory):
    """A model that knows nothing (no effects, no GP): predicts 0."""
    d = tmp_path_factory.mktemp("models") / "flat"
    HybridModel((), gp_inputs="none").fit(make(1)).save(d)
    return d


def compare_json(*args, **kw):
    """compare's result as its JSON object (the dict `dt compare --json` prints), and the arrays."""
    res, arr = compare(*args, **kw)
    return res.to_dict(), arr


def test_figures_match_numpy(gp_dir):
    ds = make(2)
    res, arr = compare_json([gp_dir], ds)
    r = ds.error - HybridModel.load(gp_dir).predict(ds)
    norm = np.linalg.norm(r, axis=1)
    assert res["n"] == 300
    assert res["rmse_mm"] == pytest.approx(np.sqrt(np.mean(norm ** 2)) * 1e3, rel=1e-9)
    assert res["mae_mm"] == pytest.approx(norm.mean() * 1e3, rel=1e-9)
    assert res["max_mm"] == pytest.approx(norm.max() * 1e3, rel=1e-9)
    for k, ax in enumerate("xyz"):
        pa = res["per_axis"][ax]
        assert pa["rmse_mm"] == pytest.approx(np.sqrt(np.mean(r[:, k] ** 2)) * 1e3, rel=1e-9)
        assert pa["mean_mm"] == pytest.approx(r[:, k].mean() * 1e3, rel=1e-9, abs=1e-12)
        assert pa["max_mm"] == pytest.approx(np.abs(r[:, k]).max() * 1e3, rel=1e-9)
    asis = res["models"][0]
    assert asis["name"] == AS_IS
    assert asis["rmse_mm"] == pytest.approx(np.sqrt(np.mean(np.sum(ds.error ** 2, 1))) * 1e3, rel=1e-9)
    # the model removes most of the error and reaches the noise floor, sqrt(3) sigma
    assert res["rmse_mm"] < 0.3 * asis["rmse_mm"]
    assert res["noise_floor_mm"] == pytest.approx(np.sqrt(3) * SIGMA * 1e3)
    assert res["rmse_mm"] < 1.5 * res["noise_floor_mm"]
    np.testing.assert_allclose(arr["models"][-1]["residual"], r)
    json.dumps(res, allow_nan=False)  # JSON-ready, no NaN


def test_several_models_side_by_side(gp_dir, flat_dir):
    res, _ = compare_json([flat_dir, gp_dir], make(2), names=["nothing", "gp"])
    assert [m["name"] for m in res["models"]] == [AS_IS, "nothing", "gp"]
    assert res["primary"] == "gp" and res["rmse_mm"] == res["models"][-1]["rmse_mm"]
    # a model that predicts 0 is as good as no model
    assert res["models"][1]["rmse_mm"] == pytest.approx(res["models"][0]["rmse_mm"])
    assert res["models"][2]["rmse_mm"] < res["models"][1]["rmse_mm"]


def test_injected_region_is_named_worst(gp_dir):
    ds = make(3, extra=lambda P: np.where(P[:, :1] > X_INJECT, [1e-3, 0, 0], 0.0))
    res, _ = compare_json([gp_dir], ds)
    worst = res["worst_cells"]
    assert 1 <= len(worst) <= 5
    assert worst[0]["factor"] == "region" and worst[0]["cell"].startswith("x+")
    assert all(w["n"] >= 5 for w in worst)
    assert worst[0]["ratio"] > 1.3
    assert worst[0]["mean_mm"][0] == pytest.approx(1.0, abs=0.2)  # the cell's bias shows the +1 mm in x
    cells = {c["cell"]: c for c in res["breakdown"]["region"]}
    assert sum(c["n"] for c in cells.values()) == ds.n
    assert all(c["rmse_mm"] < 0.3 for name, c in cells.items() if name.startswith("x-"))


def test_breakdown_factors_present_and_constant_skipped(gp_dir):
    res, arr = compare_json([gp_dir], make(2))
    assert set(res["breakdown"]) == {"region", "speed", "payload", "temperature", "time", "configuration"}
    assert [c["cell"] for c in res["breakdown"]["speed"]] == ["100 mm/s", "250 mm/s", "500 mm/s"]
    assert {c["cell"] for c in res["breakdown"]["configuration"]} == {"q3+,q5+", "q3+,q5-", "q3-,q5+", "q3-,q5-"}
    for cells in res["breakdown"].values():
        assert sum(c["n"] for c in cells) == 300
    res2, _ = compare_json([gp_dir], make(2, payload=5.0))
    assert "payload" not in res2["breakdown"]


def test_failure_fraction_consistent_vs_missed_offset(gp_dir, flat_dir):
    res, arr = compare_json([gp_dir], make(4))
    f = res["failures"]
    assert f["expected_fraction_if_consistent"] == pytest.approx(EXPECTED_ANY_AXIS)
    assert all(v <= 0.10 for v in f["per_axis"].values()), f["per_axis"]  # 5 % per axis expected
    assert f["fraction"] <= 0.22  # 14.3 % expected over three axes
    assert "ux, uy, uz" in res["t_test"]["u_meas_source"]
    fail_rows = np.flatnonzero(arr["models"][-1]["fail"].any(1))
    assert f["count"] == len(fail_rows) and f["rows"] == fail_rows[:50].tolist()
    assert f["lines"] == (fail_rows[:50] + 2).tolist()  # file lines of the failing rows
    # the same data with an offset the model never saw: nearly every row fails
    off, _ = compare_json([gp_dir, flat_dir], make(4, extra=lambda P: np.tile([0, 0, 0.4e-3], (len(P), 1))),
                     names=["gp", "flat"])
    assert off["models"][1]["failures"]["fraction"] > 0.9  # the gp model
    assert off["models"][1]["failures"]["per_axis"]["z"] > 0.9
    assert off["failures"]["fraction"] > 0.9  # flat: predicts nothing


def test_without_u_the_models_noise_is_used_and_said(gp_dir):
    res, _ = compare_json([gp_dir], make(4, u=False))
    assert res["noise_floor_mm"] is None
    assert "not in the dataset" in res["t_test"]["u_meas_source"]
    assert res["failures"]["fraction"] <= 0.25
    only_asis, _ = compare_json([], make(4, u=False))
    assert only_asis["failures"] is None and only_asis["primary"] == AS_IS


def test_report_written(gp_dir, flat_dir, tmp_path):
    ds = make(3, extra=lambda P: np.where(P[:, :1] > X_INJECT, [1e-3, 0, 0], 0.0))
    res, arr = compare_json([flat_dir, gp_dir], ds)
    path = write_compare_report(res, arr, tmp_path / "rep")
    html = path.read_text(encoding="utf-8")
    assert path.name == "report.html"
    for title in ("Models side by side", "Where the model fails", "Residual against each factor",
                  "Normality of the residuals", "Breakdown by factor", "Model parameters"):
        assert title in html
    assert html.count("<img ") >= 4  # steps, maps, factors, normal plot
    assert "Not shown" not in html  # every block rendered
    assert "noise floor" in html and "/ mm" in html
    assert res["worst_cells"][0]["cell"] in html
    back = json.loads((tmp_path / "rep" / "compare.json").read_text(encoding="utf-8"))
    assert {"n", "rmse_mm", "mae_mm", "per_axis", "failures", "models"} <= set(back)


def test_bad_input_raises_clearly(gp_dir, tmp_path):
    with pytest.raises(ModelError, match="no such model directory"):
        compare([tmp_path / "nope"], make(2))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelError, match="not a model directory"):
        compare([tmp_path / "empty"], make(2))
    empty = Dataset(commanded=np.zeros((0, 3)), error=np.zeros((0, 3)))
    with pytest.raises(DataError, match="no data rows"):
        compare([gp_dir], empty)
    with pytest.raises(DataError, match="names"):
        compare([gp_dir], make(2), names=["a", "b"])


# --------------------------------------------------------------------------- through the `dt` CLI

def _dt(capsys, *argv) -> tuple[int, dict]:
    from dt_runtime.cli.main import main

    code = main([*argv, "--json", "--no-progress"])
    return code, json.loads(capsys.readouterr().out)


def test_cli_fit_then_compare_held_out_side_by_side(capsys, tmp_path):
    """`dt fit` twice (no GP knowledge of the regional bias, then a GP on the TCP), `dt compare`
    of both on the training file with --cv: the figures are held out and the GP column lower."""
    from dt_runtime.measurements.dataset import write_table

    ds = make(5, extra=lambda P: np.where(P[:, :1] > X_INJECT, [1e-3, 0, 0], 0.0))
    ds.point_id = np.arange(ds.n)
    csv = write_table(ds, tmp_path / "data.csv")
    for name, gp in (("flat", "none"), ("gp", "tcp")):
        code, fit = _dt(capsys, "fit", "--data", str(csv), "--gp-inputs", gp, "--out", str(tmp_path / name))
        assert code == 0 and fit["n"] == 300
    code, res = _dt(capsys, "compare", "--data", str(csv), "--model", str(tmp_path / "flat"),
                    "--model", str(tmp_path / "gp"), "--cv", "4", "--report", str(tmp_path / "rep"))
    assert code == 0
    assert [m["name"] for m in res["models"]] == [AS_IS, "flat", "gp"]
    assert res["heldout"]["folds"] == 4
    assert {"n", "rmse_mm", "mae_mm", "per_axis", "failures"} <= set(res)
    assert res["models"][2]["rmse_mm"] < 0.5 * res["models"][1]["rmse_mm"]
    # held out is worse than the model's own fit on its training rows (it cannot remember a point)
    _, saved = _dt(capsys, "compare", "--data", str(csv), "--model", str(tmp_path / "gp"))
    assert saved["heldout"] is None and saved["rmse_mm"] < res["rmse_mm"]
    html = (tmp_path / "rep" / "report.html").read_text(encoding="utf-8")
    assert "Held-out 3D RMS" in html and "4-fold cross-validation" in html


def test_cli_compare_bad_model_is_one_json_error(capsys, tmp_path):
    from dt_runtime.measurements.dataset import write_table

    csv = write_table(make(2, n=20), tmp_path / "d.csv")
    code, res = _dt(capsys, "compare", "--data", str(csv), "--model", str(tmp_path / "missing"))
    assert code == 2 and "no such model directory" in res["error"]


def test_comparing_on_the_training_file_warns_that_the_figures_are_in_sample(capsys, tmp_path):
    from dt_runtime.measurements.dataset import write_table

    ds = make(6)
    ds.point_id = np.arange(ds.n) // 2  # two replicates per point
    csv = write_table(ds, tmp_path / "train.csv")
    other = write_table(make(7), tmp_path / "other.csv")
    code, _ = _dt(capsys, "fit", "--data", str(csv), "--gp-inputs", "tcp", "--out", str(tmp_path / "m"))
    assert code == 0
    code, res = _dt(capsys, "compare", "--data", str(csv), "--model", str(tmp_path / "m"),
                    "--report", str(tmp_path / "rep"))
    assert code == 0 and res["in_sample"] == ["m"]
    html = (tmp_path / "rep" / "report.html").read_text()
    assert "in-sample figures" in html and "one marker per commanded point" in html
    code, res = _dt(capsys, "compare", "--data", str(other), "--model", str(tmp_path / "m"))
    assert code == 0 and res["in_sample"] == []
    code, res = _dt(capsys, "compare", "--data", str(csv), "--model", str(tmp_path / "m"), "--cv", "3")
    assert code == 0 and res["in_sample"] == []  # held out: no warning


def test_rows_outside_the_training_domain_are_counted(capsys, tmp_path):
    from dt_runtime.measurements.dataset import write_table

    train = make(8)
    csv = write_table(train, tmp_path / "train.csv")
    code, _ = _dt(capsys, "fit", "--data", str(csv), "--gp-inputs", "tcp", "--out", str(tmp_path / "m"))
    assert code == 0
    test = make(9)
    test.commanded = test.commanded.copy()
    test.commanded[:50, 0] += 1.5  # 50 rows beyond the training box in x
    test.joints = test.joints.copy()
    test.joints[50:60, 3] = 4.5  # 10 rows with a wrist angle the training never reached (259 deg)
    code, res = _dt(capsys, "compare", "--data", str(write_table(test, tmp_path / "t.csv")),
                    "--model", str(tmp_path / "m"))
    out = res["models"][-1]["outside_training"]

    assert code == 0 and out["rows"] == 60 and out["columns"] == {"x": 50, "q4": 10}


def test_residual_against_each_factor_draws_every_model_and_categories_as_categories(gp_dir, flat_dir,
                                                                                      monkeypatch):
    """Every model's curve on every factor (the arrays once held only 'as is' and the last model);
    the direction of approach (-1/+1) and the joint configuration are categories: one marker per
    model and category, no line through 0."""
    from dt_runtime.reports import compare_report

    res, arr = compare_json([flat_dir, gp_dir], make(2), names=["nothing", "gp"])
    assert [m["name"] for m in arr["models"]] == [AS_IS, "nothing", "gp"]
    figs = []
    monkeypatch.setattr(compare_report, "fig_to_img_tag", lambda fig, **kw: figs.append(fig) or "<img>")
    compare_report._fig_factors(res, arr)
    axes = [ax for ax in figs[0].axes if ax.get_visible()]
    names = {ax.get_xlabel(): ax for ax in axes}
    assert {"speed / (mm/s)", "payload / kg", "temperature / °C", "time from start / s", "q3 / deg",
            "approach of q1", "joint configuration"} <= set(names)
    for ax in axes:
        assert [ln.get_label() for ln in ax.lines] == [AS_IS, "nothing", "gp"], ax.get_xlabel()
    approach = names["approach of q1"]
    assert [t.get_text() for t in approach.get_xticklabels()] == ["−", "+"]
    assert all(ln.get_linestyle() == "None" and len(ln.get_xdata()) == 2 for ln in approach.lines)
    config = names["joint configuration"]
    assert [t.get_text() for t in config.get_xticklabels()] == ["q3+,q5+", "q3+,q5-", "q3-,q5+", "q3-,q5-"]
    assert names["speed / (mm/s)"].lines[1].get_linestyle() == "-"  # a numeric factor keeps its line
