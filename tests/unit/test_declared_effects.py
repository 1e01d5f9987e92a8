"""Effects beyond the catalogue: the user's own effects, declared in YAML as regressors built
from the data's columns or published by a package under the entry point group `cobot_dt.effects`,
are tested by `dt diagnose` (its candidates in worker processes, as the command line runs them),
estimated by `dt fit` in their declared unit, and kept by the saved model. A call's declarations
are its own (`models.effects.Catalogue`): nothing is registered in the process.

The data (tests/support/humidity_campaign.py, the example of docs/diagnosis.md): a UR10 campaign from
tests/support/ur10_generator.py (not the project's plant; geometric errors, 15 um tracker noise per axis,
so the noise floor is a 3D RMS of sqrt(3) * 15 um = 0.026 mm), 40 points x 3 passes, with a
logged `humidity` column (%) that drives an error no catalogue effect reads (a random walk over
the campaign), and a `fixture_temp` column (deg C) that turns joints 2 and 3 (rad/K) in a second
file."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.models import effects as fx
from tests.support.humidity_campaign import K_FIXTURE, K_HUMIDITY, campaign
from tests.support.plugin_install import installed
from tests.support.ur10_generator import noise_floor_mm

UR10 = str(CONFIGS / "robots" / "ur10.yaml")
HUMIDITY_YAML = str(CONFIGS / "effects" / "humidity.yaml")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("declared")
    return {"humidity": campaign(d / "humidity.csv"), "fixture": campaign(d / "fixture.csv", 0 * K_HUMIDITY, True),
            "swelling": campaign(d / "swelling.csv", np.array([0.0, 0.0, -5e-6]))}


@pytest.fixture
def workers(monkeypatch):
    """`dt diagnose` as the command line runs it on 2 cores: its candidates in 2 worker processes
    (analysis.parallel; the suite's default is none), which must get the declared effects."""
    monkeypatch.setenv("DT_WORKERS", "2")


def _run(capsys, *argv) -> tuple[int, dict]:
    rc = main([*argv, "--json"] + (["--no-progress"] if argv[0] not in ("correct",) else []))
    return rc, json.loads(capsys.readouterr().out)


def test_the_column_check_flags_humidity_when_no_effect_reads_it(data, capsys):
    rc, r = _run(capsys, "diagnose", "--auto", "--data", str(data["humidity"]), "--robot", UR10)
    assert rc == 0, r
    top = r["columns"][0]
    # measured: p = 1.9e-25, 64 % of the per-point residual variance; 3.0x the floor after +geometric
    assert top["column"] == "humidity" and top["significant"] and top["p_value"] < 1e-10, top
    assert top["explained_fraction"] > 0.4
    assert "follows the column 'humidity'" in r["verdict"] and "declare an effect of your own" in r["verdict"]
    assert r["added"] == ["+geometric"] and r["floor_ratio"] > 2


def test_declared_humidity_is_added_from_the_papers_model_and_the_error_falls_to_the_floor(data, capsys, workers):
    rc, r = _run(capsys, "diagnose", "--auto", "--data", str(data["humidity"]), "--robot", UR10,
                 "--effects-file", HUMIDITY_YAML)
    assert rc == 0, r
    # the noise injected: 15 um per axis, a 3D RMS of sqrt(3) * 15 um = 0.026 mm (the file's ux..uz)
    assert r["noise_floor_mm"] == pytest.approx(noise_floor_mm(), rel=1e-6)
    # no other effect; with warm-started GP fits the loop may also switch the GP's inputs at the end
    assert r["start"] == "GP(TCP, v)" and r["added"][:2] == ["+geometric", "+humidity"], r["added"]
    assert all(a.startswith("GP -> ") for a in r["added"][2:]), r["added"]
    before, after = r["steps"][1]["rmse_mm"], r["final_rmse_mm"]  # geometric + GP, then + humidity
    # measured: 0.2244 (paper's) -> 0.0770 (+geometric) -> 0.0269 mm (+humidity), floor 0.0260 mm: 1.03x
    assert r["floor_ratio"] < 1.3 and after < 0.5 * before, r["steps"]
    assert r["steps"][1]["change"] == "+humidity" and r["steps"][1]["p_value"] < r["steps"][1]["alpha"]
    assert "the residual followed the hall's relative humidity" in r["verdict"]
    assert "at the noise floor" in r["verdict"]
    assert r["declared_effects"] == {"file": HUMIDITY_YAML, "effects": ["humidity"]}


def test_plain_diagnose_ranks_the_declared_effect_and_names_its_factor(data, capsys, workers):
    rc, r = _run(capsys, "diagnose", "--data", str(data["humidity"]), "--robot", UR10, "--effects", "geometric",
                 "--effects-file", HUMIDITY_YAML)
    assert rc == 0, r
    top = r["ranking"][0]
    assert top["effect"] == "humidity" and top["p_value"] < 0.01 and top["explained_fraction"] > 0.5, top
    assert "The model lacks 'humidity'" in r["verdict"] and "the hall's relative humidity" in r["verdict"]


def test_a_call_with_the_file_leaves_nothing_behind_for_the_next(data, tmp_path, capsys):
    """The declarations belong to the call that read the file: the next call without it does not
    know `humidity` (in this process, whatever ran before), and a model saved with it still does."""
    args = ["--data", str(data["humidity"]), "--robot", UR10, "--gp-inputs", "none"]
    rc, r = _run(capsys, "fit", *args, "--effects", "humidity", "--effects-file", HUMIDITY_YAML,
                 "--out", str(tmp_path / "m"))
    assert rc == 0, r
    assert "humidity" not in fx.names()
    for argv in (["fit", *args, "--effects", "humidity", "--out", str(tmp_path / "m2")],
                 ["diagnose", *args, "--candidates", "humidity"],
                 ["calibrate", "--registration", str(data["humidity"]), "--doe", str(data["humidity"]),
                  "--effects", "humidity", "--out", str(tmp_path / "t")]):
        rc, r = _run(capsys, *argv)
        assert rc == 2 and "unknown effect(s) humidity" in r["error"], (argv[0], r)
        assert "--effects-file" in r["error"]
    assert not (tmp_path / "m2").exists() and not (tmp_path / "t").exists()
    # the saved model carries its declaration: compare and diagnose load it without the file
    rc, r = _run(capsys, "compare", "--model", str(tmp_path / "m"), "--data", str(data["humidity"]))
    assert rc == 0 and r["models"][-1]["rmse_mm"] < r["models"][0]["rmse_mm"], r  # humidity alone: a part


def test_the_library_example_of_effects_md_fits_the_declared_effect(data, monkeypatch):
    import re

    from dt_runtime.measurements.dataset import read_table

    root = CONFIGS.parent
    text = (root / "docs" / "effects.md").read_text(encoding="utf-8")
    block = next(b for b in re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M) if "with_file" in b)
    monkeypatch.chdir(root)  # the example's paths are the repository's
    ns = {"ds": read_table(data["humidity"])}
    exec(block, ns)
    got = {p["name"]: p["value"] for p in ns["model"].parameters() if p["effect"] == "humidity"}
    np.testing.assert_allclose(list(got.values()), K_HUMIDITY, atol=1e-6)
    assert "humidity" not in fx.names()


def test_a_catalogue_crosses_a_process_boundary_with_its_declarations():
    """The pool's workers get the problem's catalogue pickled; a declared effect's class is made
    per declaration, so it travels as its declaration."""
    import pickle

    cat = fx.default().with_file(HUMIDITY_YAML)
    back = pickle.loads(pickle.dumps(cat))
    assert back.names() == cat.names() and back.names()[-1] == "humidity"
    assert back.get("humidity").spec == cat.get("humidity").spec
    assert back.get("humidity").factor == "the hall's relative humidity"
    inp = fx.Inputs(commanded=np.zeros((3, 3)), extra={"humidity": np.array([40.0, 45.0, 50.0])})
    np.testing.assert_array_equal(back.build("humidity", inp, None).A, cat.build("humidity", inp, None).A)
    assert "humidity" not in fx.default().names()  # reading the file registered nothing


def test_fit_estimates_the_declared_coefficients_in_their_unit(data, tmp_path, capsys):
    rc, r = _run(capsys, "fit", "--data", str(data["humidity"]), "--robot", UR10, "--effects", "geometric,humidity",
                 "--effects-file", HUMIDITY_YAML, "--out", str(tmp_path / "m"))
    assert rc == 0, r
    got = {p["name"]: p for p in r["parameters"] if p["effect"] == "humidity"}
    assert list(got) == ["humidity_x", "humidity_y", "humidity_z"]
    for (name, p), k in zip(got.items(), K_HUMIDITY):
        # measured: 5.99e-6 +/- 1.8e-7, -3.79e-6 +/- 1.6e-7, 5.22e-6 +/- 1.6e-7 m/%
        assert p["unit"] == "m/%" and p["identified"]
        assert abs(p["value"] - k) < 3 * p["u"] and abs(p["value"] - k) < 0.1 * abs(k), (name, p, k)
    # the declaration travels with the model, and the file is in the provenance
    meta = json.loads((tmp_path / "m" / "hybrid.json").read_text())
    assert [d["name"] for d in meta["declared_effects"]] == ["humidity"]
    assert any(Path(i["path"]).name == "humidity.yaml" for i in r["provenance"]["inputs"])


def test_the_saved_model_loads_in_a_fresh_process_without_the_file(data, tmp_path, capsys):
    assert _run(capsys, "fit", "--data", str(data["humidity"]), "--robot", UR10, "--effects", "geometric,humidity",
                "--effects-file", HUMIDITY_YAML, "--out", str(tmp_path / "m"))[0] == 0
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "dt_runtime.cli", "compare", "--model", str(tmp_path / "m"),
                          "--data", str(data["humidity"]), "--cv", "3", "--json", "--no-progress"],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    model = next(m for m in r["models"] if m["name"] == "m")
    # refitted on 2 of 3 folds in that process: the declaration came from hybrid.json
    assert model["rmse_mm"] < 1.3 * noise_floor_mm(), model["rmse_mm"]


def test_a_joint_space_term_is_estimated_in_rad_per_unit(data, tmp_path, capsys):
    yaml = tmp_path / "fixture.yaml"
    yaml.write_text("""effects:
  - name: fixture
    factor: the fixture's temperature turning joints 2 and 3
    terms:
      - {column: fixture_temp, reference: 20.0, unit: K, space: joints, joints: [2, 3]}
""")
    rc, r = _run(capsys, "fit", "--data", str(data["fixture"]), "--robot", UR10, "--effects", "geometric,fixture",
                 "--effects-file", str(yaml), "--out", str(tmp_path / "m"))
    assert rc == 0, r
    got = {p["name"]: p for p in r["parameters"] if p["effect"] == "fixture"}
    assert list(got) == ["q2_per_fixture_temp", "q3_per_fixture_temp"]
    for j, k in K_FIXTURE.items():
        p = got[f"q{j}_per_fixture_temp"]
        assert p["unit"] == "rad/K"
        assert abs(p["value"] - k) < 3 * p["u"] and abs(p["value"] - k) < 0.1 * abs(k), (p, k)


@pytest.fixture
def plugin(tmp_path):
    """The package tests/support/plugins/dt_effect_plugin, installed for the test (tests/support/plugin_install.py)."""
    with installed(tmp_path, "dt_effect_plugin", {"cobot_dt.effects": {"swelling": "dt_effect_plugin:Swelling"}},
                   fx.reload_entry_points) as names:
        yield names


def test_an_entry_point_plugin_is_a_candidate_and_is_fitted(plugin, data, tmp_path, capsys):
    assert plugin == ["swelling"] and "swelling" in fx.names()
    assert fx.names()[:7] == tuple(fx.REGISTRY)  # the catalogue first, in the contract order
    rc, r = _run(capsys, "fit", "--data", str(data["swelling"]), "--robot", UR10, "--effects", "geometric,swelling",
                 "--out", str(tmp_path / "m"))
    assert rc == 0, r
    p = next(p for p in r["parameters"] if p["effect"] == "swelling")
    assert p["name"] == "lift_per_percent" and p["unit"] == "m/%"
    assert abs(p["value"] - 5e-6) < 3 * p["u"] and abs(p["value"] - 5e-6) < 0.1 * 5e-6, p


def test_without_the_plugin_its_model_does_not_load_and_says_why(data, tmp_path, capsys, plugin):
    assert _run(capsys, "fit", "--data", str(data["swelling"]), "--effects", "swelling",
                "--out", str(tmp_path / "m"))[0] == 0
    (tmp_path / "dt_effect_plugin-0.1.0.dist-info" / "entry_points.txt").unlink()  # uninstalled
    assert fx.reload_entry_points() == []
    rc, r = _run(capsys, "compare", "--model", str(tmp_path / "m"), "--data", str(data["swelling"]))
    assert rc == 2 and "swelling" in r["error"] and "hybrid.json" in r["error"], r


@pytest.mark.parametrize("yaml, effects, message", [
    ("{name: thermal, factor: heat, terms: [{column: humidity}]}", "thermal",
     ["key 'effects.0.name'", "'thermal'", "not a catalogue effect's name"]),
    ("{name: Humidity-2, factor: damp, terms: [{column: humidity}]}", "geometric",
     ["key 'effects.0.name'", "'Humidity-2'", "lower-case letters"]),
    ("{name: fixture, factor: heat, terms: [{column: fixture_temp, space: joints, joints: [2, 7]}]}",
     "geometric,fixture", ["effect 'fixture'", "joint(s) 7", "beyond the robot's 6"]),
    ("{name: damp, factor: damp, terms: [{column: humidty}]}", "geometric,damp",
     ["effect 'damp'", "humidty", "their columns:", "fixture_temp, humidity"]),
    ("{name: damp, factor: damp, terms: [{column: humidity, scale: 2}]}", "geometric,damp",
     ["key 'effects.0.terms.0.scale'", "known keys: axes, column, joints, reference, space, unit"]),
], ids=["catalogue-name", "name-pattern", "joint-beyond-robot", "missing-column", "unknown-key"])
def test_bad_declarations_say_what_is_wrong(data, tmp_path, capsys, yaml, effects, message):
    f = tmp_path / "bad.yaml"
    f.write_text(f"effects:\n  - {yaml}\n")
    rc, r = _run(capsys, "fit", "--data", str(data["humidity"]), "--robot", UR10, "--effects", effects,
                 "--effects-file", str(f), "--out", str(tmp_path / "m"))
    assert rc == 2 and not (tmp_path / "m").exists(), r
    for m in message:
        assert m in r["error"], (m, r["error"])
    assert "bad.yaml" in r["error"]


def _twin(data, tmp_path) -> Path:
    """A twin whose e_LT map holds the declared humidity effect (registration frames identity,
    stated uncertainties made up: this checks the deployment's inputs, not a budget)."""
    from dt_runtime.frames.registration import RigidTransform
    from dt_runtime.measurements.dataset import read_table
    from dt_runtime.models.hybrid import HybridModel
    from dt_runtime.twin.twin import Twin, TwinUncertainty

    ds = read_table(data["humidity"])
    e_lt = HybridModel(("geometric", "humidity"), "tcp_speed", robot=UR10,
                       catalogue=fx.default().with_file(HUMIDITY_YAML)).fit(ds)
    e_mvs = HybridModel((), "tcp_speed").fit(ds)
    stated = {"u": [1e-5] * 3, "dof": [50.0] * 3, "k": [2.0] * 3, "U": [2e-5] * 3}
    u = {k: stated for k in TwinUncertainty.KEYS.values()}
    ident = RigidTransform.identity()
    Twin(ident, ident, ident, e_lt, e_mvs, u).save(tmp_path / "twin")
    return tmp_path / "twin"


def test_dt_correct_reads_the_declared_column_from_the_program_or_refuses(data, tmp_path, capsys):
    from dt_runtime.measurements.dataset import read_table

    twin = _twin(data, tmp_path)  # `dt correct` finds the declaration in the twin's map, not in a file
    ds = read_table(data["humidity"])
    rows = [f"p{i},{','.join(f'{v * 1e3:.4f}' for v in ds.commanded[i])},250,"
            + ",".join(f"{q:.6f}" for q in ds.joints[i - 1]) for i in (5, 17, 40)]
    head = "point_id,x,y,z,speed," + ",".join(f"q{j}" for j in range(1, 7))
    out = {}
    for h in (35.0, 55.0):
        prog = tmp_path / f"prog{h:.0f}.csv"
        prog.write_text(head + ",humidity\n" + "".join(f"{r},{h}\n" for r in rows))
        dst = tmp_path / f"c{h:.0f}.csv"
        rc, r = _run(capsys, "correct", "--twin", str(twin), "--targets", str(prog), "--out", str(dst))
        assert rc == 0 and r["n"] == 3, r
        lines = dst.read_text().splitlines()[1:]
        out[h] = np.array([[float(v) for v in line.split(",")[5:8]] for line in lines])  # cx, cy, cz (mm)
    # 20 % more humidity moves every command by the humidity's fitted offset: ~(6, -4, 5) um/% x 20 %
    shift = (out[55.0] - out[35.0]) / 20.0 * 1e-3  # m/%
    assert np.allclose(shift, K_HUMIDITY, atol=1e-6), shift
    prog = tmp_path / "no_humidity.csv"
    prog.write_text(head + "\n" + "".join(f"{r}\n" for r in rows))
    rc, r = _run(capsys, "correct", "--twin", str(twin), "--targets", str(prog), "--out", str(tmp_path / "c.csv"))
    assert rc == 2 and not (tmp_path / "c.csv").exists()
    assert "need humidity" in r["error"] and "declared effect(s) humidity" in r["error"], r


def test_a_declared_effect_of_the_wrong_form_is_named_when_its_column_still_explains_the_residual(
        data, capsys, tmp_path):
    """The user declared humidity as turning the wrist (it moves the TCP along x, y and z): the
    column check still flags humidity, and the verdict says the declared form is not the data's."""
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("effects:\n  - name: wrist_humidity\n    factor: humidity turning the wrist\n"
                     "    terms:\n      - {column: humidity, reference: 45.0, unit: '%', space: joints, joints: [6]}\n")
    rc, r = _run(capsys, "diagnose", "--auto", "--data", str(data["humidity"]), "--robot", UR10,
                 "--effects-file", str(wrong))
    assert rc == 0, r
    assert "+wrist_humidity" not in r["added"] and r["columns"][0]["column"] == "humidity"
    assert "your effect(s) wrist_humidity read it but did not explain a significant part" in r["verdict"]
