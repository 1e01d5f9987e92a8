"""A whole tracker campaign read by one mapping, with no conversion script (issue 13, part 7):
three sessions exported as the instruments do (Latin-1 points in each session's own tracker
frame, the joints in a ';'/decimal-comma spreadsheet CSV in degrees, no commanded positions),
each registered on its own, scored held out by session after re-registration, and the session
whose wrist turns beyond anything trained flagged as outside the domain."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dt_runtime.cli.main import main
from tests.campaign_generator import write_campaign


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    return write_campaign(tmp_path_factory.mktemp("tracker"), seed=7)


def _q6_outside(campaign) -> int:
    """Rows of the test session (s3) whose wrist 3 lies beyond the training sessions' range
    widened by 2 % (the domain rule)."""
    train = np.concatenate([s["q"][:, 5] for s in campaign["sessions"][:2]])
    lo, hi = train.min(), train.max()
    w = 0.02 * (hi - lo)
    q6 = campaign["sessions"][2]["q"][:, 5]
    return int(np.sum((q6 > hi + w) | (q6 < lo - w)))


def test_one_mapping_reads_the_campaign_and_scores_each_session_held_out(campaign, capsys, caplog):
    files = [str(f) for f in campaign["files"]]
    rc = main(["diagnose", "--data", *files, "--mapping", str(campaign["mapping"]), "--auto",
               "--candidates", "geometric", "--json", "--no-progress"])
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert rc == 0 and out["n"] == 180
    assert out["robot"].endswith("ur10.yaml")  # the mapping's robot is the analysis' robot
    # each session registered on its own: what is left is the arm's non-rigid error (0.2-0.5 mm)
    regs = [f["registration"] for f in out["session_files"]]
    assert [r["method"] for r in regs] == ["rigid"] * 3
    assert all(0.2 < r["rms_3d_mm"] < 0.5 for r in regs)
    assert "+geometric" in out["added"]
    sessions = out["sessions"]
    assert [s["rows"] for s in sessions] == [60, 60, 60]
    for s in sessions:
        assert s["reregistered"] and s["dof_absorbed"] == 6 and s["absorbed"] == ["registration"]
        # re-registration only removes what a rigid fit can absorb: never more error, and the
        # geometric model's held-out residual falls to near the tracker noise (0.017 mm 3D)
        assert s["rmse_mm"] <= s["rmse_raw_mm"]
        assert s["start_rmse_mm"] <= s["start_rmse_raw_mm"]
        assert s["rmse_mm"] < 0.06 < 0.2 < s["start_rmse_mm"]
        assert s["rmse_mm"] < s["as_is_rmse_mm"]
    # the wrist up to 259 deg while the others stay within +-170: the domain warning
    assert np.rad2deg(campaign["sessions"][2]["q"][:, 5].max()) == pytest.approx(259.0)
    n_out = _q6_outside(campaign)
    assert n_out > 20 and sessions[2]["outside_training"]["columns"]["q6"] == n_out
    assert "Session 2 (s3.csv) leaves the other sessions' domain" in out["verdict"]
    assert any(r.name == "dt.diagnose" and r.getMessage().startswith("session 2 (s3.csv): ") and "q6 " in r.getMessage()
               for r in caplog.records)  # the warning on stderr


def test_compare_on_a_new_session_reports_the_figure_after_reregistration(campaign, tmp_path, capsys, caplog):
    files = [str(f) for f in campaign["files"]]
    mapping = str(campaign["mapping"])
    assert main(["fit", "--data", *files[:2], "--mapping", mapping, "--effects", "geometric", "--out",
                 str(tmp_path / "m"), "--json", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["compare", "--model", str(tmp_path / "m"), "--data", files[2], "--mapping", mapping, "--json",
                 "--no-progress"]) == 0
    out = json.loads(capsys.readouterr().out)
    rr = out["after_reregistration"]
    assert rr["dof_absorbed"] == 6 and rr["sessions"] == 1
    as_is = out["models"][0]["rmse_mm"]
    assert rr["rmse_mm"] < 0.05 < out["rmse_mm"] < 0.5 * as_is  # the rigid part was the session's set-up
    assert out["outside_training"]["columns"]["q6"] == _q6_outside(campaign)
    assert any("outside its training domain" in r.getMessage() for r in caplog.records)
