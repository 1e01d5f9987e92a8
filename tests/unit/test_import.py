"""Import mappings: foreign layouts, units, registration with a probe offset, the UR10 data."""
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.measurements.dataset import read_table, write_table
from dt_runtime.measurements.importer import ImportMapping, import_file, load_mapping
from dt_runtime.measurements.registration_fit import fit_rigid_offset

ROOT = Path(__file__).resolve().parents[2]
UR10_MAPPING = ROOT / "configs" / "import" / "ur10.yaml"
UR10_DATA = ROOT / "dt_runtime" / "data" / "ipa_ur10"


def _comma(v: float) -> str:
    return repr(float(v)).replace(".", ",")


def _write_foreign(path, header, rows):
    path.write_text(";".join(header) + "\n" + "\n".join(";".join(r) for r in rows) + "\n", encoding="utf-8")
    return path


FOREIGN = {
    "separator": ";", "decimal": ",",
    "columns": {"x": "X [m]", "y": "Y [m]", "z": "Z [m]", "joints": ["A1", "A2"],
                "speed": "v", "temperature": "T", "ex": "dX", "ey": "dY", "ez": "dZ"},
    "units": {"position": "m", "measurement": "mm", "joints": "deg", "speed": "m/s"},
    "error_sign": "measured_minus_commanded",
    "time": {"source": "seconds", "column": "time"},
}


def test_decimal_comma_semicolon_degrees_mapping(tmp_path):
    p = _write_foreign(tmp_path / "foreign.csv", ["time", "X [m]", "Y [m]", "Z [m]", "A1", "A2", "v", "T", "dX", "dY", "dZ", "note"], [
        ["10,5", "0,5", "-0,25", "1,0", "90", "-45,5", "0,25", "21,5", "0,1", "-0,2", "0,3", "a"],
        ["12,0", "0,6", "-0,25", "1,0", "180", "0", "0,5", "", "1,0E-2", "0", "0", "b"],
    ])
    m = ImportMapping.model_validate(FOREIGN)
    ds, rep = import_file(p, m)
    np.testing.assert_allclose(ds.commanded, [[0.5, -0.25, 1.0], [0.6, -0.25, 1.0]])
    np.testing.assert_allclose(ds.joints, np.radians([[90, -45.5], [180, 0]]))
    np.testing.assert_allclose(ds.speed, [0.25, 0.5])
    assert ds.temperature[0] == 21.5 and np.isnan(ds.temperature[1])
    # file gives measured - commanded: the dataset holds commanded - measured
    np.testing.assert_allclose(ds.error, [[-1e-4, 2e-4, -3e-4], [-1e-5, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(ds.t, [0.0, 1.5])
    assert rep.method == "none" and rep.n == 2
    assert rep.rms_3d_mm == pytest.approx(np.sqrt(np.mean(np.sum((ds.error * 1e3) ** 2, 1))))
    # the imported table is a contract table
    back = read_table(write_table(ds, tmp_path / "contract.csv"))
    np.testing.assert_allclose(back.error, ds.error, atol=1e-15)


def test_foreign_bad_row_and_skip_bad(tmp_path):
    rows = [["1,0", "0,5", "0", "1", "0", "0", "0,1", "20", "0", "0", "0", "x"]] * 3
    rows[1] = ["2,0", "0,5", "0", "1", "0", "0", "0.1", "20", "0", "0", "0", "x"]  # '.' in a ',' file
    p = _write_foreign(tmp_path / "f.csv", ["time", "X [m]", "Y [m]", "Z [m]", "A1", "A2", "v", "T", "dX", "dY", "dZ", "n"], rows)
    m = ImportMapping.model_validate({**FOREIGN, "time": "row_order"})
    with pytest.raises(DataError, match=r"f\.csv: line 3: column 'v': value '0\.1'"):
        import_file(p, m)
    ds, rep = import_file(p, m, skip_bad=True)
    assert ds.n == 2 and rep.n_skipped == 1 and ds.skipped[0].line == 3
    assert ds.t.tolist() == [0.0, 1.0]


def test_mapping_validation_names_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("separator: ';'\ndecimal: ';'\ncolumns: {x: a, y: b, z: c, ex: d, ey: e, ez: f}\n")
    with pytest.raises(ConfigError) as exc:
        load_mapping(bad)
    assert exc.value.key == "decimal" and "bad.yaml" in str(exc.value)
    with pytest.raises(ValidationError, match="exactly one"):
        ImportMapping.model_validate({"columns": {"x": "a", "y": "b", "z": "c", "ex": "d", "ey": "e", "ez": "f",
                                                  "mx": "g", "my": "h", "mz": "i"}})
    with pytest.raises(ValidationError, match="instrument"):
        ImportMapping.model_validate({"measured_frame": "instrument",
                                      "columns": {"x": "a", "y": "b", "z": "c", "ex": "d", "ey": "e", "ez": "f"}})


def _synthetic_tracker(n=60, seed=3, noise_mm=0.01):
    rng = np.random.default_rng(seed)
    R_true = Rotation.from_euler("xyz", [5.0, -12.0, 140.0], degrees=True).as_matrix()
    t_true = np.array([1.2, -0.4, 0.3])                      # m
    o_true = np.array([0.012, -0.004, 0.105])                # m, probe on the flange
    p_f = rng.uniform([-0.6, -0.6, 0.2], [0.6, 0.6, 1.2], (n, 3))
    eul = np.column_stack([rng.uniform(-180, 180, n), rng.uniform(-60, 60, n), rng.uniform(-180, 180, n)])
    R_f = Rotation.from_euler("ZYX", eul, degrees=True).as_matrix()  # intrinsic, degrees
    p_robot = p_f + R_f @ o_true + rng.normal(0, noise_mm * 1e-3, (n, 3))
    p_inst = (p_robot - t_true) @ R_true                     # R^T (p - t)
    return p_f, eul, R_f, p_inst, R_true, t_true, o_true


def test_registration_recovers_transform_and_probe_offset(tmp_path):
    p_f, eul, R_f, p_inst, R_true, t_true, o_true = _synthetic_tracker()
    fit = fit_rigid_offset(p_inst, p_f, R_f)
    assert fit.offset_dof == 3
    assert Rotation.from_matrix(fit.rotation @ R_true.T).magnitude() < 1e-4
    np.testing.assert_allclose(fit.translation, t_true, atol=2e-5)
    np.testing.assert_allclose(fit.offset, o_true, atol=2e-5)

    # the same through a foreign file: mm in the tracker frame, m and degrees (intrinsic ZYX)
    header = ["px", "py", "pz", "a", "b", "c", "tx", "ty", "tz"]
    rows = [[_comma(v) for v in np.r_[p_f[i], eul[i], p_inst[i] * 1e3]] for i in range(len(p_f))]
    path = _write_foreign(tmp_path / "tracker.csv", header, rows)
    m = ImportMapping.model_validate({
        "separator": ";", "decimal": ",", "measured_frame": "instrument",
        "columns": {"x": "px", "y": "py", "z": "pz", "orientation": ["a", "b", "c"],
                    "mx": "tx", "my": "ty", "mz": "tz"},
        "units": {"position": "m", "measurement": "mm", "orientation": "deg"},
        "orientation_convention": "ZYX"})
    ds, rep = import_file(path, m)
    assert rep.method == "rigid+offset"
    np.testing.assert_allclose(rep.offset, o_true, atol=2e-5)
    np.testing.assert_allclose(rep.translation, t_true, atol=2e-5)
    assert np.all(rep.offset_std_mm < 0.02)
    # residual = the injected 10 um noise per axis
    assert 0.01 < rep.rms_3d_mm < 0.03 and np.all(rep.rms_axis_mm < 0.02)
    np.testing.assert_allclose(ds.commanded, p_f + R_f @ o_true, atol=3e-5)
    np.testing.assert_allclose(ds.error, ds.commanded - ds.measured)
    assert rep.to_dict()["offset_mm"] == pytest.approx(list(o_true * 1e3), abs=0.02)


@pytest.mark.parametrize("order", ["quaternion_wxyz", "quaternion_xyzw"])
def test_quaternion_orientation_columns_carry_the_probe_offset(tmp_path, order):
    """A tracker export with the flange orientation as a quaternion (scalar first or last)."""
    p_f, _, R_f, p_inst, _, t_true, o_true = _synthetic_tracker()
    q = Rotation.from_matrix(R_f).as_quat()  # x, y, z, w
    q = q if order == "quaternion_xyzw" else q[:, [3, 0, 1, 2]]
    header = ["px", "py", "pz", "q1", "q2", "q3", "q4", "tx", "ty", "tz"]
    rows = [[f"{v:.12g}" for v in np.r_[p_f[i], q[i], p_inst[i] * 1e3]] for i in range(len(p_f))]
    path = tmp_path / "tracker.csv"
    path.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n")
    mapping = {"measured_frame": "instrument", "orientation_convention": order,
               "columns": {"x": "px", "y": "py", "z": "pz", "orientation": ["q1", "q2", "q3", "q4"],
                           "mx": "tx", "my": "ty", "mz": "tz"},
               "units": {"position": "m", "measurement": "mm"}}
    ds, rep = import_file(path, ImportMapping.model_validate(mapping))
    assert rep.method == "rigid+offset"
    np.testing.assert_allclose(rep.offset, o_true, atol=2e-5)
    np.testing.assert_allclose(rep.translation, t_true, atol=2e-5)
    np.testing.assert_allclose(ds.commanded, p_f + R_f @ o_true, atol=3e-5)
    # a quaternion that is not of unit length (a column in the wrong place, a unit) is refused
    rows[4][3] = "2"
    path.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n")
    with pytest.raises(DataError, match="quaternion of data row 5 has length"):
        import_file(path, ImportMapping.model_validate(mapping))
    # three columns for a quaternion, or four for Euler angles: named
    with pytest.raises(DataError, match="takes 4"):
        import_file(path, ImportMapping.model_validate(
            mapping | {"columns": mapping["columns"] | {"orientation": ["q1", "q2", "q3"]}}))
    with pytest.raises(DataError, match="takes 3"):
        import_file(path, ImportMapping.model_validate(mapping | {"orientation_convention": "xyz"}))


def test_registration_without_orientation_variety_keeps_offset():
    p_f, eul, R_f, p_inst, R_true, t_true, o_true = _synthetic_tracker()
    fixed = np.broadcast_to(R_f[0], R_f.shape)
    p_inst = (p_f + fixed @ o_true - t_true) @ R_true
    fit = fit_rigid_offset(p_inst, p_f, fixed)
    assert fit.offset_dof == 0 and np.all(fit.offset == 0)
    assert np.sqrt(np.mean(np.sum(fit.residual ** 2, 1))) < 1e-9  # t absorbs R_f o


def test_timestamps_sorted_and_mangled_fallback(tmp_path):
    base = {"separator": ";", "decimal": ",", "columns": {"x": "x", "y": "y", "z": "z", "ex": "e", "ey": "e", "ez": "e"},
            "time": {"source": "timestamp", "column": "Timestamp", "order": "sort", "fallback": "row_order"}}
    rows = [["20200714163904", "1", "0", "0", "0"], ["20200714163924", "2", "0", "0", "0"],
            ["20200714163914", "3", "0", "0", "0"]]
    p = _write_foreign(tmp_path / "ts.csv", ["Timestamp", "x", "y", "z", "e"], rows)
    ds, rep = import_file(p, ImportMapping.model_validate(base))
    assert ds.t.tolist() == [0.0, 10.0, 20.0] and ds.lines.tolist() == [2, 4, 3]
    assert any("sorted" in s for s in rep.notes)
    rows = [["2,02011E+13", "1", "0", "0", "0"]] * 3
    p = _write_foreign(tmp_path / "mangled.csv", ["Timestamp", "x", "y", "z", "e"], rows)
    ds, rep = import_file(p, ImportMapping.model_validate(base))
    assert ds.t.tolist() == [0.0, 1.0, 2.0] and any("row index" in s for s in rep.notes)
    strict = {**base, "time": {"source": "timestamp", "column": "Timestamp"}}
    with pytest.raises(DataError, match=r"line 2: column 'Timestamp': value '2,02011E\+13'"):
        import_file(p, ImportMapping.model_validate(strict))


def test_ur10_series_d_rigid_registration_residual():
    ds, rep = import_file(UR10_DATA / "Series_D" / "measurements_iso_cubes.csv", UR10_MAPPING)
    assert ds.n == 632 and ds.joints.shape == (632, 6) and ds.flange_rotation.shape == (632, 3, 3)
    # docs/results.md: 0.78 mm RMS left after a rigid registration (base pose + probe offset)
    assert 0.6 < rep.rms_3d_mm < 1.0
    assert rep.method == "rigid+offset"
    assert ds.u is not None and np.all(ds.u < 1e-4)          # tracker std, mm -> m
    assert np.all(np.abs(ds.temperature - 20.7) < 1.0)
    assert ds.t.tolist() == list(range(632))                  # mangled timestamps: row order
    assert len(np.unique(ds.point_id)) == ds.n


def test_ur10_data_ships_with_licence():
    assert (UR10_DATA / "LICENSE.md").read_text().startswith("MIT License")
    for s in "ABCD":
        assert list((UR10_DATA / f"Series_{s}").glob("measurements_*.csv"))
        assert (UR10_DATA / f"Series_{s}" / "Trafo_TM_F_init.txt").exists()


def test_a_latin1_export_reads_with_the_mappings_encoding(tmp_path):
    """A tracker's export in Latin-1 (a degree sign in a header, an umlaut in a note): refused as
    UTF-8 with a message that names the option, read with `encoding: latin-1`."""
    header = ["time", "X [m]", "Y [m]", "Z [m]", "A1", "A2", "v", "T", "dX", "dY", "dZ", "Bemerkung"]
    rows = [["10,5", "0,5", "-0,25", "1,0", "90", "-45,5", "0,25", "21,5", "0,1", "-0,2", "0,3", "Prüfung"],
            ["12,0", "0,6", "-0,25", "1,0", "180", "0", "0,5", "21,6", "0,01", "0", "0", "größer"]]
    p = tmp_path / "export.csv"
    p.write_text(";".join(header) + "\n" + "\n".join(";".join(r) for r in rows) + "\n", encoding="latin-1")
    with pytest.raises(DataError, match="encoding: latin-1"):
        import_file(p, ImportMapping.model_validate(FOREIGN))
    ds, _ = import_file(p, ImportMapping.model_validate(FOREIGN | {"encoding": "latin-1"}))
    assert ds.n == 2 and ds.temperature[1] == pytest.approx(21.6)
    with pytest.raises(ValueError, match="unknown text encoding"):
        ImportMapping.model_validate(FOREIGN | {"encoding": "klingon-8"})
