"""A 7-axis catalogue arm (the Franka Panda) through the command line: fit, diagnose, compare and
export (URDF and DH) on a small seeded synthetic campaign (tests/support/panda_campaign.py: its own
forward kinematics from Franka's published Craig table, joint zero offsets and link errors,
an SMR on the flange, 0.02 mm tracker noise; 200 rows, q1..q7), and the redundant arm's inverse
kinematics."""
import json

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import load_robot
from tests.support.panda_campaign import write_campaign


def dt(capsys, *argv) -> dict:
    code = main([*argv, "--json", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0, out
    return json.loads(out)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    return write_campaign(tmp_path_factory.mktemp("panda"), seed=3)


def test_fit_diagnose_compare_export_a_seven_axis_arm(capsys, campaign, tmp_path):
    data = str(campaign.files["table"])
    fit = dt(capsys, "fit", "--data", data, "--robot", "panda", "--effects", "geometric", "--out",
             str(tmp_path / "m"))
    as_is = np.sqrt(np.mean(np.sum((campaign.commanded - campaign.measured) ** 2, axis=1))) * 1e3
    assert as_is > 0.3  # the arm's errors are there to find
    assert fit["train_rmse_mm"] < 0.045  # the noise floor is 0.035 mm (0.02 mm per axis)
    assert len([p for p in fit["parameters"] if p["name"].startswith("offset_q")]) == 7
    # the catalogue arm has no tool: the one the commanded TCP implies travels in the reference
    assert fit["robot"].startswith("panda?tool_mm=") and fit["tool_offset"]["from"] == "commanded"
    np.testing.assert_allclose(fit["tool_offset"]["xyz_mm"], [12, -6, 95], atol=1e-3)

    diag = dt(capsys, "diagnose", "--data", data, "--robot", "panda")
    assert diag["ranking"][0]["effect"] == "geometric" and diag["ranking"][0]["p_value"] < 1e-6

    cmp = dt(capsys, "compare", "--model", str(tmp_path / "m"), "--data", data)
    assert cmp["n"] == 200 and cmp["rmse_mm"] == pytest.approx(fit["train_rmse_mm"], rel=1e-9)

    for fmt, suffix in (("urdf", "urdf"), ("dh", "yaml")):
        out = tmp_path / f"calibrated.{suffix}"
        ex = dt(capsys, "export", "--model", str(tmp_path / "m"), "--format", fmt, "--out", str(out))
        assert ex["fk_check"]["ok"] and ex["fk_check"]["max_mm"] < 0.01
        back = robots.load(str(out)) if fmt == "urdf" else load_robot(out)
        assert back.dof == 7
        # the exported arm is nearer the truth than the nominal: it carries the calibration
        err_nom = np.linalg.norm(robots.load(fit["robot"]).fk(campaign.q) - campaign.measured, axis=1)
        err_cal = np.linalg.norm(back.fk(campaign.q) - campaign.measured, axis=1)
        assert np.sqrt(np.mean(err_cal ** 2)) < 0.2 * np.sqrt(np.mean(err_nom ** 2))


def test_joints_only_import_of_a_seven_axis_arm_fits_the_tool_and_trains(capsys, campaign, tmp_path):
    f = campaign.files
    fit = dt(capsys, "fit", "--data", str(f["joints"]), "--mapping", str(f["mapping"]), "--effects", "geometric",
             "--out", str(tmp_path / "mj"))
    assert fit["tool_offset"]["from"] == "measured" and fit["robot"].startswith("panda?tool_mm=")
    assert fit["train_rmse_mm"] < 0.045
    back = dt(capsys, "compare", "--model", str(tmp_path / "mj"), "--data", str(f["joints"]), "--mapping",
              str(f["mapping"]))
    assert back["rmse_mm"] == pytest.approx(fit["train_rmse_mm"], rel=1e-9)


def test_redundant_ik_stays_on_the_seed_branch_with_small_steps(campaign):
    chain = robots.load("panda").with_tool([0.012, -0.006, 0.095])
    for q0 in campaign.q[1:11]:  # (q[0] is near full stretch: that move leaves the workspace)
        p, R = chain.pose(q0)
        target = p + np.array([0.01, -0.02, 0.015])
        q = chain.ik(target, q0)
        np.testing.assert_allclose(chain.pose(q)[0], target, atol=1e-9)
        np.testing.assert_allclose(chain.pose(q)[1], R, atol=1e-8)  # the tool keeps its orientation
        assert np.max(np.abs(q - q0)) < 0.3  # a 27 mm move: no jump to another elbow (null-space) branch
