"""`dt diagnose --auto`: the whole compare/diagnose/add loop as one command (forward selection over
the effects and the GP's inputs, Bonferroni per step, a minimum effect size)."""
from __future__ import annotations

import contextlib
import io
import json

import pytest

from dt_runtime.analysis.diagnose import DiagnoseOptions, diagnose
from dt_runtime.reports.verdicts import verdict
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    out = tmp_path_factory.mktemp("auto")
    files = {}
    for name in ("backlash", "none"):
        files[name] = out / f"{name}.csv"
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["simulate", "--scenario", str(CONFIGS / "scenarios" / "hidden" / f"{name}.yaml"),
                         "--out", str(files[name]), "--json"]) == 0
    return files


@pytest.mark.parametrize("effects, gp_inputs", [((), "tcp_speed"), (("geometric",), "tcp_speed"), ((), "joints")],
                         ids=["paper", "geometric", "gp-joints"])
def test_auto_names_the_hidden_backlash_from_every_start_and_reaches_the_floor(hidden, effects, gp_inputs):
    """The same named effects from the paper's model, from geometric and from a GP on the joints
    (the effect terms are estimated jointly with the GP: from the paper's model the ordinary
    fit made backlash look harmful, "explains -117.7 %")."""
    r = diagnose(hidden["backlash"], DiagnoseOptions(effects=effects, gp_inputs=gp_inputs,
                                                     robot=CONFIGS / "robots" / "cobot_hc20_like.yaml", auto=True))
    assert "+backlash" in r.added and set(r.effects) == {"geometric", "backlash"}
    assert r.added[0] == "+backlash"  # the biggest step first
    assert r.floor_ratio is not None and r.floor_ratio < 1.3
    assert r.steps[0].rmse_mm > 2 * r.final_rmse_mm  # the backlash was most of the held-out error
    assert r.steps[0].p_value < r.steps[0].alpha and r.steps[0].explained_fraction > 0.5
    assert "at the noise floor" in verdict(r)


def test_auto_on_a_clean_arm_adds_nothing_but_geometric(hidden, capsys):
    rc = main(["diagnose", "--data", str(hidden["none"]), "--auto", "--json", "--no-progress"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert set(out["added"]) <= {"+geometric"}
    assert out["floor_ratio"] < 1.3
    step = out["steps"][0]
    assert {"model", "rmse_mm", "u_rmse_mm", "change", "p_value", "explained_fraction", "alpha"} <= step.keys()
    # the level of each step is alpha / candidates tested there (Bonferroni)
    assert step["alpha"] < out["alpha"]


def _with_humidity(src, dst, effect_mm: float, seed: int = 3):
    """The clean arm's file plus a logged column no effect term reads: 'humidity' (%), drifting
    over the campaign; the error gains effect_mm per 10 % of it along x and z."""
    import numpy as np

    from dt_runtime.measurements.dataset import read_table, write_table

    ds = read_table(src)
    rng = np.random.default_rng(seed)
    # one value per visit of a point (a slow random walk over the campaign)
    h = 45 + np.cumsum(rng.normal(0, 1.5, ds.n))
    ds.error = ds.error + np.outer((h - h.mean()) / 10 * effect_mm * 1e-3, [1.0, 0.0, 0.5])
    ds.measured = None  # the error columns carry it
    write_table(ds, dst)
    lines = dst.read_text().splitlines()
    dst.write_text("\n".join([lines[0] + ",humidity,operator"] +
                             [f"{line},{v:.3f},ana" for line, v in zip(lines[1:], h)]) + "\n")
    return dst


def test_an_error_driven_by_an_unknown_column_is_flagged(hidden, tmp_path):
    r = diagnose(_with_humidity(hidden["none"], tmp_path / "h.csv", 0.03), DiagnoseOptions(auto=True))
    top = r.columns[0]
    assert top["column"] == "humidity" and top["significant"] and top["explained_fraction"] > 0.3
    assert "follows the column 'humidity'" in verdict(r) and "declare an effect of your own" in verdict(r)
    assert "operator" not in {c["column"] for c in r.columns}  # a text column is not a factor


def test_a_column_without_effect_is_not_flagged(hidden, tmp_path):
    r = diagnose(_with_humidity(hidden["none"], tmp_path / "h0.csv", 0.0), DiagnoseOptions(auto=True))
    hum = next(c for c in r.columns if c["column"] == "humidity")
    assert not hum["significant"]
    assert "humidity" not in verdict(r)


def test_the_instruments_mpe_is_the_noise_floor_when_the_data_state_none(hidden, tmp_path, capsys):
    from dt_runtime.measurements.dataset import read_table, write_table

    ds = read_table(hidden["none"])
    ds.u = None  # a tracker export states no per-point uncertainty
    csv = write_table(ds, tmp_path / "no_u.csv")
    assert main(["diagnose", "--data", str(csv), "--auto", "--json", "--no-progress"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["noise_floor_mm"] is None and "not known" in out["verdict"]
    assert main(["diagnose", "--data", str(csv), "--auto", "--mpe-mm", "0.02", "--json", "--no-progress"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["noise_floor_mm"] == pytest.approx(0.02) and "at the noise floor" in out["verdict"]


def test_several_files_are_one_campaign_and_sessions_that_disagree_are_a_finding(hidden, tmp_path, capsys):
    """Two files of the simulated cell with two seeds, which draw two arms (the plant's geometric
    errors come from the seed): one command reads both as one campaign (time continues, point ids do
    not collide), holds each session out, finds how they differ (the set-up and the joint zeros) and
    says not to deploy: each arm is predicted worse than no correction by a model of the other."""
    from dt_runtime.measurements.dataset import read_table

    second = tmp_path / "second.csv"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--scenario", str(CONFIGS / "scenarios" / "hidden" / "none.yaml"),
                     "--seed", "5", "--out", str(second), "--json"]) == 0
    rc = main(["diagnose", "--data", str(hidden["none"]), str(second), "--auto", "--json", "--no-progress"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    a, b = read_table(hidden["none"]), read_table(second)
    assert out["n"] == a.n + b.n
    assert [s["rows"] for s in out["sessions"]] == [a.n, b.n]
    assert out["validation"]["deployment"]["kind"] == "sessions"
    assert {"+session base", "+session joints"} <= set(out["added"])
    assert [v["session"] for v in out["session_term_values"]] == [1, 1]
    assert any(s["rmse_mm"] > s["as_is_rmse_mm"] for s in out["sessions"]) and out["deploy"]["ok"] is False
    v = out["verdict"]
    assert "Held out by session" in v and v.rfind(" Do not deploy: held out") > v.rfind(" Stopped")


def test_out_writes_every_rows_held_out_residual_of_the_first_and_the_final_model(hidden, tmp_path):
    """residuals.csv beside the model: the residuals the steps were scored on (each point predicted by
    the model fitted on the other folds), not the saved model's in-sample ones."""
    import numpy as np

    from dt_runtime.analysis.crossval import cross_validate, folds_of, groups_of
    from dt_runtime.analysis.data import load_data
    from dt_runtime.models.hybrid import HybridModel, load_map
    from dt_runtime.reports.residuals import read_residuals

    out = tmp_path / "model"
    with contextlib.redirect_stdout(io.StringIO()) as text:
        assert main(["diagnose", "--data", str(hidden["backlash"]), "--auto", "--out", str(out), "--json",
                     "--no-progress"]) == 0
    d = json.loads(text.getvalue())
    t = read_residuals(out / "residuals.csv")
    names = [k[4:] for k in t if k.startswith("r_x:")]
    assert names == [f"first: {d['steps'][0]['model']}", f"final: {d['steps'][-1]['model']}"]
    r = {n: np.array([[float(v) for v in t[f"r_{a}:{n}"]] for a in "xyz"]).T for n in names}
    ds = load_data(hidden["backlash"]).dataset
    assert len(t["x"]) == ds.n == d["n"] and [int(v) for v in t["line"]] == ds.lines.tolist()
    # the figures of the steps are these residuals' RMS
    for n, step in zip(names, (d["steps"][0], d["steps"][-1])):
        assert np.sqrt(np.mean(np.sum(r[n] ** 2, axis=1))) == pytest.approx(step["rmse_mm"], rel=1e-5)
    # the same cross-validation done here: the diagnosis's folds (groups_of, folds_of, seed 0), the first
    # model's hyperparameters fitted on all rows, the final one with the saved model's
    final = load_map(out)
    groups = groups_of(ds)
    folds = folds_of(groups, d["folds"], 0)
    first = cross_validate(HybridModel((), "tcp_speed", robot=final.robot, seed=0), ds, ds.error, groups, folds)
    assert np.abs(first.residual * 1e3 - r[names[0]]).max() < 1e-5  # mm; the file holds 6 digits
    assert final.gp_ is not None
    last = cross_validate(final, ds, ds.error, groups, folds, thetas=final.gp_.thetas_)
    assert np.abs(last.residual * 1e3 - r[names[1]]).max() < 1e-5
    in_sample = (ds.error - final.predict(ds)) * 1e3
    assert np.abs(in_sample - r[names[1]]).max() > 1e-3  # held out: not what the saved model fits
