"""HybridModel follows scikit-learn's estimator contract: __init__ only stores, fit validates
and returns self, learned attributes end in '_', clone/get_params/set_params work, fit takes a
measurement Dataset with y defaulting to its error; GP options are typed and saved, and models
saved with the older `gp_kw` still load."""
import json

import numpy as np
import pytest
import sklearn.base

from dt_kernel.errors import DataError, ModelError
from dt_runtime.analysis.crossval import cross_validate, folds_of, grouped_residuals, groups_of
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.models import effects as fx
from dt_runtime.models.gp import GPOptions, MultiOutputGP
from dt_runtime.models.hybrid import HybridModel

ROBOT = CONFIGS / "robots" / "cobot_hc20_like.yaml"
PARAMS = {"effects", "gp_inputs", "ridge", "seed", "robot", "gp_options", "nuisance", "reference_session",
          "catalogue"}
FAST = GPOptions(n_restarts=0, max_iter=50)


def dataset(n=60, seed=0) -> Dataset:
    rng = np.random.default_rng(seed)
    P = rng.uniform([0.3, -0.3, 0.3], [0.8, 0.3, 0.8], (n, 3))
    q = rng.uniform(-1, 1, (n, 6))
    E = 1e-3 * np.column_stack([np.sin(3 * P[:, 0]), np.cos(2 * P[:, 1]), P[:, 2]]) + rng.normal(0, 1e-5, (n, 3))
    return Dataset(commanded=P, error=E, joints=q, speed=rng.choice([0.1, 0.3], n),
                   temperature=np.linspace(20, 23, n), t=np.linspace(0, 3600, n), point_id=np.arange(n) // 2)


def test_init_only_stores_and_clone_works():
    m = HybridModel(effects=("bogus",), gp_inputs="nowhere", robot="no/such.yaml")  # no validation here
    assert set(m.get_params()) == PARAMS and m.get_params()["effects"] == ("bogus",)
    c = sklearn.base.clone(HybridModel(effects=("geometric",), gp_options=FAST))
    assert c.get_params()["effects"] == ("geometric",) and c.gp_options == FAST
    assert m.set_params(effects=("thermal",)) is m and m.effects == ("thermal",)
    with pytest.raises(DataError, match="unknown effect\\(s\\) bogus"):
        HybridModel(effects=("bogus",)).fit(dataset())
    with pytest.raises(DataError, match="unknown GP inputs 'nowhere'"):
        HybridModel(gp_inputs="nowhere").fit(dataset())


def test_fit_on_a_dataset_learns_only_underscore_attributes_and_returns_self():
    ds = dataset()
    m = HybridModel(("thermal",), gp_inputs="tcp", gp_options=FAST)
    assert m.fit(ds) is m
    learned = set(vars(m)) - PARAMS
    assert learned and all(k.endswith("_") for k in learned), learned
    same = HybridModel(("thermal",), gp_inputs="tcp", gp_options=FAST).fit(fx.Inputs.of(ds), ds.error)
    np.testing.assert_array_equal(m.predict(ds), same.predict(ds))
    mean, std = m.predict(ds, return_std=True)
    assert mean.shape == std.shape == (ds.n, 3) and np.all(std >= 0)
    with pytest.raises(DataError, match="y .* is required"):
        HybridModel().fit(fx.Inputs.of(ds))
    with pytest.raises(ModelError, match="not fitted"):
        HybridModel().predict(ds)


def test_prebuilt_design_gives_the_same_fit():
    ds = dataset()
    m = HybridModel(("geometric", "drift"), gp_inputs="none", robot=ROBOT)
    D = m.design_matrix(ds)
    assert D.A.shape[:2] == (ds.n, 3) and len(D.params) == D.A.shape[2]
    a = m.unfitted().fit(ds).theta_
    b = m.unfitted().fit(ds, design=D).theta_
    np.testing.assert_array_equal(a, b)


def test_chain_error_names_the_parameter_not_a_flag():
    with pytest.raises(DataError) as err:
        HybridModel(("geometric",), gp_inputs="none").fit(dataset())
    assert "parameter robot" in str(err.value) and "--" not in str(err.value)


def test_gp_options_saved_and_older_gp_kw_models_load(tmp_path):
    ds = dataset()
    opts = GPOptions(n_restarts=0, n_inducing=50)
    m = HybridModel((), gp_inputs="tcp", gp_options=opts).fit(ds)
    m.save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "hybrid.json").read_text())
    assert meta["gp_options"] == opts.to_dict()
    back = HybridModel.load(tmp_path / "m")
    assert back.gp_options == opts
    np.testing.assert_array_equal(back.predict(ds), m.predict(ds))
    # the format before GPOptions: only the overridden options, under "gp_kw"
    del meta["gp_options"]
    meta["gp_kw"] = {"n_restarts": 0, "n_inducing": 50}
    (tmp_path / "m" / "hybrid.json").write_text(json.dumps(meta))
    old = HybridModel.load(tmp_path / "m")
    assert old.gp_options == opts
    np.testing.assert_array_equal(old.predict(ds), m.predict(ds))


def test_a_saved_robot_reference_reloads_the_chain(tmp_path):
    ds = dataset()
    m = HybridModel(("geometric",), gp_inputs="none", robot=ROBOT).fit(ds)
    assert m.robot_ == "robots/cobot_hc20_like.yaml"
    back = HybridModel.load(m.save(tmp_path / "g"))
    assert back.robot_ == m.robot_
    np.testing.assert_allclose(back.predict(ds), m.predict(ds), rtol=0, atol=1e-15)


def test_folds_hold_whole_groups_and_cover_every_row():
    g = groups_of(dataset())
    folds = folds_of(g, 5, seed=3)
    assert len(folds) == 5 and np.all(np.sum(folds, axis=0) == 1)
    for f in folds:
        assert not set(g[f]) & set(g[~f])


def test_grouped_residuals_reproduce_the_calibration_loop():
    """The twin's calibration cross-validation (a GP per DOE): the same folds, the same numbers."""
    rng = np.random.default_rng(1)
    groups = np.repeat(np.arange(15), 3)
    X = rng.uniform(0, 1, (45, 2))
    Y = np.column_stack([np.sin(3 * X[:, 0]), X[:, 1] ** 2]) + rng.normal(0, 0.01, (45, 2))

    def fit_predict(Xtr, Ytr, Xte):
        return MultiOutputGP(seed=7).fit(Xtr, Ytr).predict(Xte)

    # the reference loop, as dt_runtime/twin/calibration.py wrote it
    ref = np.full_like(Y, np.nan)
    ids = np.unique(groups)
    np.random.default_rng(7).shuffle(ids)
    for f in range(4):
        te = np.isin(groups, ids[f::4])
        ref[te] = Y[te] - MultiOutputGP(seed=7).fit(X[~te], Y[~te]).predict(X[te])
    np.testing.assert_array_equal(grouped_residuals(X, Y, groups, 4, 7, fit_predict), ref)


def test_cross_validate_takes_the_model_configuration():
    ds = dataset()
    g = groups_of(ds)
    model = HybridModel(("thermal",), gp_inputs="tcp", gp_options=FAST)
    cv = cross_validate(model, ds, ds.error, g, folds_of(g, 4, 0), return_std=True)
    assert cv.residual.shape == cv.std.shape == (ds.n, 3) and np.all(np.isfinite(cv.residual))
    assert len(cv.group_mse) == len(np.unique(g))
    assert not hasattr(model, "theta_")  # the template is not fitted, its clones are


def test_the_library_surface_is_the_analysis_modules_own():
    import dt_runtime
    from dt_runtime.analysis import compare, data, diagnose

    assert dt_runtime.diagnose is diagnose.diagnose and dt_runtime.compare is compare.compare
    assert dt_runtime.load_data is data.load_data and dt_runtime.HybridModel is HybridModel


def test_results_serialise_to_the_contract_keys(tmp_path):
    from dt_runtime.analysis.compare import compare
    from dt_runtime.analysis.data import Data
    from dt_runtime.analysis.diagnose import DiagnoseOptions, diagnose
    from dt_runtime.analysis.training import fit
    from dt_runtime.common.jsonsafe import dumps

    ds = dataset(n=40)
    d = Data(ds, {"data": "synthetic", "n": ds.n})
    f = fit(d, ("thermal",), "none", None, tmp_path / "m", cv_folds=3)
    assert f.heldout_rmse_mm is not None
    assert list(f.to_dict())[:8] == ["out", "n", "effects", "gp_inputs", "robot", "fit_seconds", "train_rmse_mm",
                                     "parameters"]
    r = diagnose(d, DiagnoseOptions(effects=(), gp_inputs="none", candidates=("thermal", "dynamic"), folds=3))
    assert r.top is r.ranking[0] and r.to_dict()["data"] == "synthetic"
    top = r.to_dict()["ranking"][0]
    assert {"effect", "explained_fraction", "p_value", "rmse_before_mm", "rmse_after_mm"} <= set(top)
    c, _ = compare([tmp_path / "m"], ds)
    assert c.primary.name == "m" and {"n", "rmse_mm", "mae_mm", "per_axis", "failures"} <= set(c.to_dict())
    for res in (f, r, c):
        assert dumps(res) == dumps(res.to_dict())  # the one JSON sanitiser reads to_dict()
