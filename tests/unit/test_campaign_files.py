"""Campaign files round-trip exactly and refuse the usual unit slips and another robot's files;
the twin-side inverse kinematics that a deployed joint-space map needs."""
import numpy as np
import pytest

from dt_kernel.errors import DataError, UnreachableError
from dt_runtime.analysis.crossval import folds_of
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.measurements.campaign_files import check_robot, read_phase, write_phase
from dt_runtime.measurements.phase import PhaseData

COBOT = load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")
UR10 = load_robot(CONFIGS / "robots" / "ur10.yaml")


def _phase(n=12, seed=0, registration=False, truth=True):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.8, 0.8, (n, 6)) + np.array([0, 0.4, 0.8, 0, 0.6, 0])
    p = COBOT.fk(q)
    lt = p + rng.normal(0, 1e-4, (n, 3)) + [2.0, 0.1, -0.3]
    mvs = p + rng.normal(0, 1e-4, (n, 3))
    mvs[3] = np.nan  # a refused reading
    return PhaseData("doe", np.arange(n) % 4, np.arange(n) // 4, p.copy(), rng.uniform(0.1, 1.0, n), p, lt, mvs,
                     np.cumsum(rng.uniform(1, 5, n)), q, 20 + rng.normal(0, 1, n), np.full(n, 5.0),
                     truth_lt=lt - 1e-5 if truth else None,
                     axis=np.array(list("xyz" * (n // 3)), dtype=object) if registration else None,
                     distance=np.tile([0.025, 0.05, 0.075], n // 3) if registration else None)


def test_a_phase_round_trips(tmp_path):
    d = _phase(registration=True)
    back = read_phase(write_phase(tmp_path / "r.csv", d), "registration", registration=True)
    for f in ("target", "p_rdk", "p_lt", "truth_lt", "q", "speed", "temperature", "payload", "t", "distance"):
        assert np.allclose(getattr(back, f), getattr(d, f), rtol=0, atol=1e-12), f
    assert np.isnan(back.p_mvs[3]).all() and np.allclose(np.delete(back.p_mvs, 3, 0), np.delete(d.p_mvs, 3, 0),
                                                         atol=1e-12)
    assert list(back.axis) == list(d.axis) and back.refusals == []
    assert back.point_id.dtype.kind == "i" and np.array_equal(back.point_id, d.point_id)
    assert np.array_equal(back.rep, d.rep) and back.q.shape == (12, 6)
    assert not (tmp_path / "r.csv.part").exists()
    check_robot(back, COBOT, "r.csv")  # consistent


def test_integer_point_ids_group_and_fold_as_in_memory(tmp_path):
    """A twin from the files equals the in-memory one: ids read as text would sort '10' < '2'
    and give other seeded cross-validation folds."""
    d = _phase(n=60)
    d.point_id = np.arange(60) % 20
    back = read_phase(write_phase(tmp_path / "doe.csv", d), "doe")
    for a, b in zip(folds_of(back.point_id, 5, 3), folds_of(d.point_id, 5, 3)):
        assert np.array_equal(a, b)
    d.point_id = np.array([f"P{i}" for i in range(60)])  # named points stay text
    assert list(read_phase(write_phase(tmp_path / "named.csv", d), "doe").point_id) == list(d.point_id)


def test_without_truth_and_optional_columns(tmp_path):
    back = read_phase(write_phase(tmp_path / "doe.csv", _phase(truth=False)), "doe")
    assert back.truth_lt is None and "truth_lt" not in (tmp_path / "doe.csv").read_text()
    p = tmp_path / "min.csv"
    p.write_text("x,y,z,speed,lt_x,lt_y,lt_z\n850,-120,450,250,2841.2,-112.6,151.9\n"
                 "800,100,500,100,2791.5,107.1,201.0\n")
    m = read_phase(p, "doe")
    assert np.allclose(m.p_rdk[0], [0.85, -0.12, 0.45], rtol=0, atol=1e-15) and np.array_equal(m.target, m.p_rdk)
    assert np.allclose(m.speed, [0.25, 0.1], rtol=0, atol=1e-15)
    assert list(m.point_id) == [1, 2] and list(m.rep) == [0, 0] and m.q.shape == (2, 0)
    for f in ("t", "temperature", "payload"):
        assert np.isnan(getattr(m, f)).all(), f
    assert np.isnan(m.p_mvs).all() and m.truth_lt is None and m.axis is None
    check_robot(m, UR10, "min.csv")  # no joints: nothing to check


def _edit(path, col, fn):
    lines = path.read_text().splitlines()
    head = lines[0].split(",")
    k = head.index(col)
    out = [lines[0]]
    for ln in lines[1:]:
        cells = ln.split(",")
        cells[k] = fn(cells[k])
        out.append(",".join(cells))
    path.write_text("\n".join(out) + "\n")


@pytest.mark.parametrize("col, fn, message", [
    ("x", lambda v: "", "empty cell"),
    ("speed", lambda v: "-1", "speed must be > 0"),
    ("payload", lambda v: "-2", "payload must be >= 0"),
    ("speed", lambda v: "", "empty cell"),
    ("q2", lambda v: str(float(v) * 57.3 + 90), "degrees"),
    ("axis", lambda v: "w", "x, y, z"),
])
def test_bad_cells_name_file_and_column(tmp_path, col, fn, message):
    p = write_phase(tmp_path / "doe.csv", _phase(registration=True))
    _edit(p, col, fn)
    with pytest.raises(DataError, match=message) as e:
        read_phase(p, "doe", registration=col == "axis")
    assert "doe.csv" in str(e.value) and f"column '{col}'" in str(e.value) and "line 2" in str(e.value)


def test_an_empty_measurement_cell_is_a_refused_reading(tmp_path):
    p = write_phase(tmp_path / "doe.csv", _phase())
    _edit(p, "lt_y", lambda v: "")
    back = read_phase(p, "doe")
    assert np.isnan(back.p_lt[:, 1]).all() and np.isfinite(back.p_lt[:, [0, 2]]).all()


@pytest.mark.parametrize("drop", ["lt_y", "speed", "x"])
def test_a_missing_required_column_is_named(tmp_path, drop):
    p = write_phase(tmp_path / "doe.csv", _phase())
    _edit(p, drop, lambda v: v)
    p.write_text(p.read_text().replace(f",{drop},", ",other,", 1))
    with pytest.raises(DataError, match="missing column") as e:
        read_phase(p, "doe")
    assert "doe.csv" in str(e.value) and f"'{drop}'" in str(e.value)


def test_joint_columns_with_a_gap(tmp_path):
    p = write_phase(tmp_path / "doe.csv", _phase())
    p.write_text(p.read_text().replace(",q3,", ",q7,", 1))
    with pytest.raises(DataError, match="q1 to qN") as e:
        read_phase(p, "doe")
    assert "doe.csv" in str(e.value) and "q7" in str(e.value)


def test_metres_in_a_mm_file_and_missing_columns(tmp_path):
    p = write_phase(tmp_path / "doe.csv", _phase())
    for c in "xyz":
        _edit(p, c, lambda v: str(float(v) / 1000))
    with pytest.raises(DataError, match="looks like metres") as e:
        read_phase(p, "doe")
    assert "doe.csv" in str(e.value) and "x, y, z" in str(e.value) and "mm" in str(e.value)
    with pytest.raises(DataError, match="axis"):
        read_phase(write_phase(tmp_path / "r.csv", _phase()), "registration", registration=True)


@pytest.mark.parametrize("wrong, right", [("temprature", "temperature"), ("mvs x", "mvs_x"), ("Payload", "payload")])
def test_a_misspelled_campaign_column_is_refused_naming_it(tmp_path, wrong, right):
    p = write_phase(tmp_path / "doe.csv", _phase())
    head, rest = p.read_text().split("\n", 1)
    p.write_text(",".join(wrong if c == right else c for c in head.split(",")) + "\n" + rest)
    with pytest.raises(DataError, match=f"column '{wrong}' is not a contract column but looks like '{right}'") as e:
        read_phase(p, "doe")
    assert "doe.csv: line 1" in str(e.value) and "campaign-files.md" in str(e.value)


def test_files_of_another_robot(tmp_path):
    back = read_phase(write_phase(tmp_path / "doe.csv", _phase()), "doe")
    with pytest.raises(DataError, match=r"doe\.csv.*robot config ur10.* by [0-9.]+ mm.*another robot"):
        check_robot(back, UR10, "doe.csv")
    back.q = np.degrees(back.q)  # joints in other units: the robot's own config refuses them too
    with pytest.raises(DataError, match="q columns look like degrees"):
        check_robot(back, COBOT, "doe.csv")


@pytest.mark.parametrize("chain", [COBOT, UR10], ids=["cobot", "ur10"])
def test_ik_reaches_the_position_on_the_seeds_branch(chain):
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.uniform(-1.0, 1.0, chain.dof) + np.array([0, -0.5, 1.0, 0, 0.8, 0])[: chain.dof]
        p, R = chain.pose(q)
        if np.linalg.norm(p[:2]) < 0.3:  # near the base axis: a singular region no work target lies in
            continue
        seed = q + rng.normal(0, 0.03, chain.dof)
        sol = chain.ik(p, seed, R)
        assert np.linalg.norm(chain.fk(sol)[0] - p) < 1e-9
        assert np.max(np.abs(sol - q)) < 1e-6  # the seed's branch: the same configuration
        kept = chain.ik(p, seed)  # default: a linear move keeps the tool's orientation at the seed
        assert np.linalg.norm(chain.fk(kept)[0] - p) < 1e-9
        assert np.allclose(chain.pose(kept)[1], chain.pose(seed)[1], atol=1e-9)
    with pytest.raises(UnreachableError, match="mm"):
        chain.ik(np.array([10.0, 0.0, 0.0]), q)
    with pytest.raises(DataError):
        chain.ik(np.array([np.nan, 0.0, 0.0]), q)
