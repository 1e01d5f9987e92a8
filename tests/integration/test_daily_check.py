"""The daily check (`dt calibrate --reference FILE --twin DIR`): the demo's twin deployed to a
re-mounted session (its base moved 1.5, -1.0, 0.8 mm and turned 0.3, -0.2, 0.5 mrad), new poses
measured on the simulated cell. Before the check the stated U95 covers none of the session's poses
and Eq. 17 fails them all; after a check on 10 reference poses both are back to what the twin
does in its own session, without refitting the maps."""
from __future__ import annotations

import hashlib
import json
import shutil

import pytest

from dt_runtime.cli.main import main
from dt_runtime.measurements.campaign_files import read_phase
from dt_runtime.twin.twin import Twin
from dt_runtime.workflows.daily_check import score
from tests.support.remount import remount


def _digest(d) -> dict:
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file()}


@pytest.fixture(scope="module")
def session(quick_demo, tmp_path_factory):
    rc, _, demo = quick_demo
    assert rc == 0
    d = tmp_path_factory.mktemp("daily")
    ref, rest = remount(demo / "model", demo / "campaign" / "doe.csv", d / "session", k=10, n=40, seed=5)
    return demo / "model", ref, rest, d


def test_a_daily_check_of_10_poses_restores_coverage_and_eq17_without_recalibrating(session, tmp_path, capsys):
    model, ref, rest, _ = session
    twin_dir = tmp_path / "twin"
    shutil.copytree(model, twin_dir)
    maps_before = {k: v for k, v in _digest(twin_dir).items() if k != "twin.json"}
    before = score(Twin.load(twin_dir), read_phase(rest, "validation"))
    assert before["n"] >= 35
    assert max(before["coverage_95"].values()) < 0.2  # the re-mount: U95 covers (almost) nothing
    assert min(before["eq17_failures_per_axis"].values()) > 0.5  # and Eq. 17 fails (almost) everything
    capsys.readouterr()
    assert main(["calibrate", "--reference", str(ref), "--twin", str(twin_dir), "--json", "--no-progress"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["poses"] == 10 and s["maps_refitted"] is False and s["validity"]["status"] == "ok"
    lt = s["frames"]["lt"]
    # the tracker frame's change is the inverse of the re-mount, to within its stated U
    assert lt["p_value_no_change"] < 1e-6 and all(u < 0.1 for u in lt["translation_U_mm"])
    assert "mvs" in s["frames"]  # the file has camera points: the camera frame is re-referenced too
    assert any("not separable" in t["text"] or not t["identified"] for t in s["terms"])
    assert "small sample" in s["validity"]["checks"][0]["what"]
    after = score(Twin.load(twin_dir), read_phase(rest, "validation"))
    assert all(0.9 <= c <= 1.0 for c in after["coverage_95"].values()), after
    assert max(after["eq17_failures_per_axis"].values()) <= 0.1, after
    assert after["rms_mm"] < 0.1 * before["rms_mm"]
    # only twin.json changed: the error maps are the calibration's, byte for byte
    assert {k: v for k, v in _digest(twin_dir).items() if k != "twin.json"} == maps_before
    meta = json.loads((twin_dir / "twin.json").read_text())
    assert meta["session"]["daily_check"]["poses"] == 10
    assert [c["label"] for c in meta["position_uncertainty"]["rest"]].count("u_session_reg") == 1
    # a second check on the same poses finds no change and adds no second component
    assert main(["calibrate", "--reference", str(ref), "--twin", str(twin_dir), "--json", "--no-progress"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert max(abs(v) for v in again["frames"]["lt"]["translation_mm"]) < 1e-6
    meta = json.loads((twin_dir / "twin.json").read_text())
    assert [c["label"] for c in meta["position_uncertainty"]["rest"]].count("u_session_reg") == 1


def test_the_human_output_ends_with_the_validity_and_what_to_do(session, tmp_path, capsys):
    model, ref, _, _ = session
    out = tmp_path / "checked"
    capsys.readouterr()
    assert main(["calibrate", "--reference", str(ref), "--twin", str(model), "--out", str(out), "--no-progress"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("validity: OK") and lines[-2].startswith("next: the twin is ready")
    assert any(ln.strip().startswith("tracker frame T_lt refitted: moved") for ln in lines)
    assert any(ln.strip().startswith("kept: the error maps") for ln in lines)
    assert (out / "twin.json").is_file()


def test_a_bad_reference_leaves_the_twin_byte_identical(session, tmp_path, capsys):
    model, ref, _, _ = session
    twin_dir = tmp_path / "twin"
    shutil.copytree(model, twin_dir)
    before = _digest(twin_dir)
    few = tmp_path / "few.csv"
    few.write_text("\n".join(ref.read_text().splitlines()[:4]) + "\n")  # header + 3 poses
    assert main(["calibrate", "--reference", str(few), "--twin", str(twin_dir), "--no-progress"]) == 2
    assert "at least 4" in capsys.readouterr().err
    assert main(["calibrate", "--reference", str(ref), "--no-progress"]) == 2
    assert "needs both --reference FILE.csv and --twin TWIN" in capsys.readouterr().err
    assert main(["calibrate", "--reference", str(ref), "--twin", str(tmp_path), "--no-progress"]) == 2
    assert "not a twin directory" in capsys.readouterr().err
    assert _digest(twin_dir) == before


def test_an_interrupted_write_leaves_the_twin_byte_identical(session, tmp_path, monkeypatch):
    from dt_runtime.workflows import daily_check

    model, ref, _, _ = session
    twin_dir = tmp_path / "twin"
    shutil.copytree(model, twin_dir)
    before = _digest(twin_dir)
    real = daily_check.write

    def interrupted(src, out, meta):  # the new twin.json is written, then Ctrl-C
        real(src, out, meta)
        raise KeyboardInterrupt

    monkeypatch.setattr(daily_check, "write", interrupted)
    assert main(["calibrate", "--reference", str(ref), "--twin", str(twin_dir), "--no-progress"]) == 130
    assert _digest(twin_dir) == before and sorted(p.name for p in tmp_path.iterdir()) == ["twin"]
