"""Identifiable parameters are the report (issue 21, part 4): the base parameters (QR with column
pivoting of the standardised regressor, as FIGAROH) reproduce the model's prediction, are
measured within their uncertainty on a campaign whose truth is known, and `dt fit` / `dt compare`
print them as one short table instead of a screenful of aliasing lists."""
from __future__ import annotations

import contextlib
import io
import json
import re

import numpy as np
import pytest

from dt_runtime.cli.fit import human
from dt_runtime.cli.main import main
from dt_runtime.models.effects import Inputs
from dt_runtime.models.hybrid import HybridModel, resolve_chain
from dt_runtime.models.identifiability import analyse, base_of

SERIES_A = "dt_runtime/data/ipa_ur10/Series_A/measurements_grid.csv"
UR10 = "configs/robots/ur10.yaml"


def _run(argv: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(argv)
    return rc, buf.getvalue()


def test_base_of_a_known_design():
    """Columns a, b, a (an alias), 2 a + b in other units, round-off zero: rank 2, the alias goes
    to the parameter listed first, the coefficients come out in physical units."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 300))
    A = np.column_stack([a, b, a, 1e3 * (2 * a + b), 1e-19 * a])  # column 3: 1000x smaller unit
    scale = np.sqrt(np.mean(A ** 2, axis=0))
    zero = scale <= 1e-9 * scale.max()
    scale[zero] = 1.0
    As = A / scale
    As[:, zero] = 0.0
    base = base_of(As, scale, zero)
    assert base.lead == [0, 1]
    # beta_0 = theta_0 + theta_2 + 2000 theta_3, beta_1 = theta_1 + 1000 theta_3
    np.testing.assert_allclose(base.C, [[1, 0, 1, 2000, 0], [0, 1, 0, 1000, 0]], atol=1e-9)
    theta = rng.normal(size=5)
    full = A @ theta
    np.testing.assert_allclose(A[:, base.lead] @ (base.C @ theta), full, rtol=0, atol=1e-12 * np.abs(full).max())
    # the same analysis tells the same rank, and the state round-trips
    ident = analyse(As, zero, scale)
    assert ident.rank == 2 and ident.no_effect == [4]
    back = type(ident).from_state(json.loads(json.dumps(ident.state())))
    assert back.base is not None and back.base.lead == base.lead
    np.testing.assert_allclose(back.base.C, base.C)


def test_synthetic_campaign_base_parameters_within_3u():
    """A UR10 campaign made with known geometric errors (all 45 parameters, 0.3 mrad / 0.3 mm) and
    15 um noise: every base parameter the fit reports lies within 3 u of the true combination,
    and the normalised errors scatter as they should (their mean square near 1)."""
    rng = np.random.default_rng(7)
    chain = resolve_chain(UR10)
    q = rng.uniform(-np.pi, np.pi, size=(400, 6))
    q[:, 1] = rng.uniform(-2.5, -0.6, 400)  # elbow up, the arm clear of the floor
    q[:, 2] = rng.uniform(0.4, 2.2, 400)
    inp = Inputs(chain.fk(q), joints=q)
    model = HybridModel(("geometric",), "none", robot=UR10)
    A = model.design_matrix(inp).A
    units = [u for _, _, u, _ in model.design_matrix(inp).params]
    theta_true = rng.normal(size=A.shape[2]) * 3e-4  # rad and m alike: 0.3 mrad, 0.3 mm
    error = np.einsum("nap,p->na", A, theta_true) + rng.normal(size=(len(q), 3)) * 15e-6
    model.fit(inp, error)
    bp = model.base_parameters()
    assert bp is not None and bp["rank"] == len(bp["parameters"]) and 20 <= bp["rank"] < len(units)
    C = model.identifiability_.base.C
    z = np.array([(p["value"] - t) / p["u"] for p, t in zip(bp["parameters"], C @ theta_true)])
    assert np.all(np.abs(z) < 3), z
    assert 0.4 < float(np.mean(z ** 2)) < 2.0, np.mean(z ** 2)


@pytest.fixture(scope="module")
def series_a(tmp_path_factory):
    """`dt fit --effects geometric` on all of UR10 Series A (the real command, GP included:
    ~12 s of CPU): (exit code, its JSON, the model directory)."""
    out = tmp_path_factory.mktemp("series_a") / "m"
    rc, text = _run(["fit", "--data", SERIES_A, "--mapping", "configs/import/ur10.yaml", "--robot", UR10,
                     "--effects", "geometric", "--out", str(out), "--json", "--no-progress"])
    return rc, json.loads(text), out


def test_ur10_series_a_fit_prints_the_base_parameter_table(series_a):
    rc, res, _ = series_a
    assert rc == 0 and res["n"] == 11911
    text = human(res)
    lines = text.splitlines()
    assert len(lines) <= 15, text
    assert "aliased with" not in text
    bp = res["base_parameters"]
    assert bp["n_params"] == 45 and bp["rank"] == len(bp["parameters"])
    assert f"geometric: {bp['rank']} base parameters of 45" in text
    assert re.search(rf"^{45 - bp['rank']} directions of 45 not separable by these data.*parameters\[\]\.group",
                     text, flags=re.M)
    assert sum(ln.startswith("  joint ") for ln in lines) <= 6 and any(ln.startswith("  tool ") for ln in lines)
    # the per-parameter list (with the aliased groups) stays in the JSON, with its keys
    assert len(res["parameters"]) == 45 and all("identified" in p for p in res["parameters"])
    # a parameter the per-parameter analysis identifies is a base parameter on its own, same value
    base = {p["name"]: p for p in bp["parameters"]}
    for p in res["parameters"]:
        if p["identified"]:
            assert base[p["name"]]["absorbs"] == [] and base[p["name"]]["value"] == pytest.approx(p["value"])
    # offset_q1 stands for itself and what turns the arm about the same vertical axis
    assert set(base["offset_q1"]["absorbs"]) == {"geometric.frame1_rz", "geometric.frame2_ry"}
    assert all(p["u"] > 0 for p in bp["parameters"])


def test_series_a_base_regressor_reproduces_the_prediction(series_a):
    """A theta == A_b beta on the campaign's poses, to round-off, with the saved model (loaded)."""
    from dt_runtime.analysis.data import load_data

    _, res, out = series_a
    model = HybridModel.load(out)
    d = load_data(SERIES_A, "configs/import/ur10.yaml", False, UR10)
    A = model.design_matrix(d.dataset).A.reshape(-1, 45)
    bp = model.base_parameters()
    assert bp == json.loads(json.dumps(res["base_parameters"]))  # the model file keeps the table
    lead = model.identifiability_.base.lead
    beta = np.array([p["value"] for p in bp["parameters"]])
    full = A @ model.theta_
    assert np.abs(full).max() > 1e-4  # the effect predicts something (0.1 mm and more)
    np.testing.assert_allclose(A[:, lead] @ beta, full, rtol=0, atol=1e-12)


def test_compare_prints_and_reports_the_same_table(series_a, tmp_path):
    _, _, model = series_a
    rc, text = _run(["compare", "--data", SERIES_A, "--mapping", "configs/import/ur10.yaml", "--model", str(model),
                     "--report", str(tmp_path / "r"), "--no-progress"])
    assert rc == 0
    part = text[text.index("effect parameters of m"):].splitlines()
    assert len(part) <= 14 and "aliased with" not in text and "base parameters of 45" in part[1]
    html = (tmp_path / "r" / "report.html").read_text()
    section = html[html.index('id="parameters"'):html.index('id="method"')]
    assert "base parameters of 45" in section and "aliased with" not in section
    assert section.count("<tr>") <= 9  # header, six joints at most, the tool


def test_a_model_saved_before_base_parameters_still_loads_and_prints(tmp_path):
    """hybrid.json without `base_parameters` and an identifiability without `base` (as written
    before): the model loads, predicts, and prints its identified parameters compactly."""
    rng = np.random.default_rng(3)
    chain = resolve_chain(UR10)
    q = rng.uniform(-2.0, 2.0, size=(120, 6))
    inp = Inputs(chain.fk(q), joints=q)
    m = HybridModel(("geometric",), "none", robot=UR10)
    e = np.einsum("nap,p->na", m.design_matrix(inp).A, rng.normal(size=45) * 2e-4)
    m.fit(inp, e + rng.normal(size=e.shape) * 1e-5).save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "hybrid.json").read_text())
    del meta["base_parameters"], meta["identifiability"]["base"], meta["identifiability"]["no_effect"]
    (tmp_path / "m" / "hybrid.json").write_text(json.dumps(meta))
    old = HybridModel.load(tmp_path / "m")
    assert old.base_parameters() is None
    np.testing.assert_allclose(old.predict(inp), m.predict(inp))
    from dt_runtime.cli.common import parameter_lines

    lines = parameter_lines(old.parameters(), None)
    n_id = sum(p["identified"] for p in old.parameters())
    assert lines[0].startswith(f"geometric: {n_id} identified parameters of 45") and len(lines) <= 12
    assert lines[-1].startswith(f"{45 - n_id} of 45 parameters not identified")


def test_a_tiny_value_is_shown_in_a_smaller_unit_not_with_a_power_of_ten_beside_one():
    from dt_runtime.reports.parameter_table import parameter_table, text, with_unit

    # the backlash's play: 0 rad within 34 nrad printed as "play_rad 0(34)e-6 mrad"
    assert with_unit(0.0, 3.4e-8, "rad") == "0.000(34) µrad"
    assert with_unit(0.0, 3.4e-8, "rad", plus_minus=True) == "0.000 ± 0.034 µrad"
    assert with_unit(8.7e-5, 9e-6, "rad") == "0.0870(90) mrad"  # a normal size stays in mrad
    assert with_unit(2e-9, 1e-10, "m/h") == "2.00(10) nm/h"
    params = [{"effect": "backlash", "name": "play_rad", "value": 0.0, "u": 3.4e-8, "unit": "rad",
               "method": "profile likelihood"}]
    lines = text(parameter_table(params, {"parameters": [], "not_separable": 0, "n_params": 0}))
    assert any("play_rad 0.000(34) µrad (profile likelihood)" in ln for ln in lines), lines
    assert not any("e-6 mrad" in ln for ln in lines)
