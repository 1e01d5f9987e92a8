"""The tool (SMR) offset fitted from the data for a robot without one (frames.tool_fit), on the
synthetic Panda campaign (tests/support/panda_campaign.py: its own FK, joint zero offsets and link
errors of 0.3-0.6 mm RMS at the TCP, 0.02 mm tracker noise)."""
import numpy as np
import pytest

from dt_runtime.frames import robots
from dt_runtime.frames.tool_fit import fit_tool
from dt_runtime.measurements.importer import import_file
from tests.support.panda_campaign import write_campaign


@pytest.mark.parametrize("seed", [0, 1, 3, 5])
def test_the_fitted_offset_is_near_the_truth_with_the_arms_errors(tmp_path, seed):
    t = write_campaign(tmp_path, seed=seed)
    f = fit_tool(robots.load("panda"), t.q, t.measured)
    assert f.n == 200 and np.all(f.u < 0.005e-3) and 0.2e-3 < f.residual_rms < 1e-3
    dev = np.abs(f.offset - t.tool)
    # the offset shares directions with combinations of the other joints' errors (module docstring):
    # within 0.03 mm across and 0.06 mm along the flange's axis, not always within 3 u (shortfall)
    assert np.all(dev[:2] < 0.03e-3) and dev[2] < 0.06e-3, (dev, f.u)


def test_noise_alone_leaves_the_offset_within_3u(tmp_path):
    t = write_campaign(tmp_path, seed=2)
    chain = robots.load("panda")
    exact = np.array([(T := chain.frames(q[None])[2][0])[:3, 3] + T[:3, :3] @ t.tool for q in t.q])
    noisy = exact + np.random.default_rng(2).normal(0, 2e-5, exact.shape)
    f = fit_tool(chain, t.q, noisy)
    assert np.all(np.abs(f.offset - t.tool) <= 3 * f.u), (f.offset - t.tool, f.u)
    assert f.u[0] == pytest.approx(2e-5 / np.sqrt(200), rel=0.5)


def test_the_import_fits_the_tool_when_the_robot_has_none_and_states_it(tmp_path):
    t = write_campaign(tmp_path, seed=3)
    ds, rep = import_file(t.files["joints"], t.files["mapping"])
    tool = rep.to_dict()["tool_offset"]
    assert tool["from"] == "measured" and tool["n"] == 200 and tool["residual_rms_mm"] > 0.2
    np.testing.assert_allclose(tool["xyz_mm"], t.tool * 1e3, atol=0.05)
    assert any(n.startswith("tool offset fitted from 200 measured positions") for n in rep.notes)
    # the commanded TCP carries it: nominal flange + R o
    np.testing.assert_allclose(ds.commanded, robots.load("panda").with_tool(np.array(tool["xyz_mm"]) / 1e3).fk(t.q),
                               atol=1e-12)


# --- the tool kept in one orientation, a robot config with no tool offset (the paper's DOE shape) ---

def _ur10_no_tool(tmp_path):
    from dt_runtime.common.paths import CONFIGS

    text = (CONFIGS / "robots" / "ur10.yaml").read_text().splitlines()
    path = tmp_path / "my_ur10.yaml"
    path.write_text("\n".join(line for line in text if not line.startswith("tool_xyz_m")) + "\n")
    return path


def _campaign(path, chain, tool_mm, one_orientation, seed=0, n=300, swap=False):
    """A contract table: the commanded TCP the chain with `tool_mm` computes from q (rounded as a
    controller's export is: q to 1e-5 rad, positions to 1e-6 mm), errors of 0.1 mm."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-1.3, -2.3, -2.3, -2.6, 0.6, -2.5]), np.array([1.3, -0.9, -0.7, -0.6, 2.5, 2.5])
    q = lo + (hi - lo) * rng.random((n, 6))
    if one_orientation:  # q5, q6 fixed, q4 keeping the tool pointing down
        q[:, 4], q[:, 5], q[:, 3] = -np.pi / 2, 0.0, -np.pi / 2 - q[:, 1] - q[:, 2]
    q = np.round(q, 5)
    cmd = np.round(chain.with_tool(np.asarray(tool_mm) / 1e3).fk(q) * 1e3, 6)
    err = rng.normal(0, 0.1, (n, 3))
    qs = q[:, [1, 0, 2, 3, 4, 5]] if swap else q
    rows = ["x,y,z,speed,q1,q2,q3,q4,q5,q6,ex,ey,ez"]
    rows += [",".join(f"{v:.9g}" for v in (*cmd[i], 100.0, *qs[i], *err[i])) for i in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _fit(tmp_path, data, robot, caplog):
    import logging

    from dt_runtime.cli.main import main

    with caplog.at_level(logging.INFO):
        code = main(["fit", "--data", str(data), "--robot", str(robot), "--effects", "geometric", "--out",
                     str(tmp_path / "m"), "--json", "--no-progress"])
    return code


def test_a_tool_kept_pointing_down_is_not_invented_and_the_file_is_accepted(tmp_path, caplog, capsys):
    robot = _ur10_no_tool(tmp_path)
    data = _campaign(tmp_path / "down.csv", robots.load(str(robot)), (0, 0, 0), True)
    assert _fit(tmp_path, data, robot, caplog) == 0
    import json

    fit = json.loads(capsys.readouterr().out)
    tool = fit["tool_offset"]
    assert tool["undetermined"] == ["z"] and abs(tool["xyz_mm"][2]) < 1e-9  # kept at the config's (none: 0)
    assert np.all(np.abs(tool["xyz_mm"]) < 0.01)  # x, y determined by the turns about z: 0
    said = caplog.text
    assert "tool z not determined by these poses" in said and "give tool_xyz_m" in said


def test_fit_tool_keeps_every_component_of_a_fixed_orientation(tmp_path):
    chain = robots.load(str(_ur10_no_tool(tmp_path)))
    q = np.tile(np.array([[0.1, -1.5, -1.2, -1.9, -1.57, 0.0]]), (50, 1))
    q[:, 0] += np.linspace(0, 0.001, 50)  # turns by 1 mrad only
    p = chain.with_tool(np.array([0.0, 0.0, 0.1])).fk(q) + 1e-7
    f = fit_tool(chain, q, p, "measured")
    assert f.undetermined == ("x", "y", "z") and f.why == "the tool kept one orientation"
    assert np.all(f.offset == 0) and np.all(f.u == 0)


def test_a_tool_in_the_data_the_config_does_not_give_is_named_as_such(tmp_path, caplog, capsys):
    robot = _ur10_no_tool(tmp_path)
    chain = robots.load(str(robot))
    varied = _campaign(tmp_path / "varied.csv", chain, (10, 5, 100), False)
    assert _fit(tmp_path, varied, robot, caplog) == 0  # varied wrist: fitted
    import json

    np.testing.assert_allclose(json.loads(capsys.readouterr().out)["tool_offset"]["xyz_mm"], [10, 5, 100], atol=0.01)
    down = _campaign(tmp_path / "down.csv", chain, (10, 5, 100), True)
    assert _fit(tmp_path, down, robot, caplog) == 2
    err = capsys.readouterr().err
    assert "a tool offset the robot config does not give" in err and "give tool_xyz_m" in err
    assert "100.000) mm from the flange" in err  # what is missing, in the flange frame
    swapped = _campaign(tmp_path / "swapped.csv", chain, (10, 5, 100), False, swap=True)
    assert _fit(tmp_path, swapped, robot, caplog) == 2
    err = capsys.readouterr().err
    assert "with any tool offset" in err and "joints in another order" in err
