"""`dt correct --path`: a path program interpolated at the controller's rate and every set-point
corrected with its U, end to end through the command line, on the quick demo's twin (the paper's
map) and on a twin whose map reads the joints (geometric); bad paths get a clear error and nothing
is written."""
import csv
import json

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.twin import Twin

SEAM = """path: 1
start: [900, 0, 550]
speed: 250
acceleration: 2000
{extra}segments:
  - line: {{to: [950, 0, 550]}}
  - arc: {{via: [985.35533906, 14.64466094, 550], to: [1000, 50, 550]}}
  - line: {{to: [1000, 120, 550], speed: 100}}
  - line: {{to: [1000, 120, 600]}}
"""
START_JOINTS = "[0.0, 0.0959, 0.9323, 0.0, -0.4282, 0.0]"  # the simulated cobot near the start


def _run(capsys, *args):
    rc = main(["correct", *map(str, args), "--json"])
    return rc, json.loads(capsys.readouterr().out)


def _rows(path):
    return list(csv.DictReader(path.open()))


def _mm(row, keys):
    return np.array([float(row[k]) for k in keys])


def test_a_path_is_corrected_at_every_set_point(twin_dir, tmp_path, capsys):
    twin = Twin.load(twin_dir)
    (tmp_path / "seam.yaml").write_text(SEAM.format(extra=""))
    out = tmp_path / "seam_setpoints.csv"
    rc, r = _run(capsys, "--twin", twin_dir, "--path", tmp_path / "seam.yaml", "--rate", 125, "--out", out)
    assert rc == 0, r
    rows = _rows(out)
    assert r["kind"] == "path" and r["n"] == len(rows) and r["segments"] == 4 and r["rate_hz"] == 125
    assert r["n_outside"] == 0 and r["max_speed_mm_s"] == pytest.approx(250.0)
    assert list(rows[0]) == ["t", "segment", "x", "y", "z", "speed", "cx", "cy", "cz", "Ux", "Uy", "Uz", "inside",
                             "distance_mm"]
    t = np.array([float(x["t"]) for x in rows])
    assert np.allclose(np.diff(t), 1 / 125) and r["duration_s"] == pytest.approx(t[-1])
    assert [int(x["segment"]) for x in (rows[0], rows[-1])] == [0, 3]
    # every set-point: Twin.correct at the segment's programmed speed (the map's speed input)
    for row in rows[::20] + [rows[-1]]:
        target = _mm(row, "xyz") * 1e-3
        v = 0.1 if row["segment"] == "2" else 0.25
        c = twin.correct(target, v)
        assert _mm(row, ("cx", "cy", "cz")) == pytest.approx(c.command * 1e3, abs=2e-6)
        assert _mm(row, ("Ux", "Uy", "Uz")) == pytest.approx(c.U * 1e3, abs=2e-6)
    assert _mm(rows[-1], "xyz") == pytest.approx([1000, 120, 600])


@pytest.mark.parametrize("text, message", [
    (SEAM.format(extra="").replace("via:", "vai:"), "key 'segments.1.arc.via': value '<missing>'"),
    (SEAM.format(extra="").replace("[1000, 120, 600]", "[1000, 120, 3000]"),
     "set-points lie beyond the arm's reach (2338 mm from its base"),
    (SEAM.format(extra="").replace("acceleration: 2000", "acceleration: 0"), "key 'acceleration': value 0"),
])
def test_a_bad_path_is_refused_and_nothing_is_written(twin_dir, tmp_path, capsys, text, message):
    (tmp_path / "bad.yaml").write_text(text)
    out = tmp_path / "never.csv"
    rc, r = _run(capsys, "--twin", twin_dir, "--path", tmp_path / "bad.yaml", "--out", out)
    assert rc == 2 and message in r["error"] and str(tmp_path / "bad.yaml") in r["error"], r
    assert not out.exists()


def test_refuse_outside_refuses_a_path_leaving_the_calibrated_volume(twin_dir, tmp_path, capsys):
    (tmp_path / "up.yaml").write_text(SEAM.format(extra="").replace("[1000, 120, 600]", "[1000, 120, 1300]"))
    out = tmp_path / "never.csv"
    rc, r = _run(capsys, "--twin", twin_dir, "--path", tmp_path / "up.yaml", "--out", out, "--refuse-outside")
    assert rc == 2 and "set-points need a command outside the calibrated volume: set-point" in r["error"], r
    assert not out.exists()
    rc, r = _run(capsys, "--twin", twin_dir, "--path", tmp_path / "up.yaml", "--out", out)
    assert rc == 0 and 0 < r["n_outside"] < r["n"]


@pytest.fixture(scope="module")
def geometric_twin(quick_demo, tmp_path_factory):
    """The quick demo's campaign calibrated with the geometric effect: a map that reads the joints."""
    out = tmp_path_factory.mktemp("geo") / "twin"
    rc = main(["calibrate", "--campaign", str(quick_demo[2] / "campaign"), "--effects", "geometric",
               "--out", str(out), "--json", "--no-progress"])
    assert rc in (0, 3)  # 3: a validity warning of the quick plan, not a failure to calibrate
    return out


def test_a_joint_space_map_follows_the_arm_along_the_path(geometric_twin, tmp_path, capsys):
    (tmp_path / "seam.yaml").write_text(SEAM.format(extra=""))
    out = tmp_path / "geo.csv"
    rc, r = _run(capsys, "--twin", geometric_twin, "--path", tmp_path / "seam.yaml", "--out", out)
    assert rc == 2 and "need joints; give the path's key joints" in r["error"], r
    (tmp_path / "seam.yaml").write_text(SEAM.format(extra=f"joints: {START_JOINTS}\n"))
    rc, r = _run(capsys, "--twin", geometric_twin, "--path", tmp_path / "seam.yaml", "--rate", 125, "--out", out)
    assert rc == 0, r
    rows = _rows(out)
    twin = Twin.load(geometric_twin)
    chain = twin.e_lt.chain()
    q_start = np.array(json.loads(START_JOINTS))
    # set-point k is corrected where the arm stands at set-point k - 1's command (its joints by the IK)
    for k in (1, 2, 57, len(rows) - 1):
        prev = _mm(rows[k - 1], ("cx", "cy", "cz")) * 1e-3
        cond = Conditions(joints=chain.ik(prev, q_start), previous=prev)
        v = 0.1 if rows[k]["segment"] == "2" else 0.25
        c = twin.correct(_mm(rows[k], "xyz") * 1e-3, v, cond)
        assert _mm(rows[k], ("cx", "cy", "cz")) == pytest.approx(c.command * 1e3, abs=1e-5)
        assert _mm(rows[k], ("Ux", "Uy", "Uz")) == pytest.approx(c.U * 1e3, abs=1e-5)


def test_the_setpoint_benchmark_short_run(twin_dir, geometric_twin):
    """`python -m benchmarks.setpoint` at 50 Hz on both twins: the fast code gives the per-command
    code's numbers, and costs less CPU than it in the same run (ratios, not times)."""
    from benchmarks.setpoint import run

    r = run(50.0, str(twin_dir), str(geometric_twin))
    assert r["n_setpoints"] == 84 and r["ik_us"]["max_joint_diff_rad"] < 1e-9 and r["ik_us"]["mean_steps"] <= 3
    assert r["ik_us"]["speedup"] > 3  # 14x measured at 500 Hz
    for name in ("demo", "geometric"):
        t = r["twins"][name]
        assert t["max_diff_mm"] < 1e-9 and t["correction_us"]["speedup"] > 1.3, (name, t)  # 3.6x, 3.1x measured
        # U: the plain law's own rounding (tests/unit/test_corrector.py, U_ROUNDING)
        assert t["max_diff_U_mm"] < 1e-8 and t["max_diff_numpy_warm_mm"] < 1e-9, (name, t)
    assert r["twins"]["geometric"]["needs"] == ["joints"] and r["twins"]["demo"]["needs"] == []


def test_the_compiled_law_on_a_joint_space_map_is_the_numpy_path(geometric_twin):
    """`Corrector` on geometric terms + a GP: the compiled fixed point (IK, design row, GP in one
    call: twin.law_kernel) gives the numpy path's commands, joints and U, cold and warm-started."""
    from dt_runtime.common import jit
    from dt_runtime.twin.corrector import Corrector

    if not jit.enabled():
        pytest.skip("numba is not installed: the numpy path is all there is")
    twin = Twin.load(geometric_twin)
    fast, slow = Corrector(twin), Corrector(twin, compiled=False)
    assert fast.compiled and not slow.compiled
    q = np.array(json.loads(START_JOINTS))
    start = twin.e_lt.chain().fk(q[None])[0]
    warm = None
    for k in range(80):
        x = start + 1e-3 * k * np.array([0.5, 0.5, 0.0])
        cond = Conditions(joints=q)
        a, b = fast.correct(x, 0.25, cond, warm), slow.correct(x, 0.25, cond, warm)
        assert a.command == pytest.approx(b.command, abs=1e-12) and a.U == pytest.approx(b.U, abs=1e-12)
        assert a.joints == pytest.approx(b.joints, abs=1e-12)
        q, warm = a.joints, (a.command - x if k % 2 else None)
    assert fast.evaluations == slow.evaluations
