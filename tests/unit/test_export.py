"""`dt export`: the calibrated robot (fitted geometric effect) as URDF and as DH robot config.

One seeded simulation of the fault-free hidden scenario (geometric errors only), one fit with
--effects geometric; both exports must load back (chain_from_urdf and xml.etree; load_robot) and
reach, at every DOE joint configuration, the TCP the model's geometric block predicts within
0.01 mm; the non-identifiable parameters are listed and not applied."""
from __future__ import annotations

import argparse
import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from dt_kernel.errors import DataError, ModelError, TwinError
from dt_runtime.analysis.data import DEFAULT_ROBOT, load_data
from dt_runtime.analysis.export import FK_TOL_MM, calibrated_chain, export_robot, model_of_twin
from dt_runtime.analysis.training import fit
from dt_runtime.cli import export as export_cli
from dt_runtime.common.jsonsafe import dumps, jsonable
from dt_runtime.common.paths import CONFIGS, ROOT
from dt_runtime.frames.kinematics import chain_from_urdf, load_robot
from dt_runtime.frames.robot_export import dh_table, urdf_text
from dt_runtime.models.effects import Inputs
from dt_runtime.models.effects.geometric import Geometric
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.workflows.simulate import simulate

SCENARIO = CONFIGS / "scenarios" / "hidden" / "none.yaml"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    csv = d / "none.csv"
    simulate(SCENARIO, csv, seed=3)
    fit(load_data(csv), ("geometric",), "none", DEFAULT_ROBOT, d / "model", seed=0)
    return d, csv, d / "model"


def _calibrated_fk(model_dir: Path, csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """The DOE joint configurations and the TCP the model's geometric block predicts there:
    fk_nominal(q) - A(q) theta (the model has no GP: predict is the effect terms alone)."""
    model = HybridModel.load(model_dir)
    joints = load_data(csv).dataset.joints
    assert joints is not None
    q = np.unique(joints, axis=0)
    chain = load_robot(DEFAULT_ROBOT)
    p = chain.fk(q)
    return q, p - model.predict(Inputs(p, joints=q))


def _check_fk(result: dict, back, q: np.ndarray, calibrated: np.ndarray) -> float:
    diff_mm = np.linalg.norm(back.fk(q) - calibrated, axis=1) * 1e3
    assert diff_mm.max() < FK_TOL_MM, f"exported FK off by {diff_mm.max():.4f} mm"
    assert result["fk_check"]["ok"] and result["fk_check"]["max_mm"] == pytest.approx(diff_mm.max(), abs=1e-9)
    # the first-order values applied exactly already hold (a real check of the linearisation)
    assert result["fk_check"]["first_order_max_mm"] < FK_TOL_MM
    # the calibration is not trivial: the export moves the TCP by far more than the tolerance
    assert result["fk_check"]["correction_rms_mm"] > 20 * FK_TOL_MM
    return float(diff_mm.max())


def test_urdf_export_loads_back_and_reaches_the_calibrated_tcp(fitted, tmp_path):
    _, csv, model_dir = fitted
    out = tmp_path / "cal.urdf"
    result = export_robot(model_dir, "urdf", out, data=csv).to_dict()
    root = ET.parse(out).getroot()  # plain XML parser
    assert root.tag == "robot" and len(root.findall("joint")) == 7
    back = chain_from_urdf(out)
    assert back.dof == 6 and result["loads_back"] == {"xml.etree": True, "chain_from_urdf": True}
    q, calibrated = _calibrated_fk(model_dir, csv)
    _check_fk(result, back, q, calibrated)
    assert result["n_points"] == len(q)
    json.loads(dumps(result))  # JSON-ready


def test_dh_export_loads_with_load_robot_and_reaches_the_calibrated_tcp(fitted, tmp_path):
    _, csv, model_dir = fitted
    out = tmp_path / "cal.yaml"
    result = export_robot(model_dir, "dh", out, data=csv).to_dict()
    back = load_robot(out)
    assert back.dof == 6 and back.gear_harmonics == load_robot(DEFAULT_ROBOT).gear_harmonics
    q, calibrated = _calibrated_fk(model_dir, csv)
    _check_fk(result, back, q, calibrated)
    assert "dh:" in out.read_text() and out.read_text().startswith("# Calibrated by dt export")


def test_only_identifiable_combinations_are_exported(fitted, tmp_path):
    _, csv, model_dir = fitted
    out = tmp_path / "cal.urdf"
    r = export_robot(model_dir, "urdf", out, data=csv).to_dict()
    exported = {p["name"] for p in r["exported"]}
    not_id = {p["name"] for p in r["not_identifiable"]}
    assert r["n_parameters"] == 45 and r["rank"] == len(exported) == r["n_exported"]
    assert len(exported) + len(not_id) + len(r["no_effect"]) == 45
    assert not exported & (not_id | set(r["no_effect"]))
    # the rank-deficient set: offset_q1 and the base rotation about z act alike, and the TCP
    # lies on joint 6's axis (offset_q6 moves nothing)
    assert "offset_q1" in exported and "frame1_rz" in not_id
    assert "offset_q1" in next(p for p in r["not_identifiable"] if p["name"] == "frame1_rz")["absorbed_by"]
    assert "offset_q6" in r["no_effect"]
    assert any({"offset_q1", "frame1_rz"} <= set(g) for g in r["alias_groups"])
    # the file holds exactly the exported values applied to the nominal chain, nothing else
    nominal = load_robot(DEFAULT_ROBOT)
    only = calibrated_chain(nominal, {p["name"]: p["value"] for p in r["exported"]})
    q = np.random.default_rng(0).uniform(-2, 2, (50, 6))
    assert np.abs(chain_from_urdf(out).fk(q) - only.fk(q)).max() < 1e-12
    assert all(p["unit"] in ("m", "rad") for p in r["exported"])


def test_parameters_apply_with_the_effects_sign_and_axes():
    """A small parameter applied exactly moves the TCP by -A theta (e = commanded - measured)."""
    chain = load_robot(DEFAULT_ROBOT)
    q = np.random.default_rng(1).uniform(-1.5, 1.5, (20, 6))
    block = Geometric().build(Inputs(chain.fk(q), joints=q), chain)
    for k, name in enumerate(block.names):
        moved = calibrated_chain(chain, {name: 1e-6}).fk(q) - chain.fk(q)
        assert np.abs(moved + block.A[:, :, k] * 1e-6).max() < 1e-11, name


@pytest.mark.parametrize("config", ["cobot_hc20_like.yaml", "ur10.yaml"])
def test_nominal_chains_round_trip_exactly(config, tmp_path):
    chain = load_robot(CONFIGS / "robots" / config)
    (tmp_path / "r.urdf").write_text(urdf_text(chain))
    (tmp_path / "r.yaml").write_text(dh_table(chain).yaml_text("r"))
    q = np.random.default_rng(2).uniform(-3, 3, (200, 6))
    for back in (chain_from_urdf(tmp_path / "r.urdf"), load_robot(tmp_path / "r.yaml")):
        assert np.abs(back.fk(q) - chain.fk(q)).max() < 1e-12


def test_training_data_comes_from_the_provenance_checked_by_hash(fitted, tmp_path):
    d, csv, model_dir = fitted
    r = export_robot(model_dir, "dh", tmp_path / "a.yaml").to_dict()  # no --data
    assert Path(r["data"]).resolve() == csv.resolve() and r["fk_check"]["ok"]
    moved = tmp_path / "model"
    shutil.copytree(model_dir, moved)
    meta = json.loads((moved / "hybrid.json").read_text())
    meta["provenance"]["inputs"][0]["sha256"] = "0" * 64
    (moved / "hybrid.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="changed since the fit.*--data"):
        export_robot(moved, "dh", tmp_path / "b.yaml")


def _cli(argv: list[str]) -> dict:
    p = argparse.ArgumentParser()
    export_cli.add_arguments(p)
    return jsonable(export_cli.run(p.parse_args(argv)))


def test_cli_model_and_twin(fitted, tmp_path):
    d, csv, model_dir = fitted
    r = _cli(["--model", str(model_dir), "--format", "urdf", "--out", str(tmp_path / "m.urdf"), "--json",
              "--no-refine"])
    assert r["format"] == "urdf" and "FK of the exported robot" in export_cli.human(r)
    fk = r["fk_check"]
    assert not fk["refined"] and fk["max_mm"] == pytest.approx(fk["first_order_max_mm"], abs=1e-9)
    assert fk["max_mm"] < FK_TOL_MM
    twin = tmp_path / "twin"
    (twin / "maps").mkdir(parents=True)
    (twin / "twin.json").write_text("{}")
    with pytest.raises(ModelError, match="this twin's maps hold no geometric effect; "
                                         "fit one with dt fit --effects geometric"):
        _cli(["--twin", str(twin), "--format", "dh", "--out", str(tmp_path / "t.yaml")])
    shutil.copytree(model_dir, twin / "maps" / "hybrid")
    assert model_of_twin(twin) == twin / "maps" / "hybrid"
    r = _cli(["--twin", str(twin), "--format", "dh", "--out", str(tmp_path / "t.yaml"), "--data", str(csv)])
    assert load_robot(tmp_path / "t.yaml").dof == 6 and r["fk_check"]["ok"]


def test_bad_input_gives_a_clear_error(fitted, tmp_path):
    d, csv, model_dir = fitted
    with pytest.raises(DataError, match="unknown export format 'sdf'; allowed: urdf, dh"):
        export_robot(model_dir, "sdf", tmp_path / "x", data=csv)
    plain = tmp_path / "plain"
    fit(load_data(csv), (), "none", DEFAULT_ROBOT, plain)
    with pytest.raises(ModelError, match="no geometric effect; fit one with dt fit --effects geometric"):
        export_robot(plain, "urdf", tmp_path / "x.urdf", data=csv)
    with pytest.raises(DataError, match="no saved model"):
        export_robot(tmp_path / "nothing", "urdf", tmp_path / "x.urdf", data=csv)
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"name: gone\nurdf: {ROOT / 'sim' / 'assets' / 'cobot.urdf'}\n")
    gone = tmp_path / "gone"
    fit(load_data(csv), ("geometric",), "none", robot, gone)
    robot.unlink()
    with pytest.raises(ModelError, match="robot config .* is missing"):
        export_robot(gone, "urdf", tmp_path / "x.urdf", data=csv)
    with pytest.raises(TwinError, match="no such twin directory"):
        model_of_twin(tmp_path / "no_twin")
