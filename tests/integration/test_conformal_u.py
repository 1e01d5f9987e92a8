"""A stated U that holds on new data by construction: the held-out conformal factor of `dt compare
--cv K` (on a training session of the multi-session campaign generator) applied to the U95 of a new
session after its registration on reference poses covers 90-99 % of its errors; the twin's factor is
in twin.json, the summary and the validity block, and a twin saved before it loads and corrects as
before (factor 1)."""
import json
import shutil

import numpy as np
import pytest

from dt_runtime.analysis.compare import compare
from dt_runtime.analysis.data import load_data, refit_sessions
from dt_runtime.cli.main import main
from dt_runtime.models.hybrid import load_map
from dt_runtime.twin.twin import Twin
from tests.support.campaign_generator import write_campaign


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    d = tmp_path_factory.mktemp("conformal")
    truth = write_campaign(d, seed=7, n_points=40, passes=2, sessions=4)
    files = [str(f) for f in truth["files"]]
    assert main(["fit", "--data", files[0], "--mapping", str(truth["mapping"]), "--effects", "geometric",
                 "--out", str(d / "model"), "--no-progress"]) == 0
    return d, files, str(truth["mapping"])


def test_cv_conformal_factor_covers_new_sessions_within_the_band(campaign, capsys):
    d, files, mapping = campaign
    capsys.readouterr()
    assert main(["compare", "--data", files[0], "--mapping", mapping, "--model", str(d / "model"), "--cv", "5",
                 "--json", "--no-progress"]) == 0
    r = json.loads(capsys.readouterr().out)
    c = r["conformal"]
    assert c["method"] == "split conformal, grouped by target point" and c["n"] == 40 and c["rows"] == 80
    assert all(f >= 1.0 for f in c["factor"]) and "95 %" in c["guarantee"]
    assert set(c["coverage_95_conformal_cross_fitted"]) == {"x", "y", "z"}
    assert r["validity"]["stated_U"].startswith("U95 = t_crit")
    factor = np.array(c["factor"])
    model = load_map(d / "model")
    res, U = [], []
    for f in files[1:]:  # the three sessions the model never saw, each registered on 10 reference poses
        data = load_data(f, mapping)
        _, arrays = compare([model], data.dataset, refit_sessions=refit_sessions(data))
        chk = arrays["validity"]
        assert len(chk["rows"]) == 60
        res.append(chk["residual"])
        U.append(chk["U"])
    res_a, U_a = np.concatenate(res), np.concatenate(U)
    cov = (np.abs(res_a) <= factor * U_a).mean(axis=0)
    assert np.all((cov >= 0.90) & (cov <= 0.99)), cov  # 180 rows of 3 new sessions
    assert (np.abs(res_a) <= U_a).mean(axis=0).min() < 0.90  # the GUM U95 alone falls below the band here


def test_without_cv_compare_states_no_conformal_factor(campaign, capsys):
    d, files, mapping = campaign
    capsys.readouterr()
    main(["compare", "--data", files[2], "--mapping", mapping, "--model", str(d / "model"), "--json",
          "--no-progress"])
    r = json.loads(capsys.readouterr().out)
    assert "conformal" not in r and "GUM" in r["validity"]["stated_U"]


def test_the_twins_factor_is_stated_and_an_old_twin_loads_with_none(quick_demo, tmp_path):
    rc, out, d = quick_demo
    s = json.loads((d / "summary.json").read_text())
    uc = s["uncertainty_calibration"]
    assert uc["method"] == "split conformal, grouped by target point" and uc["n"] >= 19
    assert all(f >= 1.0 for f in uc["factor"]) and uc["guarantee"].startswith("marginal coverage >= 95 %")
    assert s["validity"]["guarantee"] == uc["guarantee"] and s["validity"]["sample_size"] == uc["n"]
    twin = Twin.load(d / "model")
    assert twin.conformal.n == uc["n"] and twin.conformal.factor.tolist() == uc["factor"]
    # a twin saved before the calibration existed: no uncertainty_calibration in twin.json
    old = tmp_path / "old"
    shutil.copytree(d / "model", old)
    meta = json.loads((old / "twin.json").read_text())
    del meta["uncertainty_calibration"]
    (old / "twin.json").write_text(json.dumps(meta))
    o = Twin.load(old)
    assert o.conformal.method == "none" and np.all(o.conformal.factor == 1.0)
    rng = np.random.default_rng(8)
    for p in np.array([0.9, 0.0, 0.55]) + rng.uniform(-0.2, 0.2, (10, 3)):
        a, b = o.correct(p, 0.4), twin.correct(p, 0.4)
        assert np.array_equal(a.command, b.command)
        assert a.U == pytest.approx(b.U / twin.conformal.factor, abs=1e-15)  # the plain Eq. 11 U
        assert a.budget is not None and np.array_equal(a.budget.expanded(), a.U)
