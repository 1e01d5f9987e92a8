"""`dt correct`: a program corrected offline, with the uncertainty and the volume flag of every
position; bad programs get a clear error and nothing is written."""
import csv
import json

import numpy as np
import pytest

from dt_runtime.cli.main import main
from dt_runtime.twin.twin import Twin


def _program(path, rows):
    path.write_text("point_id,x,y,z,speed\n" + "".join(f"{r}\n" for r in rows))
    return path


def _far_target(twin):
    t = np.array([0.9, 0.0, 0.55])
    while twin.volume.distance(t)[0] < 0.12:
        t = t + np.array([0.0, 0.0, 0.01])
    return t


def test_corrects_a_program_and_flags_extrapolation(quick_demo, tmp_path, capsys):
    twin_dir = quick_demo[2] / "model"
    twin = Twin.load(twin_dir)
    far = _far_target(twin) * 1e3
    prog = _program(tmp_path / "p.csv", ["a,900,0,550,500", "b,880,40,560,250", f"far,{far[0]},{far[1]},{far[2]},250"])
    out = tmp_path / "out" / "p_corr.csv"
    assert main(["correct", "--twin", str(twin_dir), "--targets", str(prog), "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n"] == 3 and res["n_outside"] == 1
    rows = list(csv.DictReader(out.open()))
    assert [r["point_id"] for r in rows] == ["a", "b", "far"] and [r["inside"] for r in rows] == ["1", "1", "0"]
    c = twin.correct(np.array([0.9, 0.0, 0.55]), 0.5)
    assert [float(rows[0][k]) for k in ("cx", "cy", "cz")] == pytest.approx(c.command * 1e3, abs=1e-6)
    assert [float(rows[0][k]) for k in ("Ux", "Uy", "Uz")] == pytest.approx(c.U * 1e3, abs=1e-6)
    assert all(float(rows[2][f"U{a}"]) > float(rows[0][f"U{a}"]) for a in "xyz")
    assert float(rows[2]["distance_mm"]) > 100 and float(rows[0]["distance_mm"]) < 0


def test_refuse_outside_writes_nothing(quick_demo, tmp_path, capsys):
    twin_dir = quick_demo[2] / "model"
    far = _far_target(Twin.load(twin_dir)) * 1e3
    prog = _program(tmp_path / "p.csv", ["a,900,0,550,500", f"far,{far[0]},{far[1]},{far[2]},250"])
    out = tmp_path / "p_corr.csv"
    rc = main(["correct", "--twin", str(twin_dir), "--targets", str(prog), "--out", str(out), "--refuse-outside",
               "--json"])
    assert rc == 2 and not out.exists()
    assert "outside the calibrated volume: far (line 3)" in json.loads(capsys.readouterr().out)["error"]


@pytest.mark.parametrize("rows, message", [
    (["a,900,0,550,0"], "line 2: column 'speed'"),
    (["a,900,zero,550,100"], "line 2: column 'y'"),
    ([], "no targets"),
])
def test_bad_programs_name_line_and_column(quick_demo, tmp_path, capsys, rows, message):
    prog = _program(tmp_path / "p.csv", rows)
    out = tmp_path / "p_corr.csv"
    rc = main(["correct", "--twin", str(quick_demo[2] / "model"), "--targets", str(prog), "--out", str(out), "--json"])
    assert rc == 2 and not out.exists()
    assert message in json.loads(capsys.readouterr().out)["error"]


@pytest.mark.parametrize("header, rows, message", [
    # metres in the mm columns (issue 22: a program was written, every target ~1 mm from the base)
    ("point_id,x,y,z,speed", ["a,0.9,0,0.55,500", "b,0.88,0.04,0.56,250"], "columns x, y, z: largest |value| 0.9 mm; "
     "this looks like metres"),
    ("point_id,x,y,z,speed", ["a,900,0,550,500", "b,1e300,0,550,250"], "data row 2: [1e+300, 0.0, 550.0] mm lies more "
     "than 5000 mm from the base"),
    ("point_id,x,y,z,speed", ["a,900,0,550,500", "b,4000,0,550,250"], "1 of 2 targets lie beyond the arm's reach "
     "(2338 mm from its base, robot config cobot_hc20_like"),
    ("point_id,x,y,z,speed", ["a,900,0,550,500", "b,inf,0,550,250"], "line 3: column 'x': value 'inf': not a finite"),
    ("point_id,x,y,z,speed", ["a,900,0,nan,500"], "line 2: column 'z': value 'nan': not a finite"),
    ("point_id,x,y,z,speed", ["a,900,0,550,5e5"], "column 'speed', data row 1: 500000 mm/s is not plausible"),
    ("point_id,x,y,z,sped", ["a,900,0,550,500"], "column 'sped' is not a contract column but looks like 'speed'"),
    ("point_id,x,y,z,speed,Temperature", ["a,900,0,550,500,21"], "column 'Temperature' is not a contract column but "
     "looks like 'temperature'"),
    ("point_id,x,y,z,speed,q1,q2,q3,q4,q5,q6", ["a,900,0,550,500,0,20,30,0,45,0"], "line 2: column 'q2': value "
     "'20': joint angles are in rad (|q| <= 2 pi); this looks like degrees"),
])
def test_targets_in_another_unit_or_outside_the_workspace_are_refused(quick_demo, tmp_path, capsys, header, rows,
                                                                      message):
    prog = tmp_path / "p.csv"
    prog.write_text(header + "\n" + "".join(f"{r}\n" for r in rows))
    out = tmp_path / "p_corr.csv"
    rc = main(["correct", "--twin", str(quick_demo[2] / "model"), "--targets", str(prog), "--out", str(out), "--json"])
    err = json.loads(capsys.readouterr().out)["error"]
    assert rc == 2 and not out.exists() and list(tmp_path.iterdir()) == [prog], err
    assert message in err and "p.csv" in err


def test_a_twin_without_its_robot_config_bounds_the_workspace_by_its_volume(quick_demo, tmp_path):
    from dt_kernel.errors import DataError
    from dt_runtime.programs.program import FAR_OUTSIDE_M, check_workspace, read_program

    twin = Twin.load(quick_demo[2] / "model")
    twin.e_lt.robot = None  # an older twin, or one whose robot config is gone
    t = np.array([0.9, 0.0, 0.55])
    while twin.volume.distance(t)[0] < FAR_OUTSIDE_M + 0.01:
        t = t + np.array([0.0, 0.0, 0.02])
    near = _far_target(twin)  # 120 mm outside: corrected and flagged, not refused
    prog = read_program(_program(tmp_path / "p.csv", [f"near,{near[0] * 1e3},{near[1] * 1e3},{near[2] * 1e3},250",
                                                      f"far,{t[0] * 1e3},{t[1] * 1e3},{t[2] * 1e3},250"]))
    with pytest.raises(DataError, match=r"1 of 2 targets lie beyond the workspace: more than 500 mm outside the "
                                        r"twin's calibrated volume .*: far \(line 3"):
        check_workspace(twin, prog, "p.csv")


def test_not_a_twin(tmp_path, capsys):
    prog = _program(tmp_path / "p.csv", ["a,900,0,550,500"])
    rc = main(["correct", "--twin", str(tmp_path), "--targets", str(prog), "--out", str(tmp_path / "o.csv"), "--json"])
    assert rc == 2 and "twin" in json.loads(capsys.readouterr().out)["error"]


def test_the_daemon_corrector_states_per_position_U_and_can_refuse_extrapolation(quick_demo):
    from dt_runtime.twin.bounds import CorrectionFault, Guard, Limits

    twin = Twin.load(quick_demo[2] / "model")
    far = _far_target(twin)
    inside_t = np.array([0.9, 0.0, 0.55])
    flag_only = Guard(twin, Limits())
    a, b = flag_only(inside_t, 0.5), Guard(twin, Limits())(far, 0.5)
    assert a.inside and not b.inside and np.all(b.U_tcp > a.U_tcp)
    assert np.allclose(a.U_tcp, twin.correct(inside_t, 0.5).U)
    strict = Guard(twin, Limits(refuse_outside_volume=True))
    assert strict(inside_t, 0.5).inside
    with pytest.raises(CorrectionFault, match="outside the calibrated volume"):
        strict(far, 0.5)
    # The workspace bounds the corrected command, not only the target.
    c = twin.correct(inside_t, 0.5).command
    lo = np.minimum(c, inside_t) - 0.5
    edge = Limits(workspace_min_m=tuple(lo), workspace_max_m=tuple(np.maximum(inside_t, c - 1e-9 * np.sign(c - inside_t))))
    with pytest.raises(CorrectionFault, match="corrected command .* outside the workspace"):
        Guard(twin, edge)(inside_t, 0.5)


def test_the_daemon_runs_the_cells_program(quick_demo, tmp_path):
    from dt_kernel.errors import ConfigError
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.service.daemon import Daemon, RuntimeConfig

    prog = _program(tmp_path / "p.csv", ["a,900,0,550,500", "b,880,40,560,250", "c,920,-30,600,400"])
    base = {"twin": str(quick_demo[2] / "model"), "store": str(tmp_path / "dt.sqlite"), "realtime": False,
            "publish": False, "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"),
                                      "cell": str(CONFIGS / "cell.yaml")}}
    cfg = RuntimeConfig.model_validate(base | {"path": {"kind": "program", "program": str(prog)}})
    d = Daemon(cfg, CONFIGS)
    try:
        d.run(max_ticks=5)
    finally:
        d.close()
    import sqlite3

    db = sqlite3.connect(tmp_path / "dt.sqlite")
    cmds = db.execute("SELECT x, y, z, speed FROM commands ORDER BY t").fetchall()
    corrs = db.execute("SELECT dx, dy, dz, ux FROM corrections ORDER BY t").fetchall()
    db.close()
    twin = Twin.load(quick_demo[2] / "model")
    want = [np.array(p) * 1e-3 for p in ([900, 0, 550], [880, 40, 560], [920, -30, 600], [900, 0, 550], [880, 40, 560])]
    assert len(cmds) == len(corrs) == 5  # the program, in order, then from its start again
    for cmd, corr, w, v in zip(cmds, corrs, want, (0.5, 0.25, 0.4, 0.5, 0.25)):
        c = twin.correct(w, v)
        assert np.allclose(cmd[:3], w, atol=1e-12) and cmd[3] == pytest.approx(v)
        assert np.allclose(corr[:3], c.command - w, atol=1e-12)
        assert corr[3] == pytest.approx(c.budget.combined()[0])  # the per-position u, not a constant
    from dt_kernel.config import validate

    with pytest.raises(ConfigError, match="path.program names the program file"):
        validate(RuntimeConfig, base | {"path": {"kind": "program"}}, "runtime.yaml")
