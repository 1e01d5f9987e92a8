"""Wrong units and implausible values are caught on import, with a message that names the column
and the likely unit error (issue: diagnosis that holds on data nobody tuned it to)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dt_kernel.errors import DataError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.measurements.checks import joints_vs_commanded, plausible_ranges
from dt_runtime.measurements.dataset import Dataset, write_table

COBOT = load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")
UR10 = load_robot(CONFIGS / "robots" / "ur10.yaml")


def _data(n: int = 40, seed: int = 0) -> Dataset:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.8, 0.8, (n, COBOT.dof)) + np.array([0.0, -0.3, 0.9, 0.0, 0.7, 0.0])
    p = COBOT.fk(q)
    return Dataset(commanded=p, error=rng.normal(0, 2e-4, (n, 3)), joints=q, speed=np.full(n, 0.25),
                   point_id=np.arange(n))


def _fit(tmp_path, ds: Dataset, capsys) -> tuple[int, dict]:
    csv = write_table(ds, tmp_path / "d.csv")
    rc = main(["fit", "--data", str(csv), "--effects", "geometric", "--gp-inputs", "none",
               "--out", str(tmp_path / "m"), "--json", "--no-progress"])
    return rc, json.loads(capsys.readouterr().out)


def test_consistent_joints_pass_and_the_mismatch_is_reported(tmp_path, capsys):
    rc, out = _fit(tmp_path, _data(), capsys)
    assert rc == 0, out
    assert out["joint_check"]["median_mm"] < 1e-3  # FK of the joints is the commanded TCP


def test_joints_in_degrees_are_named(tmp_path, capsys):
    ds = _data()
    ds.joints = np.degrees(ds.joints)
    rc, out = _fit(tmp_path, ds, capsys)
    assert rc == 2 and "d.csv" in out["error"] and "q columns look like degrees" in out["error"]


def test_positions_in_metres_are_named(tmp_path, capsys):
    ds = _data()
    ds.commanded = ds.commanded / 1000.0  # metres written in the mm columns
    rc, out = _fit(tmp_path, ds, capsys)
    assert rc == 2 and "x, y, z columns look like metres" in out["error"]


def test_another_robot_is_named():
    ds = _data()
    with pytest.raises(DataError, match="robot config ur10.*differ by .* another robot"):
        joints_vs_commanded(ds.joints, ds.commanded, UR10, "d.csv")


@pytest.mark.parametrize("column, values, text", [
    ("speed", -0.1, "column 'speed', data row 1: -100 mm/s"),
    ("payload", -2.0, "column 'payload', data row 1: -2 kg"),
    ("temperature", 500.0, "column 'temperature', data row 1: 500 deg C"),
])
def test_implausible_values_name_column_row_and_range(column, values, text):
    n = 5
    cols = {"speed": np.full(n, 0.2), "payload": np.zeros(n), "temperature": np.full(n, 21.0)}
    cols[column] = np.full(n, values)
    with pytest.raises(DataError, match="allowed") as e:
        plausible_ranges(cols, np.full((n, 3), 0.5), "d.csv")
    assert text in str(e.value) and "d.csv" in str(e.value)


@pytest.mark.parametrize("argv", [
    ["diagnose", "--data", "x.csv", "--folds", "1"],
    ["diagnose", "--data", "x.csv", "--folds", "0"],
    ["fit", "--data", "x.csv", "--out", "m", "--cv", "-3"],
    ["compare", "--data", "x.csv", "--model", "m", "--cv", "1"],
])
def test_fold_counts_are_validated(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "folds" in err or "--cv" in err


# --- issue 22: units and columns checked on every table, with or without a robot config ---------------
def _csv(tmp_path, ds: Dataset, rename: dict[str, str] | None = None):
    csv = write_table(ds, tmp_path / "d.csv")
    if rename:
        head, rest = csv.read_text().split("\n", 1)
        csv.write_text(",".join(rename.get(c, c) for c in head.split(",")) + "\n" + rest)
    return csv


def _dt(capsys, *argv: str) -> tuple[int, dict]:
    rc = main([*argv, "--json", "--no-progress"])
    return rc, json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("command", ["fit", "diagnose", "compare"])
def test_a_table_in_metres_is_refused_without_joints_and_nothing_is_written(tmp_path, capsys, command):
    ds = _data()
    ds.joints = None
    ds.commanded, ds.error = ds.commanded / 1000.0, ds.error / 1000.0  # the whole table in metres
    csv = _csv(tmp_path, ds)
    out = tmp_path / "m"
    argv = {"fit": ["fit", "--data", str(csv), "--out", str(out)],
            "diagnose": ["diagnose", "--data", str(csv), "--folds", "3"],
            "compare": ["compare", "--data", str(csv), "--model", str(out), "--report", str(tmp_path / "r")]}[command]
    rc, res = _dt(capsys, *argv)
    assert rc == 2 and "d.csv: columns x, y, z: largest |value| " in res["error"], res
    assert "this looks like metres" in res["error"] and "units: {position: m}" in res["error"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv"]  # no model, no report


@pytest.mark.parametrize("wrong, right", [("sped", "speed"), ("Temperature", "temperature"), ("point id", "point_id"),
                                          ("temprature", "temperature"), ("e_x", "ex")])
def test_a_misspelled_contract_column_is_refused_naming_the_contract_name(tmp_path, capsys, wrong, right):
    ds = _data()
    ds.temperature = np.full(ds.n, 21.0)
    csv = _csv(tmp_path, ds, {right: wrong})
    rc, res = _dt(capsys, "fit", "--data", str(csv), "--gp-inputs", "tcp", "--out", str(tmp_path / "m"))
    assert rc == 2 and f"column '{wrong}' is not a contract column but looks like '{right}'" in res["error"], res
    assert not (tmp_path / "m").exists()


def test_a_column_far_from_every_contract_name_stays_an_extra_column(tmp_path, capsys):
    from dt_runtime.measurements.dataset import read_table

    ds = _data()
    ds.extra = {"humidity": np.linspace(30, 60, ds.n), "fixture_temperature": np.full(ds.n, 22.5)}
    csv = write_table(ds, tmp_path / "d.csv")
    head, rest = csv.read_text().split("\n", 1)
    rows = rest.strip().split("\n")
    csv.write_text(head + ",humidity,fixture_temperature\n"
                   + "".join(f"{r},{30 + i},22.5\n" for i, r in enumerate(rows)))
    assert sorted(read_table(csv).extra) == ["fixture_temperature", "humidity"]
    rc, res = _dt(capsys, "fit", "--data", str(csv), "--gp-inputs", "tcp", "--out", str(tmp_path / "m"))
    assert rc == 0, res


def test_joints_in_degrees_are_refused_when_no_model_reads_them(tmp_path, capsys):
    ds = _data()
    ds.joints = np.degrees(ds.joints)
    rc, res = _dt(capsys, "fit", "--data", str(_csv(tmp_path, ds)), "--gp-inputs", "tcp", "--out", str(tmp_path / "m"))
    assert rc == 2 and "d.csv: column 'q" in res["error"] and "this looks like degrees" in res["error"], res
    assert not (tmp_path / "m").exists()
