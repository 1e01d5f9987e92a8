"""A whole tracker campaign read by one mapping, with no conversion script (issue 13, part 7):
three sessions exported as the instruments do (Latin-1 points in each session's own tracker
frame, the joints in a ';'/decimal-comma spreadsheet CSV in degrees, no commanded positions),
each registered on its own, scored held out by session after re-registration, and the session
whose wrist turns beyond anything trained flagged as outside the domain.

And the same campaign in day folders (issue 21, part 6): points.csv and joints.xlsx in every
folder, sessions named by the path that tells them apart, `dt compare` scoring each session as it
would on its own, and docs/campaigns.md's worked example run as written."""
from __future__ import annotations

import json
import re
import shlex

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.common.paths import ROOT
from dt_runtime.measurements.importer import load_mapping
from dt_runtime.measurements.session_paths import session_names
from tests.support.campaign_generator import MAPPING_DAYS, write_campaign


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
    assert [s["name"] for s in sessions] == ["s1", "s2", "s3"]  # unique file names: their stems
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
    assert "Session 2 (s3) leaves the other sessions' domain" in out["verdict"]
    assert any(r.name == "dt.diagnose" and r.getMessage().startswith("session 2 (s3): ") and "q6 " in r.getMessage()
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


def test_sessions_are_named_by_the_shortest_path_that_tells_them_apart():
    assert session_names(["a/s1.csv", "a/s2.csv", "b/s3.csv"]) == ["s1", "s2", "s3"]
    assert session_names(["h/day1/points.csv", "h/day2/points.csv", "h/day3/x/points.csv"]) == [
        "day1/points", "day2/points", "x/points"]
    assert session_names(["x/day/p.csv", "y/day/p.csv", "y/day/q.csv"]) == ["x/day/p", "y/day/p", "q"]
    assert session_names(["s1.csv", "s1.xlsx"]) == ["s1.csv", "s1.xlsx"]
    assert session_names(["d/s1.csv", "d/s1.csv", "e/s1.csv"]) == ["d/s1", "d/s1 (2)", "e/s1"]


@pytest.fixture(scope="module")
def hall(tmp_path_factory):
    """The day-folder campaign and the geometric model fitted on days 1 and 2."""
    d = tmp_path_factory.mktemp("hall")
    c = write_campaign(d, seed=7, layout="days")
    assert main(["fit", "--data", *map(str, c["files"][:2]), "--mapping", str(c["mapping"]), "--effects",
                 "geometric", "--out", str(d / "model"), "--json", "--no-progress"]) == 0
    return c | {"model": d / "model"}


def _compare(hall, files, capsys) -> dict:
    capsys.readouterr()
    assert main(["compare", "--model", str(hall["model"]), "--data", *map(str, files), "--mapping",
                 str(hall["mapping"]), "--json", "--no-progress"]) == 0
    return json.loads(capsys.readouterr().out)


def test_compare_on_several_sessions_scores_each_as_it_would_alone(hall, capsys, caplog):
    out = _compare(hall, hall["files"], capsys)
    assert [f["name"] for f in out["session_files"]] == ["day1/points", "day2/points", "day3/points"]
    assert [m["name"] for m in out["models"]] == ["as is", "model"]
    for m in out["models"]:
        assert [s["name"] for s in m["sessions"]] == ["day1/points", "day2/points", "day3/points"]
        assert [s["n"] for s in m["sessions"]] == [60, 60, 60] and all(s["reregistered"] for s in m["sessions"])
    assert out["sessions"] == out["models"][-1]["sessions"]  # the primary model's, at the top level too
    assert [s["in_sample"] for s in out["sessions"]] == [True, True, False]
    assert sum("used to train model" in r.getMessage() for r in caplog.records) == 2
    # each session's figures are those of a comparison on that session alone
    for k, f in enumerate(hall["files"]):
        alone = _compare(hall, [f], capsys)
        for m, m1 in zip(out["models"], alone["models"]):
            s = m["sessions"][k]
            for key in ("rmse_mm", "mae_mm", "max_mm"):
                assert s[key] == pytest.approx(m1[key], rel=1e-9), (k, m["name"], key)
            for ax in "xyz":
                assert s["per_axis"][ax]["rmse_mm"] == pytest.approx(m1["per_axis"][ax]["rmse_mm"], rel=1e-9)
            assert s["failures"]["count"] == m1["failures"]["count"]
            assert s["failures"]["lines"] == m1["failures"]["lines"]
            assert [r - 60 * k for r in s["failures"]["rows"]] == m1["failures"]["rows"]
            if m["name"] != "as is":
                assert s["after_reregistration"]["rmse_mm"] == pytest.approx(
                    m1["after_reregistration"]["rmse_mm"], rel=1e-9)
                assert s["after_reregistration"]["dof_absorbed"] == 6
    day3 = out["sessions"][2]
    # held out: the model takes 0.35 mm to 0.10, and to near the noise floor after re-registration
    assert day3["after_reregistration"]["rmse_mm"] < 0.05 < day3["rmse_mm"] < 0.5 * out["models"][0]["sessions"][2][
        "rmse_mm"]


def _section(title: str) -> str:
    text = (ROOT / "docs" / "campaigns.md").read_text(encoding="utf-8")
    i = text.index(f"## {title}")
    j = text.find("\n## ", i + 1)
    return text[i:] if j < 0 else text[i:j]


def _numbers(line: str) -> tuple[list[float], list[float]]:
    """The millimetre figures and the percentages of a printed line."""
    found = re.findall(r"(\d+\.\d+)( %)?", line)
    return [float(v) for v, pct in found if not pct], [float(v) for v, pct in found if pct]


def test_the_worked_example_with_spreadsheets_runs_as_documented(tmp_path, monkeypatch, capsys):
    sec = _section("A campaign in folders, with spreadsheets")
    blocks = re.findall(r"^```(\w+)\n(.*?)^```", sec, flags=re.S | re.M)
    (tmp_path / "doc.yaml").write_text(next(b for k, b in blocks if k == "yaml"), encoding="utf-8")
    (tmp_path / "gen.yaml").write_text(MAPPING_DAYS, encoding="utf-8")
    assert load_mapping(tmp_path / "doc.yaml") == load_mapping(tmp_path / "gen.yaml")
    table = next(b for k, b in blocks if k == "text" and "per session" in b).strip().splitlines()
    monkeypatch.chdir(tmp_path)
    out = ""
    for line in next(b for k, b in blocks if k == "bash").strip().splitlines():
        argv = shlex.split(line)
        if argv[0] == ".venv/bin/python":
            assert argv[1] == "-c"
            exec(argv[2], {})
        else:
            assert argv[0] == ".venv/bin/dt"
            capsys.readouterr()
            assert main([*argv[1:], "--no-progress"]) == 0, line
            out = capsys.readouterr().out
    assert (tmp_path / "out/hall/day2/joints.xlsx").is_file() and (tmp_path / "out/hall/report/report.html").is_file()
    printed = out.splitlines()
    start = next(i for i, ln in enumerate(printed) if ln.strip().startswith("per session"))
    assert "noise floor 0.0173 mm" in printed[0]
    assert len(printed) >= start + len(table)
    for doc, got in zip(table, printed[start:start + len(table)]):
        # the words (names, rows, the in-sample marks) as printed; the numbers to their last digit
        assert re.sub(r"\d+\.\d+", "#", doc).split() == re.sub(r"\d+\.\d+", "#", got).split(), (doc, got)
        (mm_doc, pct_doc), (mm_got, pct_got) = _numbers(doc), _numbers(got)
        assert mm_doc == pytest.approx(mm_got, abs=2e-4) and pct_doc == pytest.approx(pct_got, abs=0.2), (doc, got)
