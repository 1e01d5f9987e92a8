"""Campaigns, not files (issue 13, part 7): a joint-angle table joined to a measurement file (by
row or by a key), the commanded TCP from the joints' forward kinematics, a registration per
session (fitted or given) and re-registration after correction."""
from __future__ import annotations

import numpy as np
import pytest

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.analysis.reregister import reregistered
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.measurements.importer import ImportMapping, import_file, load_mapping
from tests.support.campaign_generator import write_campaign
from tests.support.ur10_generator import fk

UR10 = CONFIGS / "robots" / "ur10.yaml"
JOINTS = [f"J{j}" for j in range(1, 7)]


def _files(tmp_path, n=12, order=None, seed=4):
    """A robot-frame measurement file (points only, 'id;mx;my;mz') and its joints ('id;J1..J6',
    degrees, decimal comma), the joints' rows in `order` (default the file's). Returns (q rad, error m)."""
    rng = np.random.default_rng(seed)
    q_deg = np.round(rng.uniform(-120, 120, (n, 6)), 4)
    q = np.deg2rad(q_deg)
    err = rng.normal(0, 2e-4, (n, 3))  # commanded - measured, m
    meas = fk(q) - err
    (tmp_path / "m.csv").write_text("id;mx;my;mz\n" + "\n".join(
        f"{i + 1};" + ";".join(f"{v * 1e3:.6f}" for v in p) for i, p in enumerate(meas)) + "\n", encoding="utf-8")
    order = np.arange(n) if order is None else np.asarray(order)
    (tmp_path / "m_joints.csv").write_text("id;" + ";".join(JOINTS) + "\n" + "\n".join(
        f"{i + 1};" + ";".join(f"{v:.4f}".replace(".", ",") for v in q_deg[i]) for i in order) + "\n",
        encoding="utf-8")
    return q, err


def _mapping(join="row", **kw) -> ImportMapping:
    return ImportMapping.model_validate({
        "separator": ";", "columns": {"mx": "mx", "my": "my", "mz": "mz"},
        "joints": {"path": "{stem}_joints.csv", "separator": ";", "decimal": ",", "columns": JOINTS, "unit": "deg",
                   "join": join}} | kw)


def test_join_by_row_order_gives_the_commanded_tcp_from_the_joints(tmp_path):
    q, err = _files(tmp_path)
    ds, rep = import_file(tmp_path / "m.csv", _mapping("row"), robot=UR10)
    np.testing.assert_allclose(ds.joints, q, atol=1e-12)
    np.testing.assert_allclose(ds.commanded, load_robot(UR10).fk(q), atol=1e-12)
    # e = commanded - measured (Eq. 8), to the file's 1e-6 mm rounding
    np.testing.assert_allclose(ds.error, err, atol=1e-9)
    assert ds.flange_rotation is not None and rep.method == "none"
    assert any("forward kinematics" in n for n in rep.notes)


def test_join_by_key_pairs_rows_whatever_the_order(tmp_path):
    q, err = _files(tmp_path, order=np.random.default_rng(1).permutation(12))
    ds, _ = import_file(tmp_path / "m.csv", _mapping({"key": "id"}), robot=UR10)
    np.testing.assert_allclose(ds.joints, q, atol=1e-12)
    np.testing.assert_allclose(ds.error, err, atol=1e-9)
    # the same shuffled table joined by row order pairs wrong joints: the error is the FK of another pose
    ds_wrong, _ = import_file(tmp_path / "m.csv", _mapping("row"), robot=UR10)
    assert np.abs(ds_wrong.error).max() > 0.05


def test_row_join_with_unequal_counts_names_both_files_and_counts(tmp_path):
    _files(tmp_path, order=np.arange(11))
    with pytest.raises(DataError) as e:
        import_file(tmp_path / "m.csv", _mapping("row"), robot=UR10)
    msg = str(e.value)
    assert "m.csv: 12 data rows" in msg and "m_joints.csv has 11" in msg and "join: {key" in msg


def test_key_join_names_a_missing_key(tmp_path):
    _files(tmp_path, order=[i for i in range(12) if i != 6])  # id 7 has no joints
    with pytest.raises(DataError, match=r"line 8: column 'id': value '7': no row of the joint table .* has this key"):
        import_file(tmp_path / "m.csv", _mapping({"key": "id"}), robot=UR10)
    ds, _ = import_file(tmp_path / "m.csv", _mapping({"key": "id"}), robot=UR10, skip_bad=True)
    assert ds.n == 11 and [s.line for s in ds.skipped] == [8] and ds.skipped[0].value == "7"


def test_key_join_names_a_duplicate_key(tmp_path):
    _files(tmp_path, order=[*range(12), 3])  # id 4 twice: which joints?
    want = r"m_joints.csv: key column 'id': 1 duplicate key\(s\) \('4' at lines \[5, 14\]\)"
    with pytest.raises(DataError, match=want):
        import_file(tmp_path / "m.csv", _mapping({"key": "id"}), robot=UR10)


def test_commanded_from_joints_needs_a_robot_and_the_mapping_is_checked_once(tmp_path):
    _files(tmp_path)
    with pytest.raises(DataError, match="--robot FILE"):
        import_file(tmp_path / "m.csv", _mapping("row"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("columns: {x: a, mx: b, my: c, mz: d}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad.yaml.*must be given together"):
        load_mapping(bad)
    bad.write_text("columns: {mx: b, my: c, mz: d}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad.yaml.*no commanded x/y/z: name the joint angles"):
        load_mapping(bad)
    bad.write_text("columns: {mx: b, my: c, mz: d, joints: [a]}\njoints: {path: j.csv, columns: [a], join: column}\n",
                   encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad.yaml: key 'joints.join"):
        load_mapping(bad)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    return write_campaign(tmp_path_factory.mktemp("campaign"), seed=7)


def test_given_registration_keeps_the_robots_whole_error_a_fitted_one_absorbs_its_rigid_part(campaign):
    """Session 1 read twice: with its tracker set-up given (the 4x4 file) the error is the true arm's
    (nominal FK - true position, noise 0.01 mm); fitted on its own points, the registration lands
    near the set-up but absorbs the rigid part of the arm's error, so its residual is smaller."""
    f, truth = campaign["files"][0], campaign["sessions"][0]
    m = load_mapping(campaign["mapping"])
    fitted, rf = import_file(f, m, robot=UR10)
    given, rg = import_file(f, m.model_copy(update={"registration": m.registration.model_copy(
        update={"transform": "{stem}_trafo.txt"})}), robot=UR10)
    assert (rf.method, rg.method) == ("rigid", "given")
    true_error = truth["commanded"] - truth["actual"]
    dev = np.linalg.norm(given.error - true_error, axis=1)
    assert dev.max() < 6e-5 and np.sqrt(np.mean(dev ** 2)) < 3e-5  # the tracker noise, 0.017 mm 3D RMS
    np.testing.assert_allclose(rg.rotation, truth["R"], atol=1e-9)
    assert rf.rms_3d_mm < rg.rms_3d_mm - 0.02  # the fit absorbed a rigid part of the arm's error
    ang = np.linalg.norm(np.array(_rotvec(rf.rotation @ truth["R"].T)))
    assert ang < 1e-3 and np.linalg.norm(rf.translation - truth["t"]) < 3e-3  # near the true set-up


def _rotvec(R):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def test_a_given_transform_file_that_is_not_rigid_is_refused(campaign, tmp_path):
    m = load_mapping(campaign["mapping"])
    f = campaign["files"][0]
    (tmp_path / "scaled.txt").write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n", encoding="utf-8")
    reg = m.registration.model_copy(update={"transform": {f.name: str(tmp_path / "scaled.txt")}})
    with pytest.raises(DataError, match=r"scaled.txt: the 3x3 block scales by 2"):
        import_file(f, m.model_copy(update={"registration": reg}), robot=UR10)
    reg = m.registration.model_copy(update={"transform": {"other.csv": "x.txt"}})
    with pytest.raises(ConfigError, match=r"registration.transform.*an entry for the data file 's1.csv'"):
        import_file(f, m.model_copy(update={"registration": reg}), robot=UR10)


def test_reregistration_absorbs_a_rigid_difference_and_only_that():
    rng = np.random.default_rng(2)
    m = rng.uniform(-1, 1, (50, 3))
    noise = rng.normal(0, 1e-5, (50, 3))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([2e-4, -1e-4, 3e-4]).as_matrix()
    rigid = m @ R.T + [1e-4, -2e-4, 5e-5] - m  # what a registration can absorb
    after, T = reregistered(m, rigid + noise)
    assert np.sqrt(np.mean(np.sum(after ** 2, 1))) < np.sqrt(np.mean(np.sum(noise ** 2, 1)))
    np.testing.assert_allclose(T.R, R, atol=1e-5)  # the noise (1e-5 over +-1) limits it to a few 1e-6
    bend = 1e-4 * np.column_stack([m[:, 0] ** 2, np.zeros(50), np.zeros(50)])  # not rigid: mostly kept
    after, _ = reregistered(m, bend)
    assert np.sqrt(np.mean(np.sum(after ** 2, 1))) > 0.5 * np.sqrt(np.mean(np.sum((bend - bend.mean(0)) ** 2, 1)))


def test_the_mapping_in_campaigns_md_is_the_one_the_example_campaign_ships(tmp_path):
    import re

    from dt_runtime.common.paths import ROOT
    from tests.support.campaign_generator import MAPPING

    blocks = re.findall(r"^```yaml\n(.*?)^```", (ROOT / "docs" / "campaigns.md").read_text(encoding="utf-8"),
                        flags=re.S | re.M)
    (tmp_path / "doc.yaml").write_text(blocks[0], encoding="utf-8")
    (tmp_path / "gen.yaml").write_text(MAPPING, encoding="utf-8")
    assert load_mapping(tmp_path / "doc.yaml") == load_mapping(tmp_path / "gen.yaml")
    # the given-registration block of the page, in place of the example's fitted one
    given_yaml = MAPPING.replace("registration: {fit_offset: false}\n", "") + blocks[1]
    (tmp_path / "given.yaml").write_text(given_yaml, encoding="utf-8")
    reg = load_mapping(tmp_path / "given.yaml").registration
    assert (reg.transform, reg.transform_unit, reg.transform_maps) == ("{stem}_trafo.txt", "mm", "instrument_to_robot")


def test_row_join_with_skip_bad_drops_the_row_whose_joints_are_bad(tmp_path):
    q, err = _files(tmp_path)
    jt = tmp_path / "m_joints.csv"
    lines = jt.read_text(encoding="utf-8").splitlines()
    cells = lines[3].split(";")
    lines[3] = ";".join([cells[0], "n/a", *cells[2:]])  # data row 3 of the joints: a bad cell
    jt.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(DataError, match=r"m_joints.csv: line 4: column 'J1': value 'n/a'"):
        import_file(tmp_path / "m.csv", _mapping("row"), robot=UR10)
    ds, _ = import_file(tmp_path / "m.csv", _mapping("row"), robot=UR10, skip_bad=True)
    assert ds.n == 11 and [(s.line, s.column) for s in ds.skipped] == [(4, "<joints>")]
    np.testing.assert_allclose(ds.error, np.delete(err, 2, axis=0), atol=1e-9)
