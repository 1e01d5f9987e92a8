import numpy as np
import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.measurements.plans import PlanConfig, build_plan, doe_points, load_plan


def test_doe_geometry_matches_the_paper():
    cfg = PlanConfig(registration_speed=1.0)
    pts = doe_points(cfg)
    assert len(pts) == 62 and len(np.unique(pts.round(9), axis=0)) == 62
    planes = [pts[np.isclose(pts[:, 2], z)] for z in (0.9, 0.55, 0.2)]
    assert [len(p) for p in planes] == [9, 13, 26]
    assert len(pts) - sum(len(p) for p in planes) == 14  # on the connecting lines
    assert np.diff(sorted([0.9, 0.55, 0.2])).tolist() == pytest.approx([0.35, 0.35])
    # Sides at 150 mm: every perimeter point has a neighbour 150 mm away in its plane.
    for p in planes:
        d = np.linalg.norm(p[:, None] - p[None], axis=2) + np.eye(len(p))
        assert np.all(d.min(axis=1) <= 0.15 + 1e-9)
    areas = [np.ptp(p[:, 0]) * np.ptp(p[:, 1]) for p in planes]
    assert areas[0] < areas[1] < areas[2]


def test_plan_phases_counts_and_randomised_orders():
    plan = build_plan(PlanConfig(registration_speed=1.0))
    assert len(plan.registration) == 120 and len(plan.doe) == 62 * 3 * 9
    assert len(plan.validation) == 140
    orders = [tuple((r.point_id, r.speed_frac) for r in plan.doe[k * 186:(k + 1) * 186]) for k in range(9)]
    assert len(set(orders)) == 9  # each replication its own path
    assert sorted(orders[0]) == sorted(orders[1])
    v = np.array([r.speed_frac for r in plan.validation])
    assert (v == 0.8).sum() == 70 and (v == 0.4).sum() == 70
    dmin = np.min(np.linalg.norm(plan.validation_points[:, None] - plan.doe_points[None], axis=2))
    assert dmin >= 0.06


def test_same_seed_same_plan():
    a = build_plan(PlanConfig(registration_speed=1.0, seed=4))
    b = build_plan(PlanConfig(registration_speed=1.0, seed=4))
    assert all(np.array_equal(x.target, y.target) for x, y in zip(a.doe, b.doe))


def test_bad_speed_names_file_key_value(tmp_path):
    f = tmp_path / "plan.yaml"
    f.write_text("registration_speed: 1.0\ndoe_speeds: [0.3, 1.5]\n")
    with pytest.raises(ConfigError) as ei:
        load_plan(f)
    m = str(ei.value)
    assert "plan.yaml" in m and "doe_speeds" in m and "1.5" in m and "(0, 1]" in m
