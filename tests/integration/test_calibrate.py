"""`dt calibrate`: a twin from a campaign's files, the same as the demo's for the same files and
seed; one error-model type (the twin's maps are hybrid models that compare and diagnose load);
bad input stops with a clear error and writes nothing."""
import csv
import json
import shutil

import numpy as np
import pytest

from dt_kernel.errors import DataError, ModelError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.models.hybrid import HybridModel, load_map
from dt_runtime.twin.twin import Twin


def _calibrate(args, capsys):
    rc = main(["calibrate", "--json", "--no-progress", *args])
    out = capsys.readouterr().out
    return rc, json.loads(out.strip().splitlines()[-1])


def _rewrite(src, dst, change):
    """Copy a campaign CSV, applying change(row dict) to every row."""
    with open(src, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        change(r)
    with open(dst, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def test_calibrate_on_the_demos_files_gives_the_demos_twin(quick_demo, tmp_path, capsys):
    rc, _, out = quick_demo
    assert rc == 0
    demo = json.loads((out / "summary.json").read_text())
    rc, s = _calibrate(["--campaign", str(out / "campaign"), "--out", str(tmp_path / "twin")], capsys)
    assert rc == 0, s
    for key in ("precision_before_mm", "precision_after_mm", "improvement_pct", "expanded_uncertainty_95",
                "table2_registration_residuals", "table4_model_residuals_cv", "budgets"):
        assert s[key] == demo[key], key
    a, b = Twin.load(out / "model"), Twin.load(tmp_path / "twin")
    rng = np.random.default_rng(3)
    for p in rng.uniform([0.7, -0.2, 0.3], [1.1, 0.2, 0.7], (5, 3)):
        ca, cb = a.correct(p, 0.5), b.correct(p, 0.5)
        assert np.array_equal(ca.command, cb.command) and np.array_equal(ca.U, cb.U)
    assert (tmp_path / "twin" / "report.html").is_file()
    prov = s["provenance"]
    assert {"doe.csv", "registration.csv", "campaign.yaml"} <= {f["path"].split("/")[-1] for f in prov["inputs"]}
    assert {i["role"] for i in prov["instruments"]} >= {"robot", "tracker", "camera"}


def test_the_twins_maps_are_hybrid_models_compare_and_diagnose_load(quick_demo, tmp_path, capsys):
    out = quick_demo[2]
    twin = Twin.load(out / "model")
    assert isinstance(twin.e_lt, HybridModel) and twin.e_lt.effects == ()
    assert (out / "model" / "e_lt" / "hybrid.json").is_file()  # one format: a `dt fit` model directory
    m = load_map(out / "model")  # a twin directory: its e_LT map
    X = np.array([[0.9, 0.0, 0.5], [0.8, 0.1, 0.4]])
    from dt_runtime.models.effects import Inputs
    inp = Inputs(commanded=X, speed=np.array([0.5, 0.5]))
    assert np.allclose(m.predict(inp), twin.e_lt.predict(inp))
    # dt compare takes the twin: a table measured on the same simulated arm (the scenario's seed)
    rc = main(["simulate", "--scenario", "configs/scenarios/paper_default.yaml", "--out", str(tmp_path / "d.csv"),
               "--json", "--no-progress"])
    assert rc == 0
    capsys.readouterr()
    rc = main(["compare", "--data", str(tmp_path / "d.csv"), "--model", str(out / "model"), "--json", "--no-progress"])
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 0, res
    rmse = {m["name"]: m["rmse_mm"] for m in res["models"]}
    assert rmse["model"] < 0.2 * rmse["as is"], rmse  # the twin's map explains the arm's error
    rc = main(["diagnose", "--data", str(tmp_path / "d.csv"), "--model", str(out / "model"), "--folds", "3",
               "--json", "--no-progress"])
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 0 and "ranking" in res, res


def test_an_older_gp_only_twin_loads_and_corrects_the_same(quick_demo, tmp_path):
    src = quick_demo[2] / "model"
    old = tmp_path / "old"
    shutil.copytree(src, old)
    twin = Twin.load(src)
    for name, m in (("e_lt", twin.e_lt), ("e_mvs_lt", twin.e_mvs_lt)):
        shutil.rmtree(old / name)
        m.gp_.save(old / name)  # format 1: TWIN/e_lt.json + .npz, the GP alone
    meta = json.loads((old / "twin.json").read_text())
    meta["format_version"] = 1
    (old / "twin.json").write_text(json.dumps(meta))
    t1 = Twin.load(old)
    p = np.array([0.9, 0.05, 0.5])
    assert np.array_equal(t1.correct(p, 0.4).command, twin.correct(p, 0.4).command)


def test_a_model_from_dt_fit_goes_into_a_twin(quick_demo, tmp_path, capsys):
    """--model: the fitted model's configuration becomes the e_LT map, refitted on the DOE."""
    out = quick_demo[2]
    # a `dt fit` model with the thermal effect, as a user would have it
    rc = main(["simulate", "--scenario", "configs/scenarios/hidden/thermal.yaml", "--out", str(tmp_path / "t.csv"),
               "--json", "--no-progress"])
    assert rc == 0
    rc = main(["fit", "--data", str(tmp_path / "t.csv"), "--effects", "thermal", "--out", str(tmp_path / "m"),
               "--json", "--no-progress"])
    assert rc == 0
    capsys.readouterr()
    rc, s = _calibrate(["--campaign", str(out / "campaign"), "--model", str(tmp_path / "m"),
                        "--out", str(tmp_path / "twin")], capsys)
    assert rc == 0, s
    assert s["maps"]["e_lt"]["effects"] == ["thermal"]
    twin = Twin.load(tmp_path / "twin")
    assert twin.needs == ("temperature",)
    with pytest.raises(DataError, match="temperature"):
        twin.correct(np.array([0.9, 0.0, 0.5]), 0.5)
    from dt_runtime.twin.conditions import Conditions
    c = twin.correct(np.array([0.9, 0.0, 0.5]), 0.5, Conditions(temperature=21.0))
    assert np.all(np.isfinite(c.command)) and np.all(c.U > 0)


@pytest.mark.parametrize("what, change, message", [
    ("metres", lambda r: r.update(x=str(float(r["x"]) / 1000), y=str(float(r["y"]) / 1000),
                                  z=str(float(r["z"]) / 1000)), "looks like metres"),
    ("degrees", lambda r: r.update(q2=str(np.degrees(float(r["q2"])) + 30)), "degrees"),
])
def test_a_doe_in_wrong_units_stops_with_nothing_written(quick_demo, tmp_path, capsys, what, change, message):
    camp = tmp_path / "camp"
    shutil.copytree(quick_demo[2] / "campaign", camp)
    _rewrite(camp / "doe.csv", camp / "doe.csv", change)
    rc, s = _calibrate(["--campaign", str(camp), "--out", str(tmp_path / "twin")], capsys)
    assert rc == 2 and message in s["error"] and "doe.csv" in s["error"], s
    assert not (tmp_path / "twin").exists()


def test_files_of_another_robot_are_refused(quick_demo, tmp_path, capsys):
    rc, s = _calibrate(["--campaign", str(quick_demo[2] / "campaign"), "--robot", "robots/ur10.yaml",
                        "--out", str(tmp_path / "twin")], capsys)
    assert rc == 2 and "ur10" in s["error"].lower() and "registration.csv" in s["error"], s
    assert not (tmp_path / "twin").exists()


def test_a_twin_whose_robot_config_is_missing_is_refused_at_load(quick_demo, tmp_path, capsys):
    camp = tmp_path / "camp"
    shutil.copytree(quick_demo[2] / "campaign", camp)
    robot = tmp_path / "my_robot.yaml"  # the shipped cobot config, copied where it can vanish
    robot.write_text(CONFIGS.joinpath("robots", "cobot_hc20_like.yaml").read_text().replace(
        "../../sim/assets/cobot.urdf", str(CONFIGS.parent / "sim" / "assets" / "cobot.urdf")))
    rc, s = _calibrate(["--campaign", str(camp), "--robot", str(robot), "--effects", "geometric",
                        "--out", str(tmp_path / "twin")], capsys)
    assert rc == 0, s
    robot.unlink()
    with pytest.raises(ModelError, match="my_robot.yaml"):
        Twin.load(tmp_path / "twin")


def test_calibrate_needs_its_files(tmp_path, capsys):
    rc, s = _calibrate(["--out", str(tmp_path / "t")], capsys)
    assert rc == 2 and "--campaign" in s["error"]
    rc, s = _calibrate(["--campaign", str(tmp_path), "--out", str(tmp_path / "t")], capsys)
    assert rc == 2 and "campaign.yaml" in s["error"]


def test_a_map_reading_the_temperature_gets_it_or_refuses(quick_demo, tmp_path, capsys):
    """The bounded correction refuses (robot not moved) when a condition its map reads is missing;
    a bus request may carry it; a program file's column gives it offline."""
    from dt_runtime.programs.program import correct_program, read_program
    from dt_runtime.service.correction_server import _request
    from dt_runtime.twin.bounds import CorrectionFault, Guard, Limits
    from dt_runtime.twin.conditions import Conditions

    rc, s = _calibrate(["--campaign", str(quick_demo[2] / "campaign"), "--effects", "geometric,thermal",
                        "--out", str(tmp_path / "twin")], capsys)
    assert rc == 0, s
    twin = Twin.load(tmp_path / "twin")
    assert set(twin.needs) == {"joints", "temperature"}
    corr = Guard(twin, Limits())
    target = np.array([0.9, 0.0, 0.5])
    with pytest.raises(CorrectionFault, match="temperature"):
        corr(target, 0.5, Conditions(joints=np.array([0.0, 0.4, 0.8, 0.0, 0.6, 0.0])))
    q0 = np.array([0.0, 0.4, 0.8, 0.0, 0.6, 0.0])
    a = corr(target, 0.5, Conditions(temperature=20.0, joints=q0))  # (this campaign's cell stays at 20 C:
    assert np.all(np.isfinite(a.command)) and a.inside  # tests/unit/test_deploy_effects.py shows the effect act)
    _, _, _, over = _request(b'{"target_mm": [900, 0, 500], "speed_mm_s": 500, "temperature_c": 21.5}')
    assert over == {"temperature": 21.5}
    with pytest.raises(DataError, match="payload_kg"):
        _request(b'{"target_mm": [900, 0, 500], "speed_mm_s": 500, "payload_kg": -1}')
    prog = tmp_path / "p.csv"
    prog.write_text("x,y,z,speed\n900,0,500,500\n")
    with pytest.raises(DataError, match="temperature"):
        correct_program(twin, read_program(prog))
    prog.write_text("x,y,z,speed,temperature,q1,q2,q3,q4,q5,q6\n900,0,500,500,21,0,0.4,0.8,0,0.6,0\n")
    out = correct_program(twin, read_program(prog))
    assert np.all(np.isfinite(out[0].command))


def test_an_effect_of_your_own_goes_into_the_twin_and_travels_with_it(quick_demo, tmp_path, capsys):
    """--effects-file in dt calibrate: the e_LT map fits the declared effect and keeps its
    declaration (the twin loads without the file); the next call without the file does not know it."""
    own = tmp_path / "own.yaml"
    own.write_text("effects:\n  - name: stand_creep\n    factor: the tracker's stand creeping over the campaign\n"
                   "    terms:\n      - {column: t, unit: s}\n")
    args = ["--campaign", str(quick_demo[2] / "campaign"), "--effects", "stand_creep"]
    rc, s = _calibrate([*args, "--effects-file", str(own), "--out", str(tmp_path / "twin")], capsys)
    assert rc == 0, s
    params = [p for p in s["maps"]["e_lt"]["parameters"] if p["effect"] == "stand_creep"]
    assert [p["name"] for p in params] == ["t_x", "t_y", "t_z"] and {p["unit"] for p in params} == {"m/s"}
    own.unlink()
    assert Twin.load(tmp_path / "twin").e_lt.effects == ("stand_creep",)  # the declaration is the map's
    rc, s = _calibrate([*args, "--out", str(tmp_path / "t2")], capsys)
    assert rc == 2 and "unknown effect(s) stand_creep" in s["error"] and not (tmp_path / "t2").exists(), s
