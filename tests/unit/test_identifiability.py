"""Honest parameters: the effect fit reports what the data can determine (rank, condition,
aliased groups) and gives no value to a parameter it cannot (issue 13, part 3)."""
from __future__ import annotations

import json

import numpy as np

from dt_runtime.cli.main import main
from dt_runtime.models.identifiability import analyse, zero_columns

UR10_C = "dt_runtime/data/ipa_ur10/Series_C/measurements_random_poses.csv"


def test_a_rank_deficient_design_is_grouped():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 200))
    # columns: a, b, a (an alias of the first), round-off zero, a + c
    A = np.column_stack([a, b, a, 1e-19 * rng.normal(size=200), a + c])
    scale = np.sqrt(np.mean(A ** 2, axis=0))
    zero = zero_columns(scale)
    assert zero.tolist() == [False, False, False, True, False]
    As = A / np.where(zero, 1.0, scale)
    As[:, zero] = 0.0
    r = analyse(As, zero)
    assert r.rank == 3  # a, b, c are seen; the alias and the zero column are not
    assert r.identified.tolist() == [False, True, False, False, True]
    assert sorted(r.groups) == [[0, 2], [3]]
    d = r.to_dict(["a", "b", "a2", "z", "ac"])
    assert d["not_identified"] == ["a", "a2", "z"] and ["a", "a2"] in d["groups"]


def test_ur10_geometric_parameters_are_honest(tmp_path, capsys):
    rc = main(["fit", "--data", UR10_C, "--mapping", "configs/import/ur10.yaml", "--robot", "configs/robots/ur10.yaml",
               "--effects", "geometric", "--gp-inputs", "none", "--out", str(tmp_path / "m"), "--json", "--no-progress"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    ps = {p["name"]: p for p in out["parameters"]}
    assert all("identified" in p for p in ps.values())
    # joint 6 cannot move a probe on its axis: offset_q6 was printed as 9.55e10 rad before
    assert ps["offset_q6"]["identified"] is False and ps["offset_q6"]["value"] is None
    assert ps["offset_q1"]["identified"] is False and "geometric.frame1_rz" in ps["offset_q1"]["group"]
    ok = [p for p in ps.values() if p["identified"]]
    assert ok and all(abs(p["value"]) < (0.05 if p["unit"] == "rad" else 0.02) for p in ok)  # physical sizes
    assert any(not p["identified"] for p in ps.values())


def test_backlash_widths_are_never_negative(tmp_path, capsys):
    """A clean arm (no backlash in the plant): the widths the fit finds are >= 0 (a negative width,
    -1.03 mrad, was printed as physics before); those the data push below 0 are held at 0."""
    import contextlib
    import io

    from dt_runtime.common.paths import CONFIGS

    csv = tmp_path / "none.csv"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--scenario", str(CONFIGS / "scenarios" / "hidden" / "none.yaml"),
                     "--out", str(csv), "--json"]) == 0
    rc = main(["fit", "--data", str(csv), "--effects", "geometric,backlash", "--gp-inputs", "none",
               "--out", str(tmp_path / "m"), "--json", "--no-progress"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    widths = [p for p in out["parameters"] if p["effect"] == "backlash" and p["value"] is not None]
    assert widths and all(p["value"] >= 0 for p in widths)
    assert any(p.get("at_bound") for p in widths)  # the noise pushed some below 0: held at the bound
    saved = json.loads((tmp_path / "m" / "hybrid.json").read_text())
    linear = [p for p in out["parameters"] if "method" not in p]  # not the profile-likelihood ones (moves, play)
    kept = [b for b, p in zip(saved["at_bound"], linear) if p["value"] is not None]
    assert kept == [bool(p.get("at_bound")) for p in linear if p["value"] is not None]
