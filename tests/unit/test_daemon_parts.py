"""The daemon's parts on their own (issue 23, item 8): the target sources, and the one set of
counters that `.../health` and the summary read."""
import numpy as np

from dt_runtime.programs.program import Program
from dt_runtime.service.counters import Counters
from dt_runtime.service.runtime_config import PathConfig
from dt_runtime.service.targets import CircleTargets, ProgramTargets, RandomTargets, probe_point, targets_for


def _program() -> Program:
    return Program(target=np.array([[0.8, 0.0, 0.5], [0.9, 0.1, 0.6], [1.0, -0.1, 0.4]]),
                   speed=np.array([0.1, 0.2, 0.3]), point_id=["a", "b", "c"], line=[2, 3, 4])


def test_the_program_is_commanded_row_after_row_and_repeated():
    src = targets_for(PathConfig(kind="program", program="p.csv"), _program(), max_speed=1.0, rate_hz=10.0)
    assert isinstance(src, ProgramTargets)
    got = [src.next() for _ in range(7)]
    assert [t.step for t in got] == [0, 1, 2, 0, 1, 2, 0]
    assert [t.speed for t in got[:3]] == [0.1, 0.2, 0.3]
    assert np.array_equal(got[4].position, [0.9, 0.1, 0.6])
    assert np.array_equal(probe_point(PathConfig(kind="program", program="p.csv"), _program()), [0.8, 0.0, 0.5])


def test_the_circle_streams_set_points_v_over_rate_apart():
    pc = PathConfig(kind="circle", speeds=(0.25,), circle_radius_m=0.15, circle_center_m=(0.9, 0.0, 0.55))
    src = targets_for(pc, None, max_speed=1.2, rate_hz=500.0)
    assert isinstance(src, CircleTargets)
    pts = [src.next() for _ in range(1000)]
    v = 0.25 * 1.2
    assert all(t.speed == v and t.step is None for t in pts)
    P = np.array([t.position for t in pts])
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert np.allclose(steps, v / 500.0, rtol=1e-6)  # chord of a 0.6 mm arc on a 150 mm circle
    assert np.allclose(np.linalg.norm(P[:, :2] - [0.9, 0.0], axis=1), 0.15) and np.all(P[:, 2] == 0.55)
    assert np.array_equal(probe_point(pc, None), [0.9, 0.0, 0.55])


def test_random_targets_are_seeded_in_the_box():
    pc = PathConfig(kind="random", seed=7, speeds=(0.4, 0.8))
    a, b = RandomTargets(pc, 1.0), RandomTargets(pc, 1.0)
    ta, tb = [a.next() for _ in range(50)], [b.next() for _ in range(50)]
    assert all(np.array_equal(x.position, y.position) and x.speed == y.speed for x, y in zip(ta, tb))
    P = np.array([t.position for t in ta])
    assert np.all(P >= pc.box_min_m) and np.all(P <= pc.box_max_m)
    assert {t.speed for t in ta} == {0.4, 0.8}
    rng = np.random.default_rng(7)  # the draws the daemon always made: position, then speed
    first = rng.uniform(np.array(pc.box_min_m), np.array(pc.box_max_m))
    assert np.array_equal(ta[0].position, first) and ta[0].speed == float(rng.choice(pc.speeds))


def test_health_and_summary_read_the_same_counters():
    n = Counters()
    assert not n.in_trouble()
    n.ticked()
    n.ticked()
    n.refused, n.refused_in_row, n.mvs_refused, n.stale_measurements, n.failures = 3, 2, 4, 1, 5
    n.camera_refused_since = 10.0
    s, h = n.summary(), n.health(now=12.5)
    assert list(s) == ["ticks", "t_test_failures", "refused_commands", "driver_faults", "uncorrected_commands",
                       "stale_measurements", "mvs_refused"]
    assert list(h) == ["last_tick", "ticks", "refused_in_row", "driver_faults_in_row", "stale_measurements",
                       "mvs_refused", "mvs_refused_in_row", "camera_untested_s"]
    assert s["ticks"] == h["ticks"] == 2 and s["mvs_refused"] == h["mvs_refused"] == 4
    assert s["stale_measurements"] == h["stale_measurements"] == 1
    assert s["refused_commands"] == 3 and s["t_test_failures"] == 5 and h["refused_in_row"] == 2
    assert h["camera_untested_s"] == 2.5 and h["last_tick"] is not None
    assert n.in_trouble()
